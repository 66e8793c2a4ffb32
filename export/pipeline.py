"""``embedrl export``: source -> ONNX -> C, verified, written atomically into one folder.

Everything is built in a staging folder beside the output and renamed into place only when
every step passed: on any failure the output folder is untouched (absent, or as it was).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from importlib import metadata
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import onnx

from embedrl import train
from embedrl.common import owned_temporary_folder, provenance, sha256, with_umask
from embedrl.export import (
    build,
    chain,
    cycles,
    full_integer,
    interpret,
    nan_check,
    qdq,
    quantize,
    stack,
    target,
    verify,
)
from embedrl.export.bounds import action_bounds, append_clamp, within
from embedrl.export.codegen import check_name, generate
from embedrl.export.contract import sources as can_sources
from embedrl.export.errors import ExportError, InvalidModelError, UnsupportedModelError, VerificationError
from embedrl.export.full_integer import Given, IntegerSection
from embedrl.export.interpret import Section
from embedrl.export.ir import Graph
from embedrl.export.onnx_import import Limits, load_onnx
from embedrl.export.onnx_text import safe_text
from embedrl.export.reference import OBSERVATIONS_FILE, OnnxPolicy
from embedrl.export.sb3_onnx import build_onnx
from embedrl.train.errors import InvalidModelFileError, UnsupportedModelFileError
from embedrl.train.evaluate import start_episode
from embedrl.train.interface import INTERFACE_FILE, NO_ENV, Interface, InterfaceError, from_spaces, with_names
from embedrl.train.models import LoadedPolicy, load_sb3, normalization_candidates
from embedrl.train.scenarios import BY_ENV_ID, interface_of

INTERFACE_METADATA_KEY = "embedrl.interface"
"""The same JSON in the ONNX model's ``metadata_props``."""


@dataclass(frozen=True)
class ExportOptions:
    """What ``embedrl export`` was asked to do."""

    source: Path
    out: Path
    name: str = "policy"
    env_id: str = train.ENV_ID
    episodes: int = 200
    """Closed-loop episodes (0 skips the closed loop)."""
    seed: int = 0
    vecnormalize: Path | None = None
    trust_pickle: bool = False
    """Open pickles inside or beside an SB3 model (runs code from them: only for trusted files)."""
    safe_action: tuple[float, ...] | None = None
    force: bool = False
    progress: bool = False
    targets: tuple[str, ...] = ()
    """Cortex-M targets to build, run under QEMU and measure (names in export.target.TARGETS)."""
    quantize: str | None = None
    """None (float32), "int8", "int8-weights" or "q15" (see export.full_integer, export.quantize,
    export.fixed_point)."""
    limits: Limits = field(default_factory=Limits)
    """How large a model is accepted (checked before it is read)."""
    obs_range: tuple[tuple[float, float], ...] | None = None
    """Without an env: each observation's range (one pair for all, or one per value); ``env_id`` unused."""
    act_range: tuple[tuple[float, float], ...] | None = None
    sample_time: float | None = None
    """Without an env: the control period in seconds (the node's timing)."""
    names: dict[str, Any] | None = None
    """``{"observation": [...], "action": [...]}``: names for the interface's fields."""
    names_file: Path | None = None
    """The file ``names`` came from (an input: ``--force`` must not replace a folder that holds it)."""
    tolerance: float = verify.TOLERANCE
    """Allowed error between two export steps, x max(1, |output|) (:data:`export.verify.TOLERANCE`)."""


def _set_metadata(model: onnx.ModelProto, key: str, value: str) -> None:
    for prop in model.metadata_props:
        if prop.key == key:
            prop.value = value
            return
    entry = model.metadata_props.add()
    entry.key, entry.value = key, value


def tool_version() -> str:
    try:
        return metadata.version("embedrl")
    except metadata.PackageNotFoundError:
        return "unknown"


