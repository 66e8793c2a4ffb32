"""Inference speed of an export: generated C (-O2), onnxruntime, torch, emx-onnx-cgen's C and the hardware's
limit, one run.

Single-observation latency, the number an embedded control loop cares about: the C timing comes from
``runtime_c/bench/bench_policy.c`` (a compiled loop over the observations), then the same harness on
``policy_step_batch`` over all of them; the onnxruntime and torch timings from one call per observation in
this process, onnxruntime's batched time from one call on :data:`BATCH` observations; emx-onnx-cgen's C
(with ``--emx``) in the same harness at the same optimisation level. The median over repeats is reported.
The limit comes from ``runtime_c/bench/limit_probe.c`` on this CPU: the time of the model's multiply-adds
at the measured fused multiply-add throughput, and of reading its weights once at the measured cache
bandwidth; the larger bounds any inference, and every time is also given as its ratio to it. The C gives the
same bits in every build, the baseline's (no fused multiply-add) included, so its own ceiling is the larger
of the weight read and the multiply-adds as a multiply then an add in AVX2 vectors
(``limit_without_fma_ns``). The peers' actions are checked against the C's on :data:`AGREEMENT_SAMPLES`
observations. A quantised export can be timed against the same policy's float32 export (``float32_dir``):
both in the same harness on the same observations, :data:`FLOAT32_ROUNDS` rounds taken in turn, the ratio
of their medians printed as ``c_ratio_to_float32``.
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import onnxruntime as ort
import torch

from embedrl import train
from embedrl.common import owned_temporary_folder, read_json
from embedrl.export import build
from embedrl.export.errors import ExportError
from embedrl.export.pipeline import ExportOptions, run_export
from embedrl.train.interface import INTERFACE_FILE, Interface
from embedrl.train.models import load_sb3

STUDY_ARCH = [100, 100]
"""The reference study's actor: 6 -> 100 -> 100 -> 2, ReLU, tanh output."""
C_REPEATS = 21
PY_REPEATS = 5
PY_SAMPLES = 2_000
BATCH = 1_000
"""Observations per batched onnxruntime call."""
AGREEMENT_SAMPLES = 256
AGREEMENT_TOLERANCE = 1e-5
TARGET_SPEEDUP_VS_ONNXRUNTIME = 5.0
TARGET_C_NS = 1_200.0
FLOAT32_ROUNDS = 3
"""Rounds of the harness against the float32 export, each this export's then float32's (a machine busy for a
moment slows one round of both, not one side)."""


def study_actor(folder: Path, seed: int = 0) -> Path:
    """Save an (untrained, seeded) TD3 with the study's actor shape; its speed is its shape's."""
    from stable_baselines3 import TD3

    model = TD3(
        "MlpPolicy",
        gym.make(train.ENV_ID),
        policy_kwargs={"net_arch": STUDY_ARCH},
        seed=seed,
        device="cpu",
        buffer_size=1,
    )
    path = folder / "td3_study_actor.zip"
    model.save(path)
    return path


def _median_ns(fn: Any, samples: np.ndarray) -> float:
    times = []
    for _ in range(PY_REPEATS):
        start = time.perf_counter_ns()
        for x in samples:
            fn(x)
        times.append((time.perf_counter_ns() - start) / len(samples))
    return float(np.median(times))


