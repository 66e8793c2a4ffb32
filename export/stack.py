"""The static worst-case stack of a Cortex-M image, from GCC's own accounting and the linked code.

Each function compiled by ``runtime_c`` brings its frame from ``-fstack-usage`` and its calls from
``-fcallgraph-info=su`` (the ``<image>-<source>.ci`` files beside the ELF). What the image links from
newlib and libgcc (``tanhf``, ``memcpy``, soft-float helpers) was compiled without them: its frames and
calls are read from the linked image's disassembly (every push, vpush and ``sub sp`` of the function,
summed, which bounds any one path through it; every ``bl`` and tail branch). The bound of a root is its
frame plus the deepest bound among its callees.

What cannot be bounded is an error, never a guess: recursion, a frame GCC calls dynamic and unbounded, a
``sub sp`` by a register, an indirect call or jump out of a function, a callee found nowhere.
"""

from __future__ import annotations

import bisect
import re
import subprocess
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from embedrl.export.errors import ExportError

EXCEPTION_FRAME_BYTES = 32 + 4
"""What the core pushes on entering an interrupt without floating-point context: 8 words, plus up to one
word of alignment padding (ARMv7-M Architecture Reference Manual, B1.5.7)."""
EXCEPTION_FRAME_FP_BYTES = 104 + 4
"""The same with the floating-point context (26 words: S0-S15, FPSCR and a reserved word) on a core with
an FPU, where lazy stacking reserves the space on every entry."""
OBJDUMP = "arm-none-eabi-objdump"
GCC_INDIRECT_CALL = "__indirect_call"
"""The callee GCC's call graph names for a call through a pointer."""