def _check_output_folder(out: Path, force: bool) -> None:
    if out.exists() and not out.is_dir():
        raise ExportError(f"output {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise ExportError(f"output folder {out} is not empty; use --force to replace it")


def _inputs(opts: ExportOptions) -> list[Path]:
    """Every file the export may read: the source, its statistics (given or found beside it), its run
    config and the names file."""
    sb3 = opts.source.suffix.lower() == ".zip"
    found = [*normalization_candidates(opts.source), chain.run_config_of(opts.source)] if sb3 else []
    given = [opts.source, opts.vecnormalize, opts.names_file]
    return [p for p in [*given, *found] if p is not None and p.exists()]


def _check_inputs_outside(out: Path, inputs: list[Path]) -> None:
    """Refuse an output folder that is or holds one of the inputs (replacing it would delete them)."""
    if not out.is_dir():
        return
    folder = out.resolve()
    for path in inputs:
        if path.resolve().is_relative_to(folder):
            raise ExportError(
                f"output folder {out} holds the input {path}: replacing it would delete the input; "
                "give another --out"
            )


def run_export(opts: ExportOptions, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run every step; return the export report. Raises :class:`ExportError` on any failure."""
    check_name(opts.name)
    if opts.obs_range is not None or opts.act_range is not None:
        opts = replace(opts, env_id=NO_ENV)  # a policy without an env: its ranges are its interface
    unknown = [t for t in opts.targets if t not in target.TARGETS]
    if unknown:
        raise ExportError(f"unknown target(s) {unknown}; supported: {', '.join(target.TARGETS)}")
    if opts.targets and opts.name != "policy":
        raise ExportError(
            "--target builds the test firmware around policy_step: use the default --name policy"
        )
    if opts.episodes < 0:
        raise ExportError(f"closed-loop episodes must be >= 0, got {opts.episodes}")
    if opts.out.is_symlink():  # written through: the link stays, its target folder is replaced
        opts = replace(opts, out=opts.out.resolve())
    _check_output_folder(opts.out, opts.force)
    _check_inputs_outside(opts.out, _inputs(opts))
    try:
        opts.out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ExportError(f"cannot create the output folder {opts.out}: {exc.strerror or exc}") from None
    with _locked(opts.out):
        _check_output_folder(opts.out, opts.force)  # again: an export that held the lock may have written it
        _remove_abandoned_staging(opts.out)
        try:
            staging = Path(tempfile.mkdtemp(prefix=f".{opts.out.name}.partial-", dir=opts.out.parent))
            with_umask(staging)  # it becomes the export folder, which others read too
        except OSError as exc:
            raise ExportError(f"cannot create the output folder {opts.out}: {exc.strerror or exc}") from None
        try:
            report = _export_into(staging, opts, log)
            _replace_folder(staging, opts.out)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return report


def _remove_abandoned_staging(out: Path) -> None:
    """Remove what a killed export into ``out`` left beside it: its staging folder and the previous output
    it had renamed away. Called holding ``out``'s lock, so no live export is using them."""
    left = re.compile(re.escape(f".{out.name}.") + r"(partial-[a-z0-9_]{8}|old-[0-9]+)")
    for path in out.parent.iterdir():
        if left.fullmatch(path.name) and path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)


@contextlib.contextmanager
def _locked(out: Path) -> Iterator[None]:
    """Hold ``.<out>.lock`` beside ``out`` for the whole export: a second export into the same folder
    refuses at once instead of silently replacing the first one's result. The lock file is removed at
    the end (a waiter that opened it before checks that it still is the file on disk)."""
    lock = out.with_name(f".{out.name}.lock")
    while True:
        try:
            fd = os.open(lock, os.O_CREAT | os.O_RDWR, 0o644)
        except OSError as exc:
            raise ExportError(f"cannot create the lock {lock}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise ExportError(f"another export is writing {out} (it holds {lock}); wait for it") from None
        try:
            same = os.stat(lock).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the holder removed the file after we opened it: take the new one
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)
        os.close(fd)


def _verify_target(
    t: target.Target,
    c_dir: Path,
    vectors_path: Path,
    vectors: np.ndarray,
    expected: np.ndarray,
    build_dir: Path,
    act_dim: int,
    quantized: str | None,
    sample_time_s: float | None,
    tolerance: float,
) -> dict[str, Any]:
    """Build and run one target's firmware: float actions must match onnxruntime within ``tolerance`` (the
    export's rule, as on the host), quantised ones the Python model bit for bit; its instructions and
    estimated cycles per inference."""
    out = target.build_firmware(t, c_dir, vectors_path, build_dir)
    run = target.run_qemu(t, out / "firmware.elf", len(vectors), act_dim)
    if np.any(run.codes != 0):
        raise VerificationError(
            f"{t.name}: policy_step returned an error on {int(np.sum(run.codes != 0))} observations"
        )
    err = verify.max_abs_error(run.actions, expected)
    if quantized:
        mismatches = verify.bitwise_mismatches(run.actions, expected)
        if mismatches:
            raise VerificationError(
                f"{t.name}: the {quantized} firmware differs from the Python model "
                f"on {mismatches} observations"
            )
    else:
        failure = verify.tolerance_failure(
            run.actions, expected, vectors, tolerance, f"{t.name}: the firmware differs from onnxruntime"
        )
        if failure:
            raise VerificationError(failure)
    traced = cycles.profile(out / "policy.elf", t.qemu_machine, t.name)
    return {
        "stack_bound": stack.policy_bound(out / "firmware.elf"),
        "node_firmware": target.node_firmware(t, c_dir, build_dir),
        "qemu_machine": t.qemu_machine,
        "max_abs_error": err,
        **cycles.time_on_target(run.instructions_per_inference, traced, t.name, sample_time_s),
        **target.sizes(out, run.stack_bytes),
        "quantize": quantized,
        "bit_exact_with_model": True if quantized else None,
        "samples": len(vectors),
        "memory_kib": {"flash": t.flash_kib, "ram": t.ram_kib},
        "compiler": build.compiler(t.name),
    }


def _replace_folder(staging: Path, out: Path) -> None:
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        out.rename(old)
    staging.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@dataclass
class Loaded:
    """Stage 1: the source as an ONNX model (built from SB3's layers, or read), and what it came from."""

    model: onnx.ModelProto
    onnx_path: Path
    """``staging/policy.onnx`` once :func:`_lower` has written it (an ONNX source: the source until then)."""
    loaded: LoadedPolicy | None
    vecnormalize: Path | None
    files: dict[str, Path]
    """Files written into the export so far, by their name in it."""


@dataclass(frozen=True)
class Lowered:
    """Stage 2: the frozen IR checked against the env, and the interface the export carries."""

    graph: Graph
    obs_space: gym.spaces.Box
    interface: Interface | None
    interface_problem: str | None
    action_clamp: dict[str, Any]
    """Whether a clamp to the action space was appended, and the action bounds that decided it."""
    reference: Callable[[np.ndarray], np.ndarray]
    """The policy the export is verified against (SB3's ``predict`` or onnxruntime)."""
    onnx_policy: Callable[[np.ndarray], np.ndarray]
    given: Given | None = None
    """A QDQ model's own int8 quantisation (:mod:`embedrl.export.qdq`)."""


@dataclass(frozen=True)
class Generated:
    """Stage 3: the generated C and the observations it is verified on."""

    c_dir: Path
    samples: np.ndarray
    from_rollouts: int
    section: Section | None


@dataclass(frozen=True)
class Built:
    """Stage 4: the C compiled into a loadable library and measured."""

    compiled: build.CPolicy
    code_size: dict[str, int]
    build_dir: Path


@dataclass(frozen=True)
class Verified:
    """Stage 5: every check's numbers, the Cortex-M targets and the closed loop."""

    checks: dict[str, Any]
    targets: dict[str, Any]
    loop: dict[str, Any]


def _export_into(staging: Path, opts: ExportOptions, log: Callable[[str], None]) -> dict[str, Any]:
    """The stages in order: load, lower, generate, build, verify, write (the report)."""
    loaded = _load(staging, opts, log)
    if qdq.is_qdq(loaded.model):
        if opts.quantize not in (None, full_integer.SCHEME):
            raise ExportError(
                f"{opts.source.name} is quantised (QDQ): it carries its own int8 quantisation; export it "
                f"with --quantize {full_integer.SCHEME} or without --quantize, not --quantize {opts.quantize}"
            )
        opts = replace(opts, quantize=full_integer.SCHEME)
        log(f"      quantised (QDQ): its own int8 scales, as --quantize {full_integer.SCHEME}")
    lowered = _lower(loaded, staging, opts)
    generated = _generate(loaded, lowered, staging, opts, log)
    with owned_temporary_folder("embedrl-build-") as tmp:
        built = _build(generated, tmp, opts, lowered.graph, log)
        verified = _verify(loaded, lowered, generated, built, staging, opts, log)
        _keep_binaries(built.build_dir, staging, opts.targets)
    report = _write_report(loaded, lowered, built, verified, staging, opts)
    links = _chain_links(staging, loaded, opts)
    chain.write(staging, links, [_export_step(links)])
    return report


BINARIES = {"host": ("libpolicy.so",), "target": ("firmware.elf", "node.elf")}
"""What the export keeps in ``bin/<host or target>/``: the binaries its verification ran."""


def _keep_binaries(build_dir: Path, staging: Path, targets: tuple[str, ...]) -> None:
    for where, names in [("host", BINARIES["host"]), *((t, BINARIES["target"]) for t in targets)]:
        (staging / "bin" / where).mkdir(parents=True)
        for name in names:
            shutil.copy2(
                build_dir / ("" if where == "host" else where) / name, staging / "bin" / where / name
            )


def _chain_links(staging: Path, loaded: Loaded, opts: ExportOptions) -> list[chain.TraceLink]:
    """The export's traceability chain (:mod:`embedrl.export.chain`), from the run to the report."""
    links = []
    config = chain.run_config_of(opts.source) if opts.source.suffix.lower() == ".zip" else None
    if config is not None:  # small and part of the evidence (the seed): copied into the bundle
        copy = staging / chain.PROVENANCE / config.name
        copy.parent.mkdir()
        shutil.copyfile(config, copy)
        links.append(chain.link(staging, "run config", copy, [], seed=chain.seed_of(copy)))
    links.append(chain.link(staging, "model", opts.source, ["run config"] if config else []))
    if loaded.vecnormalize is not None:
        links.append(chain.link(staging, "normalisation statistics", loaded.vecnormalize, ["run config"]))
    parents = ["model", *(["normalisation statistics"] if loaded.vecnormalize else [])]
    links.append(chain.link(staging, "ONNX", staging / "policy.onnx", parents))
    if (staging / INTERFACE_FILE).is_file():
        links.append(chain.link(staging, "interface", staging / INTERFACE_FILE, ["ONNX"]))
    for c_file in sorted((staging / "c").iterdir()):
        links.append(chain.link(staging, f"C source {c_file.name}", c_file, ["ONNX"]))
    sources = [k.name for k in links if k.name.startswith("C source")]
    for folder in can_sources.FOLDERS:
        for can_file in sorted((staging / folder).iterdir()) if (staging / folder).is_dir() else []:
            name = f"CAN code {folder}/{can_file.name}"
            links.append(chain.link(staging, name, can_file, ["interface"]))
    classic = [k.name for k in links if k.name.startswith(f"CAN code {can_sources.folder(False)}/")]
    for test_file in sorted((staging / "test").iterdir()):
        links.append(chain.link(staging, f"test data {test_file.name}", test_file, ["ONNX"]))
    for binary in sorted((staging / "bin").rglob("*")):
        if binary.is_file():
            name = f"binary {binary.relative_to(staging / 'bin')}"
            node = binary.name == "node.elf"  # the firmware node: the policy and its classic CAN code
            links.append(chain.link(staging, name, binary, sources + classic if node else sources))
    binaries = [k.name for k in links if k.name.startswith(("binary", "test data"))]
    links.append(chain.link(staging, "verification report", staging / "export_report.json", binaries))
    return links


def _export_step(links: list[chain.TraceLink]) -> chain.Step:
    """The export as a step of the chain: what it read (the run's files) and what it wrote."""
    inputs = [k.name for k in links if k.name in ("run config", "model", "normalisation statistics")]
    outputs = [k.name for k in links if k.name not in inputs]
    return chain.Step("export", f"embedrl {tool_version()}", list(provenance()["command"]), inputs, outputs)


def _load(staging: Path, opts: ExportOptions, log: Callable[[str], None]) -> Loaded:
    source = opts.source
    suffix = source.suffix.lower()
    if suffix not in (".zip", ".onnx"):
        raise UnsupportedModelError(
            f"{source}: unsupported source type '{suffix or '(none)'}'; "
            "give an SB3 model (.zip) or an ONNX file (.onnx)"
        )
    if suffix == ".onnx":
        log(f"[1/5] loading {source}")
        return Loaded(load_onnx(source, opts.limits), source, None, None, {})
    log(f"[1/5] loading {source}")
    try:
        loaded = load_sb3(
            source, opts.vecnormalize, opts.trust_pickle, opts.limits.max_bytes, opts.limits.max_parameters
        )
    except UnsupportedModelFileError as exc:
        raise UnsupportedModelError(str(exc)) from None
    except InvalidModelFileError as exc:
        raise InvalidModelError(str(exc)) from None
    vecnorm_path = loaded.normalization_file
    if vecnorm_path:
        log(f"      with the normalisation statistics {vecnorm_path}")
    onnx_path = staging / "policy.onnx"  # saved by _lower, with the interface in its metadata
    return Loaded(
        safe_text(build_onnx(loaded, tool_version())),
        onnx_path,
        loaded,
        vecnorm_path,
        {"policy.onnx": onnx_path},
    )


def _lower(loaded: Loaded, staging: Path, opts: ExportOptions) -> Lowered:
    graph, given = qdq.lowered(loaded.model)
    obs_dim, act_dim = graph.size(graph.input), graph.size(graph.output)
    obs_space, act_space, interface, interface_problem = _spaces(opts, obs_dim, act_dim)
    if not isinstance(obs_space, gym.spaces.Box) or obs_space.shape != (obs_dim,):
        raise ExportError(
            f"the policy observes {obs_dim} values but {opts.env_id} gives {obs_space}; pass --env, or "
            "--obs-range, --act-range and --sample-time for a policy without an env"
        )
    if not isinstance(act_space, gym.spaces.Box) or act_space.shape != (act_dim,):
        raise ExportError(
            f"the policy outputs {act_dim} values but {opts.env_id} takes {act_space}; pass --env"
        )
    if opts.safe_action is not None:
        safe = np.asarray(opts.safe_action, dtype=np.float32)
        if safe.shape != (act_dim,) or not act_space.contains(safe):
            raise ExportError(
                f"--safe-action {list(opts.safe_action)} must be {act_dim} values within the action space "
                f"[{act_space.low.tolist()}, {act_space.high.tolist()}]"
            )
    scenario = BY_ENV_ID.get(opts.env_id)
    if graph.states and scenario is not None and scenario.robots > 1:
        raise ExportError(
            f"a policy with memory holds one robot's state; the {scenario.name} scenario runs one policy for "
            "every robot: export it for one robot's scenario"
        )
    bounds = action_bounds(graph, obs_space.low, obs_space.high)
    finite_space = bool(np.all(np.isfinite(act_space.low)) and np.all(np.isfinite(act_space.high)))
    clamp = finite_space and not within(bounds, act_space.low, act_space.high)
    action_clamp = {"added": clamp, "bounds": [bounds[0].tolist(), bounds[1].tolist()]}
    if clamp:  # the policy's actions can leave the action space: bound them in the graph itself
        loaded.model = append_clamp(loaded.model, act_space.low, act_space.high)
        graph, given = qdq.lowered(loaded.model)
    if interface is not None:
        interface = interface.with_safe_action(opts.safe_action).with_state_size(graph.state_size)
        (staging / INTERFACE_FILE).write_text(interface.dumps())
        loaded.files[INTERFACE_FILE] = staging / INTERFACE_FILE
        _set_metadata(loaded.model, INTERFACE_METADATA_KEY, interface.dumps())
    # Every export carries its ONNX (an ONNX source's too, weights inline): the folder is self-contained
    # and can be moved; nothing refers back to the source's path.
    loaded.onnx_path = staging / "policy.onnx"
    loaded.files["policy.onnx"] = loaded.onnx_path
    onnx.save(loaded.model, str(loaded.onnx_path))
    reference = loaded.loaded if loaded.loaded is not None else OnnxPolicy(loaded.model)
    return Lowered(
        graph,
        obs_space,
        interface,
        interface_problem,
        action_clamp,
        reference,
        OnnxPolicy(loaded.model),
        given,
    )


def _spaces(
    opts: ExportOptions, obs_dim: int, act_dim: int
) -> tuple[gym.Space[Any], gym.Space[Any], Interface | None, str | None]:
    """The observation and action spaces, and the interface (or why there is none): from the env, or,
    without one, from the user's ranges and the model's shapes."""
    interface: Interface | None = None
    problem = None
    if opts.obs_range is not None:
        if opts.act_range is None or opts.sample_time is None:
            raise ExportError("without an env, give --obs-range, --act-range and --sample-time together")
        obs_low, obs_high = _expand(opts.obs_range, obs_dim, "--obs-range", "observes")
        act_low, act_high = _expand(opts.act_range, act_dim, "--act-range", "outputs")
        obs_space: gym.Space[Any] = gym.spaces.Box(obs_low, obs_high, dtype=np.float32)
        act_space: gym.Space[Any] = gym.spaces.Box(act_low, act_high, dtype=np.float32)
        try:
            interface = from_spaces(NO_ENV, obs_low, obs_high, act_low, act_high, opts.sample_time, 1)
        except InterfaceError as exc:
            raise ExportError(str(exc)) from None
        interface = replace(interface, name=opts.source.stem)
    else:
        try:
            env = gym.make(opts.env_id)
        except gym.error.Error as exc:
            raise ExportError(f"--env {opts.env_id}: {exc}") from None
        obs_space, act_space = env.observation_space, env.action_space
        try:
            interface = interface_of(opts.env_id, env)
        except InterfaceError as exc:
            problem = str(exc)
        env.close()
    if interface is not None and opts.names is not None:
        try:
            interface = with_names(interface, opts.names)
        except InterfaceError as exc:
            raise ExportError(str(exc)) from None
    return obs_space, act_space, interface, problem


def _expand(
    ranges: tuple[tuple[float, float], ...], dim: int, flag: str, verb: str
) -> tuple[np.ndarray, np.ndarray]:
    pairs = ranges * dim if len(ranges) == 1 else ranges
    if len(pairs) != dim:
        raise ExportError(f"{flag}: {len(ranges)} ranges, but the policy {verb} {dim} values")
    low, high = (np.array([p[k] for p in pairs], dtype=np.float32) for k in (0, 1))
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low < high)):
        raise ExportError(f"{flag}: every range must be finite with LOW < HIGH")
    return low, high


