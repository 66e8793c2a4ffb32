"""Cache a User-Mode Linux kernel that runs on CPUs where Debian stable's does not (``make deps``).

Debian bookworm's UML 6.1 dies at its first process on hosts whose CPU has AMX; UML 7.2 runs there.
7.2 is only in Debian's newer suites and needs glibc >= 2.38, so it is fetched without installing
anything system-wide:

1. a private apt configuration (own sources list and package lists under ``<cache>/apt/<suite>``,
   signed by Debian's archive key) asks the suite for ``user-mode-linux`` and a matching ``libc6``;
2. both .deb files are downloaded and checked against the SHA-256 of the signed package index;
3. they are unpacked into ``<cache>/uml/<version>/root`` and a copy of the UML binary is pointed at
   that libc with ``patchelf`` (running it through the loader instead makes UML miscompute its memory);
4. the kernel must boot and pass the sandbox self-test (vcan0, an AF_CAN round trip) on this machine;
   only then is ``manifest.json`` written (the files, versions, URLs and SHA-256), which marks the
   cache as complete.

Run as ``python -m embedrl.hil.sandbox.provision [--suite sid] [--refresh] [--force]``: with a kernel cached
already it does nothing (no network) unless asked to. Standard library only, so the
system Python runs it before the project is installed. Fails (exit 1) only if no UML kernel would
work on this machine afterwards: where Debian's packaged UML passes its self-test, a failed download
is a warning.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from embedrl.common import owned_temporary_folder
from embedrl.hil.sandbox import check
from embedrl.hil.sandbox.uml import (
    MANIFEST,
    UmlKernel,
    UmlProvider,
    cache_root,
    cached_kernels,
    packaged_kernel,
)

MIRROR = "http://deb.debian.org/debian"
KEYRING = "/usr/share/keyrings/debian-archive-keyring.gpg"
DEFAULT_SUITE = "sid"
PACKAGES = ("user-mode-linux", "libc6")
LIBDIR = "usr/lib/x86_64-linux-gnu"
LOADER = f"{LIBDIR}/ld-linux-x86-64.so.2"
UML_BINARY = "usr/bin/linux.uml"
MODULES = "usr/lib/uml/modules"
DOWNLOAD_TIMEOUT_S = 300


class ProvisionError(Exception):
    """A step of fetching, unpacking, patching or verifying the kernel failed."""


@dataclass(frozen=True)
class Deb:
    package: str
    url: str
    file: str
    size: int
    sha256: str


def _run(argv: list[str], cwd: Path | None = None) -> str:
    try:
        done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True)
    except FileNotFoundError:
        raise ProvisionError(f"`{argv[0]}` is not installed (Debian apt, dpkg, patchelf)") from None
    if done.returncode != 0:
        said = (done.stderr or done.stdout).strip().splitlines()
        raise ProvisionError(f"`{' '.join(argv[:3])} ...` failed: {said[-1] if said else done.returncode}")
    return done.stdout


def resolve(suite: str, apt_dir: Path) -> list[Deb]:
    """The suite's current .deb files for :data:`PACKAGES`, with the signed index's SHA-256."""
    (apt_dir / "lists" / "partial").mkdir(parents=True, exist_ok=True)
    (apt_dir / "cache" / "archives" / "partial").mkdir(parents=True, exist_ok=True)
    sources = apt_dir / "sources.list"
    sources.write_text(f"deb [signed-by={KEYRING}] {MIRROR} {suite} main\n")
    options = [
        "-o", f"Dir::Etc::sourcelist={sources}",
        "-o", "Dir::Etc::sourceparts=-",
        "-o", f"Dir::State::Lists={apt_dir / 'lists'}",
        "-o", f"Dir::Cache={apt_dir / 'cache'}",
        "-o", "Debug::NoLocking=1",
        "-o", "APT::Get::List-Cleanup=0",
    ]  # fmt: skip
    _run(["apt-get", *options, "-q", "update"])
    printed = _run(["apt-get", *options, "--print-uris", "download", *PACKAGES])
    debs = []
    for line in printed.splitlines():
        fields = line.split()
        if len(fields) != 4 or not fields[3].startswith("SHA256:"):
            continue
        url, file = fields[0].strip("'"), fields[1]
        debs.append(Deb(file.split("_")[0], url, file, int(fields[2]), fields[3].removeprefix("SHA256:")))
    if sorted(d.package for d in debs) != sorted(PACKAGES):
        raise ProvisionError(f"the {suite} index does not offer {', '.join(PACKAGES)} for this machine")
    return debs


def download(deb: Deb, folder: Path) -> Path:
    """Fetch ``deb`` into ``folder`` and check its size and SHA-256 against the index."""
    path = folder / deb.file
    digest = hashlib.sha256()
    with urllib.request.urlopen(deb.url, timeout=DOWNLOAD_TIMEOUT_S) as response, path.open("wb") as out:
        while chunk := response.read(1 << 20):
            digest.update(chunk)
            out.write(chunk)
    if path.stat().st_size != deb.size or digest.hexdigest() != deb.sha256:
        raise ProvisionError(f"{deb.file}: size or SHA-256 differs from the signed package index")
    return path


def provision(suite: str = DEFAULT_SUITE, force: bool = False, say: Callable[[str], None] = print) -> Path:
    """Fetch, unpack, patch and verify the suite's UML; the cached folder (reused if complete)."""
    cache = cache_root()
    debs = resolve(suite, cache / "apt" / suite)
    uml_deb = next(d for d in debs if d.package == "user-mode-linux")
    version = uml_deb.file.split("_")[1].replace("%3a", ":")
    target = cache / "uml" / version
    if (target / MANIFEST).is_file() and not force:
        say(f"User-Mode Linux {version} ({suite}) is already cached in {target}")
        return target
    shutil.rmtree(target, ignore_errors=True)  # an earlier attempt that never completed
    root = target / "root"
    root.mkdir(parents=True)
    with owned_temporary_folder("embedrl-debs-") as tmp:
        for deb in debs:
            say(f"downloading {deb.url} ({deb.size / 1e6:.1f} MB)")
            _run(["dpkg-deb", "-x", str(download(deb, Path(tmp))), str(root)])
    binary = target / "linux.uml"
    shutil.copy2(root / UML_BINARY, binary)
    _run(
        ["patchelf", "--set-interpreter", str(root / LOADER), "--set-rpath", str(root / LIBDIR), str(binary)]
    )
    releases = sorted(p.name for p in (root / MODULES).iterdir())
    kernel = UmlKernel(binary, root / MODULES, f"{version}, cached")
    with owned_temporary_folder("embedrl-uml-check-") as tmp:
        result = check(UmlProvider(kernel), Path(tmp))
    if not result.works:
        raise ProvisionError(f"User-Mode Linux {version} does not work on this machine: {result.reason}")
    manifest = {
        "version": version,
        "suite": suite,
        "kernel_releases": releases,
        "binary": binary.name,
        "modules": str((root / MODULES).relative_to(target)),
        "debs": [
            {"package": d.package, "file": d.file, "url": d.url, "size": d.size, "sha256": d.sha256}
            for d in debs
        ],
        "verified": {"boot_s": result.boot_s, "self_test": result.reason},
    }
    tmp_manifest = target / f".{MANIFEST}.partial"
    tmp_manifest.write_text(json.dumps(manifest, indent=2) + "\n")
    tmp_manifest.rename(target / MANIFEST)
    say(f"User-Mode Linux {version} cached in {target}: {result.reason}")
    return target


def packaged_works() -> str | None:
    """The self-test result of Debian's packaged UML if it passes, else None."""
    kernel = packaged_kernel()
    if kernel is None:
        return None
    with owned_temporary_folder("embedrl-uml-check-") as tmp:
        result = check(UmlProvider(kernel), Path(tmp))
    return result.reason if result.works else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m embedrl.hil.sandbox.provision", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--suite", default=DEFAULT_SUITE, help="the Debian suite to take UML from")
    parser.add_argument(
        "--refresh", action="store_true", help="ask the suite for a newer version even if one is cached"
    )
    parser.add_argument("--force", action="store_true", help="download again even if cached")
    args = parser.parse_args(argv)
    cached = cached_kernels()
    if cached and not (args.refresh or args.force):
        print(
            f"User-Mode Linux {cached[0].origin} in {cached[0].binary.parent} "
            "(--refresh looks for a newer one)"
        )
        return 0
    try:
        provision(args.suite, args.force)
    except (ProvisionError, OSError) as exc:
        fallback = packaged_works()
        if fallback is None:
            print(f"error: no User-Mode Linux kernel works on this machine: {exc}", file=sys.stderr)
            return 1
        print(f"warning: {exc}; Debian's packaged UML works here ({fallback})", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
