"""The static stack bound: GCC's frames and call graph, the linked library code's disassembly, and the
refusals (recursion, a dynamic frame, an indirect call, an unknown callee). Needs arm-none-eabi-gcc."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest

from embedrl.export import stack
from embedrl.export.stack import Function, StackError
from tests.export.test_targets import study_export  # noqa: F401  (the module-scoped fixture)

M4 = ["-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard"]
SOURCES = {
    "chain": """
        #include <string.h>
        volatile char sink[64];
        volatile size_t n = 8;
        __attribute__((noinline)) void leaf(const char *s) {
            char b[40];
            memcpy(b, s, n);
            sink[0] = b[n - 1];
        }
        __attribute__((noinline)) void middle(const char *s) {
            volatile char b[24];
            b[n] = s[0];
            leaf((const char *)sink);
            sink[1] = b[3];
        }
        int main(void) { char b[16] = "abc"; middle(b); return sink[0]; }
    """,
    "recursion": """
        __attribute__((noinline)) int fib(int n) { return n < 2 ? n : fib(n - 1) + fib(n - 2); }
        int main(void) { return fib(7); }
    """,
    "dynamic": """
        volatile int sink;
        __attribute__((noinline)) void use(volatile char *b, int n) { sink = b[n - 1]; }
        __attribute__((noinline)) void vla(int n) {
            volatile char b[n];
            for (int i = 0; i < n; ++i) b[i] = (char)i;
            use(b, n);
        }
        int main(void) { vla(sink + 3); return 0; }
    """,
    "pointer": """
        typedef int (*fn)(int);
        static int twice(int x) { return 2 * x; }
        volatile fn table[1] = {twice};
        int main(void) { return table[0](3); }
    """,
}


def _image(tmp_path: Path, name: str) -> Path:
    """``SOURCES[name]`` linked for the Cortex-M4 as runtime_c links its images, with the call graph."""
    source = tmp_path / f"{name}.c"
    source.write_text(SOURCES[name])
    elf = tmp_path / f"{name}.elf"
    subprocess.run(
        ["arm-none-eabi-gcc", *M4, "-O2", "-fstack-usage", "-fcallgraph-info=su", "--specs=nano.specs",
         "--specs=rdimon.specs", "-o", str(elf), str(source)],
        check=True, capture_output=True,
    )  # fmt: skip
    return elf


def _su_frames(tmp_path: Path) -> dict[str, int]:
    frames = {}
    for su in tmp_path.glob("*.su"):
        for line in su.read_text().splitlines():
            where, size, _ = line.split("\t")
            frames[where.rsplit(":", 1)[-1]] = int(size)
    return frames


def test_the_bound_is_the_deepest_chain_of_gcc_frames_and_the_library_code(tmp_path: Path) -> None:
    elf = _image(tmp_path, "chain")
    graph = stack.call_graph(elf)
    frames = _su_frames(tmp_path)
    result = stack.bound(graph, "main")
    assert result.path[:3] == ("main", "middle", "leaf")
    assert graph["memcpy"].source == "disassembly" and graph["main"].source == "gcc"
    own = frames["main"] + frames["middle"] + frames["leaf"]
    assert frames["leaf"] >= 40 and frames["middle"] >= 24  # the arrays are in the frames
    assert result.bytes == own + sum(graph[f].frame for f in result.path[3:])
    assert result.bytes >= own


@pytest.mark.parametrize(
    ("name", "said"),
    [
        ("recursion", "recursion: fib -> fib"),
        ("dynamic", "dynamic stack frame"),
        ("pointer", "indirect call"),
    ],
)
def test_what_cannot_be_bounded_is_refused(tmp_path: Path, name: str, said: str) -> None:
    elf = _image(tmp_path, name)
    with pytest.raises(StackError, match=said):
        stack.bound(stack.call_graph(elf), "main")


def test_an_unknown_callee_or_root_is_refused() -> None:
    graph = {"step": Function(16, frozenset({"helper"}), "gcc")}
    with pytest.raises(StackError, match="unknown callee helper \\(called by step\\)"):
        stack.bound(graph, "step")
    with pytest.raises(StackError, match="unknown callee main"):
        stack.bound(graph, "main")
    with pytest.raises(StackError, match="no call-graph files"):
        stack.call_graph(Path("/nonexistent/image.elf"))


@pytest.mark.parametrize(
    ("mnemonic", "operands", "pushed"),
    [
        ("push", "{r4, r5, r6, lr}", 16),
        ("push.w", "{r4, r5, r6, r7, r8, r9, sl, lr}", 32),
        ("stmdb", "sp!, {r4, r5, lr}", 12),
        ("vpush", "{d8-d10}", 24),
        ("vpush", "{s16-s17}", 8),
        ("sub", "sp, #20", 20),
        ("sub.w", "sp, sp, #1024", 1024),
        ("str.w", "lr, [sp, #-8]!", 8),
        ("add", "sp, #20", 0),
        ("ldr", "r3, [sp, #4]", 0),
    ],
)
def test_the_disassembly_counts_every_way_a_frame_grows(mnemonic: str, operands: str, pushed: int) -> None:
    assert stack._pushed(mnemonic, operands) == pushed


@pytest.mark.parametrize(
    ("mnemonic", "operands", "kind"),
    [
        ("bl", "2a4 <tanhf>", "2a4"),
        ("b.w", "3c0 <expm1f+0x10>", "3c0"),
        ("cbz", "r3, 1d0 <leaf+0x8>", "1d0"),
        ("blx", "r3", "indirect"),
        ("bx", "r2", "indirect"),
        ("bx", "lr", ""),
        ("ldr.w", "pc, [sp], #8", ""),
        ("ldr", "pc, [r3, #4]", "indirect"),
        ("pop", "{r4, pc}", ""),
    ],
)
def test_the_disassembly_follows_calls_and_refuses_indirect_ones(
    mnemonic: str, operands: str, kind: str
) -> None:
    assert stack._transfer(mnemonic, operands) == kind


@pytest.mark.slow
def test_the_export_reports_bounds_above_the_painted_stack(study_export: dict[str, Any]) -> None:  # noqa: F811
    for name, t in study_export["targets"].items():
        bound = t["stack_bound"]
        assert t["stack_bytes"] <= bound["bytes"] < 1024, name
        assert bound["deepest_path"][0] == "policy_step"
        node = t["node_firmware"]["stack_bound"]
        fp_frame = stack.EXCEPTION_FRAME_FP_BYTES if name == "cortex-m4" else stack.EXCEPTION_FRAME_BYTES
        assert node["interrupt"]["exception_frame_bytes"] == fp_frame
        assert node["bytes"] == node["main"]["bytes"] + node["interrupt"]["bytes"] + fp_frame
        assert node["main"]["bytes"] > bound["bytes"]  # the node's loop calls the policy
    assert json.dumps(study_export)  # the report stays JSON
