#!/bin/sh
# Run a Cortex-M link (the command after the first four arguments) and, if the image overflows the part's
# memory, refuse it in one line on stderr, exit status 2: the image, and each overflowed region's bytes
# needed against the bytes the part has (from the linker's "region `X' overflowed by N bytes"). Any other
# failure passes through with the linker's own messages and status.
#   fit.sh <target> <part> <flash KiB> <ram KiB> <link command...>
target=$1 part=$2 flash_kib=$3 ram_kib=$4
shift 4
image= previous=
for arg in "$@"; do
    [ "$previous" = -o ] && image=${arg##*/}
    previous=$arg
done
err=$("$@" 2>&1) && { [ -z "$err" ] || printf '%s\n' "$err" >&2; exit 0; }
status=$?
regions=$(printf '%s\n' "$err" | sed -n "s/.*region [\`']\{0,1\}\([A-Z]*\)'\{0,1\} overflowed by \([0-9]*\) bytes.*/\1 \2/p" | sort -u)
if [ -z "$regions" ]; then
    printf '%s\n' "$err" >&2
    exit "$status"
fi
line=$(printf '%s\n' "$regions" | while read -r region over; do
    case $region in FLASH) have=$((flash_kib * 1024)) ;; *) have=$((ram_kib * 1024)) ;; esac
    printf '%s %d bytes needed, %d available; ' "$region" $((have + over)) "$have"
done)
echo "$target ($part): $image does not fit the part's memory: ${line%; }" >&2
exit 2