def _generate(
    loaded: Loaded, lowered: Lowered, staging: Path, opts: ExportOptions, log: Callable[[str], None]
) -> Generated:
    graph, interface = lowered.graph, lowered.interface
    # Observations for verification (and for calibrating q15's fixed-point scales).
    samples, from_rollouts = verify.sample_observations(
        lowered.obs_space, opts.env_id, lowered.reference, opts.seed
    )
    section = quantize.plan_section(graph, opts.quantize, samples, lowered.given)
    obs_dim, act_dim = graph.size(graph.input), graph.size(graph.output)
    log(f"[2/5] generating C ({len(graph.nodes)} ops, {obs_dim} -> {act_dim})")
    header = {
        "tool": f"embedrl {tool_version()}",
        "source": f"{opts.source.name} sha256 {sha256(opts.source)}",
        "onnx": f"sha256 {sha256(loaded.onnx_path)}",
    }
    safe_action = interface.safe_action if interface is not None else opts.safe_action
    sources = generate(
        graph, opts.name, safe_action, header, quantize=opts.quantize, section=section, interface=interface
    )
    c_dir = staging / "c"
    c_dir.mkdir()
    for filename, text in sources.items():
        (c_dir / filename).write_text(text)
        loaded.files[f"c/{filename}"] = c_dir / filename
    if interface is not None:
        _write_can_code(loaded, interface, staging, opts.name, log)
    return Generated(c_dir, samples, from_rollouts, section)