_CI_NODE = re.compile(r'node: \{ title: "([^"]+)" label: "([^"]*)"')
_CI_EDGE = re.compile(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"')
_CI_BYTES = re.compile(r"\\n(\d+) bytes \(([a-z,]+)\)")
_FUNCTION = re.compile(r"^([0-9a-f]+) <([^>]+)>:$")
_INSN = re.compile(r"^\s+[0-9a-f]+:\s+(\S+)\s*(.*)$")
_ADDRESS = re.compile(r"(?:^|[ ,])([0-9a-f]+) <")
_REGISTER_LIST = re.compile(r"\{([^}]*)\}")
_BRANCHES = {"b", "b.n", "b.w", "beq", "bne", "bcs", "bcc", "bmi", "bpl", "bhi", "bls", "bge", "blt", "bgt",
             "ble", "bvs", "bvc", "bhs", "blo", "cbz", "cbnz"}  # fmt: skip


class StackError(ExportError):
    """The image's stack cannot be bounded (recursion, a dynamic frame, an unknown or indirect callee)."""


@dataclass(frozen=True)
class Function:
    frame: int
    """Bytes this function's own frame takes."""
    calls: frozenset[str]
    source: str
    """``gcc`` (its ``.su``/``.ci``) or ``disassembly`` (linked library code)."""
    problem: str = ""
    """Why the function cannot be bounded (raised only if a root reaches it)."""


@dataclass(frozen=True)
class Bound:
    root: str
    bytes: int
    path: tuple[str, ...]
    """The deepest call chain, root first."""

    def to_json(self) -> dict[str, object]:
        return {"bytes": self.bytes, "deepest_path": list(self.path)}


def call_graph(elf: Path) -> dict[str, Function]:
    """Every function reachable in the image: GCC's records for ``runtime_c``'s code (the ``.ci`` files
    named after ``elf``), the disassembly of ``elf`` for what they call and was not compiled here
    (callers the linker dropped keep their edges; only what a root reaches matters)."""
    graph = _from_gcc(sorted(elf.parent.glob(f"{elf.name}-*.ci")))
    if not graph:
        raise StackError(f"no call-graph files beside {elf.name}: build it with -fcallgraph-info=su")
    missing = {c for f in graph.values() for c in f.calls} - graph.keys()
    if missing:
        linked = _from_disassembly(elf)
        graph.update({name: linked[name] for name in missing if name in linked})
        graph.update({name: f for name, f in linked.items() if name not in graph})
    return graph


def bound(graph: dict[str, Function], root: str) -> Bound:
    """The worst-case stack of ``root`` and everything it calls."""
    memo: dict[str, tuple[int, tuple[str, ...]]] = {}

    def walk(name: str, chain: tuple[str, ...]) -> tuple[int, tuple[str, ...]]:
        if name == GCC_INDIRECT_CALL:
            raise StackError(f"an indirect call (through a function pointer) in {chain[-1]}")
        if name not in graph:
            caller = f" (called by {chain[-1]})" if chain else ""
            raise StackError(f"unknown callee {name}{caller}: neither compiled here nor in the image")
        if name in chain:
            raise StackError(f"recursion: {' -> '.join((*chain[chain.index(name) :], name))}")
        if graph[name].problem:
            raise StackError(graph[name].problem)
        if name not in memo:
            deepest: tuple[int, tuple[str, ...]] = (0, ())
            for callee in sorted(graph[name].calls):
                deepest = max(deepest, walk(callee, (*chain, name)), key=lambda d: d[0])
            memo[name] = (graph[name].frame + deepest[0], (name, *deepest[1]))
        return memo[name]

    total, path = walk(root, ())
    return Bound(root, total, path)


def _from_gcc(files: list[Path]) -> dict[str, Function]:
    frames: dict[str, tuple[int, str]] = {}
    calls: dict[str, set[str]] = {}
    for path in files:
        text = path.read_text()
        for title, label in _CI_NODE.findall(text):
            found = _CI_BYTES.search(label)
            if found is None:
                continue  # a callee defined elsewhere
            size, kind = int(found.group(1)), found.group(2)
            if "dynamic" in kind and "bounded" not in kind:
                raise StackError(f"{title}: a dynamic stack frame ({path.name})")
            frames[title] = (size, path.name)
        for source, target in _CI_EDGE.findall(text):
            calls.setdefault(source, set()).add(target)
    return {name: Function(size, frozenset(calls.get(name, ())), "gcc") for name, (size, _) in frames.items()}


def _from_disassembly(elf: Path) -> dict[str, Function]:
    """Every function of the linked image by each of its names (aliases such as ``__aeabi_fadd`` and
    ``__addsf3`` share one body); calls resolved by address, since objdump names an address after the
    nearest symbol of any kind."""
    text = _tool(OBJDUMP, "-d", "--no-show-raw-insn", str(elf))
    bodies: list[tuple[int, str, list[tuple[str, str]]]] = []
    for line in text.splitlines():
        header = _FUNCTION.match(line)
        if header:
            bodies.append((int(header.group(1), 16), header.group(2), []))
            continue
        insn = _INSN.match(line)
        if bodies and insn:
            bodies[-1][2].append((insn.group(1), insn.group(2)))
    starts = [start for start, _, _ in bodies]

    def owner(address: int) -> str:
        return bodies[max(0, bisect.bisect_right(starts, address) - 1)][1]

    functions = {name: _function(name, insns, owner) for _, name, insns in bodies}
    for symbol, address in _text_symbols(elf).items():
        functions.setdefault(symbol, functions[owner(address)])
    return functions


def _text_symbols(elf: Path) -> dict[str, int]:
    symbols = {}
    for line in _tool("arm-none-eabi-nm", "--defined-only", str(elf)).splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[1] in "TtWw":
            symbols[parts[2]] = int(parts[0], 16) & ~1  # the Thumb bit
    return symbols


def _tool(*cmd: str) -> str:
    try:
        return subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        raise StackError(f"{cmd[0]} could not read {Path(cmd[-1]).name}: {exc}") from None


def _function(name: str, insns: list[tuple[str, str]], owner: Callable[[int], str]) -> Function:
    """A disassembled function: its pushes summed (a bound for any path), its calls, its first problem."""
    frame, calls, problem = 0, set(), ""
    for mnemonic, operands in insns:
        frame += _pushed(mnemonic, operands)
        if mnemonic.startswith("sub") and operands.startswith("sp") and "#" not in operands:
            problem = problem or f"{name}: the stack pointer moved by a register (a dynamic frame)"
        kind = _transfer(mnemonic, operands)
        if kind == "indirect":
            problem = (
                problem or f"{name}: an indirect call or jump ({mnemonic} {operands.split(';')[0].strip()})"
            )
        elif kind:
            target = owner(int(kind, 16))
            if target != name:
                calls.add(target)  # a call, or a branch into another function (a tail call)
    return Function(frame, frozenset(calls), "disassembly", problem)


def _pushed(mnemonic: str, operands: str) -> int:
    """Bytes an instruction moves the stack pointer down by."""
    registers = _REGISTER_LIST.search(operands)
    mnemonic = mnemonic.split(".")[0]
    if mnemonic == "push" or (mnemonic.startswith("stmdb") and operands.startswith("sp!")):
        return 4 * _count(registers.group(1)) if registers else 0
    if mnemonic in ("vpush", "vstmdb") and (mnemonic == "vpush" or operands.startswith("sp!")):
        if not registers:
            return 0
        width = 8 if registers.group(1).strip().startswith("d") else 4
        return width * _count(registers.group(1))
    if mnemonic.startswith("sub") and re.match(r"sp, (sp, )?#\d+", operands):
        return int(operands.split("#")[1].split()[0])
    if mnemonic.startswith("str") and re.search(r"\[sp, #-(\d+)\]!", operands):
        return int(re.search(r"\[sp, #-(\d+)\]!", operands).group(1))  # type: ignore[union-attr]
    return 0


def _count(registers: str) -> int:
    """Registers in a list such as ``r4, r5, r6-r8, lr`` or ``d8-d11``."""
    total = 0
    for item in (r.strip() for r in registers.split(",")):
        if "-" in item:
            low, high = (int(re.sub(r"\D", "", r)) for r in item.split("-"))
            total += high - low + 1
        elif item:
            total += 1
    return total


def _transfer(mnemonic: str, operands: str) -> str:
    """The hex address a call or branch goes to; "indirect" for a call or jump through a register or
    memory; "" for anything else (a return included)."""
    base = mnemonic.split(".")[0]
    if base in _BRANCHES or base in ("bl", "blx"):
        address = _ADDRESS.search(operands)
        return address.group(1) if address else "indirect"
    if base == "ldr" and operands.startswith("pc, [sp]"):
        return ""  # a return: the saved lr popped into pc
    if (base == "bx" and not operands.startswith("lr")) or (
        base.startswith(("mov", "ldr")) and operands.startswith("pc")
    ):
        return "indirect"
    return ""


NODE_INTERRUPTS = ("LinkRx_Handler", "SysTick_Handler")
"""The firmware node's interrupt handlers (runtime_c/cortex_m/startup.c); they share one priority, so
one never preempts another."""


def policy_bound(elf: Path) -> dict[str, object]:
    """``policy_step``'s worst case in an image built by ``runtime_c`` (the firmware test image)."""
    return bound(call_graph(elf), "policy_step").to_json()


def node_bound(elf: Path, fpu: bool) -> dict[str, object]:
    """The firmware node's worst case: ``main`` (its loop: frames in, the policy, frames out) plus the
    deepest interrupt handler with the exception frame the core pushes for it (with the floating-point
    context on a core with an FPU). The start-up code before ``main`` and its exit are not a cycle."""
    graph = call_graph(elf)
    main = bound(graph, "main")
    handlers = [bound(graph, name) for name in NODE_INTERRUPTS if name in graph]
    deepest = max(handlers, key=lambda b: b.bytes, default=None)
    frame = EXCEPTION_FRAME_FP_BYTES if fpu else EXCEPTION_FRAME_BYTES
    interrupt = 0 if deepest is None else deepest.bytes + frame
    return {
        "bytes": main.bytes + interrupt,
        "main": main.to_json(),
        "interrupt": None
        if deepest is None
        else {"handler": deepest.root, "bytes": deepest.bytes, "exception_frame_bytes": frame},
    }