def run(
    export_dir: Path | None, seed: int = 0, emx: Path | None = None, float32_dir: Path | None = None
) -> dict[str, Any]:
    """Measure an export (or a fresh export of the study's actor shape) and return the numbers; ``emx``:
    emx-onnx-cgen's command, whose C of the same ONNX is timed as a peer (None: not measured);
    ``float32_dir``: the float32 export of the same policy, when ``export_dir`` is a quantised one."""
    if emx is not None and not emx.is_file():
        raise ExportError(f"no emx-onnx-cgen at {emx}: `make bench` installs it into tools/emx")
    if float32_dir is not None and export_dir is None:
        raise ExportError("--float32-dir needs EXPORT_DIR: a quantised export of the same policy")
    with owned_temporary_folder("embedrl-bench-") as tmp:
        work = Path(tmp)
        if export_dir is None:
            export_dir = work / "export"
            run_export(
                ExportOptions(source=study_actor(work, seed), out=export_dir, episodes=0, seed=seed),
                log=lambda _: None,
            )
        report_path = export_dir / "export_report.json"
        if not report_path.is_file():
            raise ExportError(f"{export_dir} is not an export folder (no export_report.json)")
        report = json.loads(report_path.read_text())
        if report["name"] != "policy":
            raise ExportError("the benchmark harness needs an export with the default --name policy")
        if (report.get("interface") or {}).get("state_size"):
            raise ExportError(
                "bench-export times policies without memory against batched peers; a recurrent policy's step "
                "depends on its state: export it with --target cortex-m4 for its instructions per step"
            )
        if float32_dir is not None:
            _check_float32_export(float32_dir, report)
        rng = np.random.default_rng(seed)
        low, high = _observation_range(export_dir, report)
        samples = rng.uniform(low, high, size=(10_000, report["observation_dim"])).astype(np.float32)
        c_ns, c_batched_ns, c_actions = _c_time(export_dir, report, samples, work)
        float32 = _against_float32(float32_dir, work)
        onnx_file = export_dir / "policy.onnx"
        if not onnx_file.is_file():
            onnx_file = Path(report["source"]["path"])
        peers = _peers(onnx_file, report, samples, c_actions)
        peers.update(_emx(emx, onnx_file, export_dir, work, c_actions))
        peers.update(_native(export_dir, work, c_actions))
        _check_agreement(export_dir, samples[:AGREEMENT_SAMPLES], c_actions, peers)
        limit = _limit(onnx_file, work, report.get("quantize"))
        size = build.object_size(work / "build" / "policy.o")
    return {
        "cpu": cpu_name(),
        "export_dir": str(export_dir) if export_dir.parent != work else "(fresh export of the study's actor)",
        "ops": report["ops"],
        "c_ns_per_inference": round(c_ns, 1),
        "c_ratio_to_limit": round(c_ns / limit["limit_ns"], 2),
        "c_ratio_to_limit_without_fma": None if limit["limit_without_fma_ns"] is None
        else round(c_ns / limit["limit_without_fma_ns"], 2),
        "c_batched_ns_per_observation": round(c_batched_ns, 1),
        "c_batched_ratio_to_onnxruntime_batched": round(
            c_batched_ns / peers["onnxruntime_batched_ns_per_observation"], 2
        ),
        **{k: v for k, v in limit.items()},
        **float32,
        **peers,
        "onnxruntime_ratio_to_limit": round(peers["onnxruntime_ns_per_inference"] / limit["limit_ns"], 2),
        "onnxruntime_batched_ratio_to_fma_limit": round(
            peers["onnxruntime_batched_ns_per_observation"] / limit["limit_fma_ns"], 2
        ),  # a batch reads the weights once for all its observations: only the arithmetic bounds it
        "speedup_vs_onnxruntime": round(peers["onnxruntime_ns_per_inference"] / c_ns, 2),
        "speedup_vs_emx_onnx_cgen": None if peers["emx_onnx_cgen_ns_per_inference"] is None
        else round(peers["emx_onnx_cgen_ns_per_inference"] / c_ns, 2),
        "speedup_vs_torch": None if peers["torch_ns_per_inference"] is None
        else round(peers["torch_ns_per_inference"] / c_ns, 2),
        "target_speedup_vs_onnxruntime": TARGET_SPEEDUP_VS_ONNXRUNTIME,
        "target_c_ns": TARGET_C_NS,
        "object_text_bytes": size["text"],
        "object_data_bytes": size["data"],
        "object_bss_bytes": size["bss"],
        "compiler": build.compiler()["command"],
    }  # fmt: skip