def _write_can_code(
    loaded: Loaded, interface: Interface, staging: Path, name: str, log: Callable[[str], None]
) -> None:
    """The node's CAN code beside ``c/`` (``can/``, ``can-fd/``: the DBC and its C), so ``make -C runtime_c``
    builds the node with the C toolchain alone."""
    files, left_out = can_sources.export_files(interface, name)
    for path, text in files.items():
        (staging / path).parent.mkdir(exist_ok=True)
        (staging / path).write_text(text)
        loaded.files[path] = staging / path
    for line in left_out:
        log(f"      {line}")


def _build(
    generated: Generated, build_dir: Path, opts: ExportOptions, graph: Graph, log: Callable[[str], None]
) -> Built:
    log("[3/5] compiling with make -C runtime_c")
    build.make("lib", generated.c_dir, build_dir)
    build.make("obj", generated.c_dir, build_dir)
    obs_dim, act_dim = graph.size(graph.input), graph.size(graph.output)
    compiled = build.CPolicy(build_dir / "libpolicy.so", opts.name, obs_dim, act_dim)
    return Built(compiled, build.object_size(build_dir / "policy.o"), build_dir)


def _verify(
    loaded: Loaded,
    lowered: Lowered,
    generated: Generated,
    built: Built,
    staging: Path,
    opts: ExportOptions,
    log: Callable[[str], None],
) -> Verified:
    """Stage 4 and 5: the numbers (ONNX vs SB3, C vs onnxruntime or its integer model), the targets, the
    safe action on NaN, then the closed loop; each failure raises :class:`VerificationError`."""
    log("[4/5] verifying: " + ("ONNX vs SB3, " if loaded.loaded is not None else "") + "C vs onnxruntime")
    checks = _numerical_checks(loaded, lowered, generated, built, opts)
    vectors, vectors_path = _write_test_data(loaded, generated, staging)
    targets = {}
    for name in opts.targets:
        log(f"[4/5] {name}: building firmware, running it on QEMU")
        start_episode(lowered.onnx_policy)  # the firmware runs the vectors as one sequence from reset
        expected = (
            quantize.evaluate(lowered.graph, vectors, generated.section)
            if opts.quantize
            else lowered.onnx_policy(vectors)
        )
        targets[name] = _verify_target(
            target.TARGETS[name], generated.c_dir, vectors_path, vectors, expected, built.build_dir,
            lowered.graph.size(lowered.graph.output), opts.quantize,
            lowered.interface.sample_time_s if lowered.interface else None, opts.tolerance,
        )  # fmt: skip
    checks["non_finite_observation"] = _safe_on_nan(built.compiled, lowered.graph.size(lowered.graph.input))
    log("[4/5] NaN propagation: each op with a NaN at each input position, C vs ONNX")
    opset = {o.domain: o.version for o in loaded.model.opset_import}.get("", 0)
    section = generated.section.nodes if generated.section is not None else frozenset()
    checks["nan_propagation"] = nan_check.check(
        lowered.graph, opts.quantize, opset, section, opts.tolerance, opts.seed
    )
    return Verified(checks, targets, _closed_loop(lowered, built, opts, log))


def _numerical_checks(
    loaded: Loaded, lowered: Lowered, generated: Generated, built: Built, opts: ExportOptions
) -> dict[str, Any]:
    graph, samples, section = lowered.graph, generated.samples, generated.section
    # A recurrent policy takes the samples as one sequence from zero state, on every side.
    for policy in (lowered.onnx_policy, loaded.loaded, built.compiled):
        start_episode(policy)
    onnx_actions = lowered.onnx_policy(samples)
    checks: dict[str, Any] = {
        "samples": len(samples),
        "samples_from_rollouts": int(generated.from_rollouts),
        "tolerance": opts.tolerance,
        "tolerance_rule": "|error| <= tolerance x max(1, |output|) for every output",
        "onnx_vs_sb3_max_abs_error": None,
        "onnx_vs_sb3_max_ulp": None,
    }
    if loaded.loaded is not None:
        sb3_actions = loaded.loaded.predict(samples)
        checks["onnx_vs_sb3_max_abs_error"] = verify.max_abs_error(onnx_actions, sb3_actions)
        checks["onnx_vs_sb3_max_ulp"] = verify.max_ulp(onnx_actions, sb3_actions)
        failure = verify.tolerance_failure(
            onnx_actions, sb3_actions, samples, opts.tolerance, "the ONNX differs from SB3's predict()"
        )
        if failure:
            raise VerificationError(failure)
    c_actions, codes = built.compiled.batch(samples)
    if np.any(codes != 0):
        raise VerificationError(
            f"the generated C returned an error code on {int(np.sum(codes != 0))} samples"
        )
    err = verify.max_abs_error(c_actions, onnx_actions)
    checks["c_vs_onnxruntime_max_abs_error"] = err
    checks["c_vs_onnxruntime_max_ulp"] = verify.max_ulp(c_actions, onnx_actions)
    if opts.quantize:
        # Quantised: the C must equal the Python model of its arithmetic bit for bit; its
        # distance from the float policy is reported (and judged in closed loop).
        mismatches = verify.bitwise_mismatches(c_actions, quantize.evaluate(graph, samples, section))
        checks["quantization"] = {
            "scheme": quantize.SCHEMES[opts.quantize],
            "worst_action_error_vs_float": err,
            "model_mismatches": mismatches,
        }
        if mismatches:
            raise VerificationError(
                f"the {opts.quantize} C differs from the Python model of its arithmetic "
                f"on {mismatches} samples"
            )
        if lowered.given is not None and section is not None:
            checks["quantization"]["qdq"] = _qdq_check(loaded.model, lowered, section, samples)
    else:
        failure = verify.tolerance_failure(
            c_actions, onnx_actions, samples, opts.tolerance, "the generated C differs from onnxruntime"
        )
        if failure:
            raise VerificationError(failure)
    return checks