def cpu_name() -> str:
    """The CPU as ``/proc/cpuinfo`` names it (its ``model name``), else as Python's platform module does."""
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _c_time(
    export_dir: Path, report: dict[str, Any], samples: np.ndarray, work: Path
) -> tuple[float, float, np.ndarray]:
    """The C's median ns per inference and per observation through ``policy_step_batch`` (the compiled
    harness), and its actions on the first samples."""
    obs_file = work / "obs.bin"
    samples.tofile(obs_file)
    for target in ("bench", "obj", "lib"):
        build.make(target, export_dir / "c", work / "build")
    out = subprocess.run(
        [str(work / "build" / "bench_policy"), str(obs_file), str(C_REPEATS)],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    c_policy = build.CPolicy(work / "build" / "libpolicy.so", "policy", report["observation_dim"],
                             report["action_dim"])  # fmt: skip
    actions, _ = c_policy.rows(samples[:AGREEMENT_SAMPLES])
    batched, _ = c_policy.batch(samples[:AGREEMENT_SAMPLES])
    if batched.tobytes() != actions.tobytes():
        raise ExportError("policy_step_batch and policy_step disagree: the generated C is broken")
    return _printed(out, "ns_per_inference"), _printed(out, "ns_per_observation_batched"), actions


def _against_float32(float32_dir: Path | None, work: Path) -> dict[str, Any]:
    """This export's harness (built by :func:`_c_time`) and ``float32_dir``'s on the same observations, in
    turn for :data:`FLOAT32_ROUNDS` rounds: each side's median ns per inference and their ratio (nothing
    without ``float32_dir``)."""
    if float32_dir is None:
        return {}
    build.make("bench", float32_dir / "c", work / "float32")
    binaries = {"c": work / "build" / "bench_policy", "float32": work / "float32" / "bench_policy"}
    times: dict[str, list[float]] = {side: [] for side in binaries}
    for _ in range(FLOAT32_ROUNDS):
        for side, binary in binaries.items():
            command = [str(binary), str(work / "obs.bin"), str(C_REPEATS)]
            out = subprocess.run(command, capture_output=True, text=True, check=True).stdout
            times[side].append(_printed(out, "ns_per_inference"))
    own, float32 = (float(np.median(times[side])) for side in binaries)
    return {
        "float32_export_dir": str(float32_dir),
        "float32_c_ns_per_inference": round(float32, 1),
        "c_ns_per_inference_beside_float32": round(own, 1),
        "c_ratio_to_float32": round(own / float32, 3),
    }


def _check_float32_export(float32_dir: Path, report: dict[str, Any]) -> None:
    """``float32_dir`` must be the float32 export of the policy ``report`` describes, under the same name."""
    report_path = float32_dir / "export_report.json"
    if not report_path.is_file():
        raise ExportError(f"--float32-dir {float32_dir} is not an export folder (no export_report.json)")
    other = json.loads(report_path.read_text())
    if report.get("quantize") is None:
        raise ExportError(
            "--float32-dir compares a quantised export with its float32 one; EXPORT_DIR is float32"
        )
    if other.get("quantize") is not None:
        raise ExportError(f"--float32-dir {float32_dir} is not a float32 export ({other['quantize']})")
    if other["source"]["sha256"] != report["source"]["sha256"] or other["name"] != report["name"]:
        theirs, ours = other["source"]["sha256"][:12], report["source"]["sha256"][:12]
        raise ExportError(
            f"--float32-dir {float32_dir} exports another policy (source sha256 {theirs}, name "
            f"{other['name']!r}) than EXPORT_DIR ({ours}, {report['name']!r})"
        )


def _peers(
    onnx_file: Path, report: dict[str, Any], samples: np.ndarray, c_actions: np.ndarray
) -> dict[str, Any]:
    """onnxruntime (one observation per call, and :data:`BATCH` per call) and torch (SB3 sources): times
    and their largest difference from the C's actions."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(onnx_file), options, providers=["CPUExecutionProvider"])
    name = session.get_inputs()[0].name
    few, check = samples[:PY_SAMPLES], samples[:AGREEMENT_SAMPLES]
    ort_ns = _median_ns(lambda x: session.run(None, {name: x.reshape(1, -1)}), few)
    batch = samples[:BATCH]
    ort_batch_ns = _median_ns(lambda _: session.run(None, {name: batch}), np.zeros((PY_REPEATS, 1))) / BATCH
    ort_actions = np.asarray(session.run(None, {name: check})[0], dtype=np.float32)
    result: dict[str, Any] = {
        "onnxruntime_ns_per_inference": round(ort_ns, 1),
        "onnxruntime_batched_ns_per_observation": round(ort_batch_ns, 1),
        "onnxruntime_max_abs_diff_from_c": float(np.max(np.abs(ort_actions - c_actions))),
        "torch_ns_per_inference": None,
        "torch_max_abs_diff_from_c": None,
    }
    if report["source"]["kind"] == "sb3":
        policy = load_sb3(Path(report["source"]["path"])).policy
        torch.set_num_threads(1)

        def torch_step(x: np.ndarray) -> Any:
            with torch.no_grad():
                return policy._predict(torch.as_tensor(x).reshape(1, -1), deterministic=True)

        result["torch_ns_per_inference"] = round(_median_ns(torch_step, few), 1)
        torch_actions = np.asarray(
            policy.predict(check, deterministic=True)[0], dtype=np.float32
        )  # env units
        result["torch_max_abs_diff_from_c"] = float(np.max(np.abs(torch_actions - c_actions)))
    return result


NATIVE_OPT = "-O3 -march=native"
"""The build a user tuning for this one machine would make: the same C, every instruction set of the CPU."""


def _native(export_dir: Path, work: Path, c_actions: np.ndarray) -> dict[str, Any]:
    """The same C and harness built with :data:`NATIVE_OPT`: its times and its largest difference from the
    default build's actions (gcc may fuse multiply-adds there, so the bits may differ)."""
    build.make("bench", export_dir / "c", work / "native", NATIVE_OPT)
    return {
        "c_native_flags": NATIVE_OPT,
        **_harness(work / "native" / "bench_policy", work, c_actions, "c_native"),
    }


def _harness(binary: Path, work: Path, c_actions: np.ndarray, prefix: str) -> dict[str, Any]:
    """Run a built ``bench_policy`` harness on the observations in ``work``: ``{prefix}_ns_per_inference``,
    ``{prefix}_batched_ns_per_observation`` and ``{prefix}_max_abs_diff_from_c`` (its actions against the
    default build's on the first samples)."""
    actions_file = work / f"{prefix}_actions.bin"
    out = subprocess.run(
        [str(binary), str(work / "obs.bin"), str(C_REPEATS), str(actions_file)],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    actions = np.fromfile(actions_file, dtype="<f4").reshape(-1, c_actions.shape[1])[: len(c_actions)]
    return {
        f"{prefix}_ns_per_inference": _printed(out, "ns_per_inference"),
        f"{prefix}_batched_ns_per_observation": _printed(out, "ns_per_observation_batched"),
        f"{prefix}_max_abs_diff_from_c": float(np.max(np.abs(actions - c_actions))),
    }


def _printed(out: str, name: str) -> float:
    """The value of the harness's ``name value`` line."""
    return float(out.split(f"{name} ")[1].split()[0])


def _emx(
    emx: Path | None, onnx_file: Path, export_dir: Path, work: Path, c_actions: np.ndarray
) -> dict[str, Any]:
    """emx-onnx-cgen's C of the same ONNX in the same harness at the same optimisation level: its time per
    observation, one per call and all in one call, and its largest difference from embedrl's actions."""
    if emx is None:
        return {"emx_onnx_cgen_ns_per_inference": None, "emx_onnx_cgen_batched_ns_per_observation": None,
                "emx_onnx_cgen_max_abs_diff_from_c": None}  # fmt: skip
    peer_c = work / "peer.c"
    generated = subprocess.run(
        [str(emx), "compile", str(onnx_file), str(peer_c), "--model-name", "peer"],
        capture_output=True,
        text=True,
    )
    if generated.returncode != 0:
        raise ExportError(f"emx-onnx-cgen could not compile the policy: {generated.stderr.strip()[-300:]}")
    build.make("bench-peer", export_dir / "c", work / "peer", extra={"PEER_C": str(peer_c)})
    return _harness(work / "peer" / "bench_peer", work, c_actions, "emx_onnx_cgen")


def _check_agreement(
    export_dir: Path, check: np.ndarray, c_actions: np.ndarray, peers: dict[str, Any]
) -> None:
    """The C must compute its export's function (the reference for its precision), and in float32 so must
    the peers; a quantised export's difference from the float peers is its precision's error, reported."""
    from embedrl.export.reference import precision_of, reference_policy

    precision = precision_of(export_dir)
    peers["precision"] = precision
    own = float(np.max(np.abs(reference_policy(export_dir)(check) - c_actions)))
    checked = {
        "reference_max_abs_diff_from_c": own,
        "c_native_max_abs_diff_from_c": peers["c_native_max_abs_diff_from_c"],
    }
    if precision == "float32":
        checked.update(
            {
                k: peers[k]
                for k in (
                    "onnxruntime_max_abs_diff_from_c", "torch_max_abs_diff_from_c",
                    "emx_onnx_cgen_max_abs_diff_from_c",
                )
            }
        )  # fmt: skip
    for key, value in checked.items():
        if value is not None and not value <= AGREEMENT_TOLERANCE:
            raise ExportError(
                f"{key} = {value:.3g} exceeds {AGREEMENT_TOLERANCE:g}: the timings would compare "
                "different functions"
            )
    peers["reference_max_abs_diff_from_c"] = own


def _observation_range(export_dir: Path, report: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Where the timed observations are drawn from: the interface's ranges (every export with one, also a
    policy without an env), else the env's observation space."""
    interface_file = export_dir / INTERFACE_FILE
    if interface_file.is_file():
        interface = Interface.from_json(read_json(interface_file))
        return interface.obs_low, interface.obs_high
    space = gym.make(report["env_id"]).observation_space
    assert isinstance(space, gym.spaces.Box)
    return space.low, space.high


WEIGHT_BYTES = {None: 4, "int8": 1, "int8-weights": 1, "q15": 2}
"""Bytes per matrix weight in the generated C, per precision."""


def _limit(onnx_file: Path, work: Path, quantize: str | None) -> dict[str, Any]:
    """The model's multiply-adds and weight bytes (its 2-D initializers, the matrices, at the C's
    precision), and the times the probe puts on them on this CPU."""
    import onnx
    from onnx import numpy_helper

    matrices = [numpy_helper.to_array(t) for t in onnx.load(str(onnx_file)).graph.initializer]
    macs = sum(int(m.size) for m in matrices if m.ndim == 2)
    weight_bytes = macs * WEIGHT_BYTES[quantize]
    build.make("probe", work, work / "build")
    out = subprocess.run([str(work / "build" / "limit_probe"), str(max(weight_bytes, 64))],
                         capture_output=True, text=True, check=True).stdout  # fmt: skip
    probe = dict(line.split() for line in out.splitlines())
    fma_ns = macs / float(probe["fma_gmacs"])
    stream_ns = float(probe["stream_ns_per_pass"])
    mul_add = float(probe["mul_add_gmacs"])
    mul_add_ns = max(macs / mul_add, stream_ns) if mul_add > 0 else None
    return {
        "model_multiply_adds": macs, "model_weight_bytes": weight_bytes,
        "limit_fma_ns": round(fma_ns, 2), "limit_weight_read_ns": round(stream_ns, 2),
        "limit_ns": round(max(fma_ns, stream_ns), 2),
        "limit_without_fma_ns": None if mul_add_ns is None else round(mul_add_ns, 2),
    }  # fmt: skip