def _qdq_check(
    model: onnx.ModelProto, lowered: Lowered, section: Section, samples: np.ndarray
) -> dict[str, Any]:
    """The integer section's output against onnxruntime running the QDQ model, in its output steps."""
    assert lowered.given is not None
    c_output = interpret.run(lowered.graph, samples, "int8", section)[section.output]
    assert isinstance(section, IntegerSection)
    found = qdq.compare(model, lowered.graph, section, c_output, samples)
    worst = max(found["max_layer_steps"])
    if worst > found["tolerance_steps"]:
        layer = found["layers"][found["max_layer_steps"].index(worst)]
        raise VerificationError(
            f"the int8 C's layer '{layer}' is {worst:.2f} steps from onnxruntime running the QDQ model "
            f"on the same int8 input (allowed {found['tolerance_steps']:g})"
        )
    return found


def _write_test_data(loaded: Loaded, generated: Generated, staging: Path) -> tuple[np.ndarray, Path]:
    """The firmware's test vectors (``test/test_vectors.c``) and the observations the HIL replays in open
    loop; the vectors and their file."""
    vectors = target.pick_test_vectors(generated.samples, generated.from_rollouts)
    vectors_path = staging / "test" / "test_vectors.c"
    vectors_path.parent.mkdir()
    vectors_path.write_text(target.test_vectors_source(vectors))
    loaded.files["test/test_vectors.c"] = vectors_path
    np.save(staging / "test" / OBSERVATIONS_FILE, generated.samples)
    loaded.files[f"test/{OBSERVATIONS_FILE}"] = staging / "test" / OBSERVATIONS_FILE
    return vectors, vectors_path


def _safe_on_nan(compiled: build.CPolicy, obs_dim: int) -> dict[str, Any]:
    nan_obs = np.full(obs_dim, np.nan, dtype=np.float32)
    compiled.reset()
    safe = compiled(nan_obs)
    if compiled.status != 1 or not np.all(np.isfinite(safe)):
        raise VerificationError("the generated C did not reject a NaN observation with the safe action")
    return {"return_code": compiled.status, "action": safe.tolist()}


def _closed_loop(
    lowered: Lowered, built: Built, opts: ExportOptions, log: Callable[[str], None]
) -> dict[str, Any]:
    if opts.episodes and verify.supports_closed_loop(opts.env_id):
        log(f"[5/5] closed loop: {opts.episodes} episodes, reference and generated C")
        loop: dict[str, Any] = verify.closed_loop(
            lowered.reference, built.compiled, opts.episodes, opts.seed, opts.progress, opts.env_id
        )
        failure = (
            verify.quantized_closed_loop_failure(loop) if opts.quantize else verify.closed_loop_failure(loop)
        )
        if failure:
            raise VerificationError(failure)
        return loop
    if opts.env_id == NO_ENV:
        reason = "no env: the C is verified against onnxruntime on observations sampled from the given ranges"
    elif not opts.episodes:
        reason = "episodes=0"
    else:
        reason = f"{opts.env_id} reports no success/collision outcomes"
    log(f"[5/5] closed loop skipped ({reason})")
    return {"skipped": reason}


def _write_report(
    loaded: Loaded, lowered: Lowered, built: Built, verified: Verified, staging: Path, opts: ExportOptions
) -> dict[str, Any]:
    graph, interface, source = lowered.graph, lowered.interface, opts.source
    vecnorm_path = loaded.vecnormalize
    report: dict[str, Any] = {
        "tool": f"embedrl {tool_version()}",
        "source": {
            "path": str(source.resolve()),
            "sha256": sha256(source),
            "kind": "sb3" if loaded.loaded is not None else "onnx",
            "policy_class": loaded.loaded.kind if loaded.loaded is not None else None,
            "vecnormalize": None
            if vecnorm_path is None
            else {"path": str(vecnorm_path), "sha256": sha256(vecnorm_path)},
        },
        "name": opts.name,
        "quantize": opts.quantize,
        "env_id": opts.env_id,
        "interface": interface.to_json()
        if interface is not None
        else {"unavailable": lowered.interface_problem},
        "action_clamp": lowered.action_clamp,
        "observation_dim": graph.size(graph.input),
        "action_dim": graph.size(graph.output),
        "ops": [n.op for n in graph.nodes],
        "compiler": build.compiler(),
        "verification": verified.checks,
        "closed_loop": verified.loop,
        "code_size": built.code_size,
        "targets": verified.targets,
        "files": {k: sha256(v) for k, v in sorted(loaded.files.items())},
        "provenance": provenance(),
    }
    (staging / "export_report.json").write_text(json.dumps(report, indent=2) + "\n")
    return report
