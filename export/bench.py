"""Inference speed of an export: generated C (-O2) vs onnxruntime vs torch, measured in one run.

Single-observation latency, the number an embedded control loop cares about: the C timing
comes from ``runtime_c/bench/bench_policy.c`` (a compiled loop over the observations), the
onnxruntime and torch timings from one call per observation in this process. The median over
repeats is reported.
"""

from __future__ import annotations

import json
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import onnxruntime as ort
import torch

from embedrl import train
from embedrl.export import build
from embedrl.export.errors import ExportError
from embedrl.export.pipeline import ExportOptions, run_export
from embedrl.train.models import load_sb3

STUDY_ARCH = [100, 100]
"""The reference study's actor: 6 -> 100 -> 100 -> 2, ReLU, tanh output."""
C_REPEATS = 21
PY_REPEATS = 5
PY_SAMPLES = 2_000
TARGET_SPEEDUP_VS_ONNXRUNTIME = 5.0
TARGET_C_NS = 1_200.0


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


def run(export_dir: Path | None, seed: int = 0) -> dict[str, Any]:
    """Measure an export (or a fresh export of the study's actor shape) and return the numbers."""
    with tempfile.TemporaryDirectory(prefix="embedrl-bench-") as tmp:
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
        obs_dim = report["observation_dim"]
        rng = np.random.default_rng(seed)
        space = gym.make(report["env_id"]).observation_space
        assert isinstance(space, gym.spaces.Box)
        samples = rng.uniform(space.low, space.high, size=(10_000, obs_dim)).astype(np.float32)
        obs_file = work / "obs.bin"
        samples.tofile(obs_file)

        build.make("bench", export_dir / "c", work / "build")
        build.make("obj", export_dir / "c", work / "build")
        out = subprocess.run(
            [str(work / "build" / "bench_policy"), str(obs_file), str(C_REPEATS)],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        c_ns = float(out.split("ns_per_inference")[1].split()[0])

        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        onnx_file = export_dir / "policy.onnx"
        if not onnx_file.is_file():
            onnx_file = Path(report["source"]["path"])
        session = ort.InferenceSession(str(onnx_file), options, providers=["CPUExecutionProvider"])
        name = session.get_inputs()[0].name
        few = samples[:PY_SAMPLES]
        ort_ns = _median_ns(lambda x: session.run(None, {name: x.reshape(1, -1)}), few)

        torch_ns = None
        if report["source"]["kind"] == "sb3":
            policy = load_sb3(Path(report["source"]["path"])).policy
            torch.set_num_threads(1)

            def torch_step(x: np.ndarray) -> None:
                with torch.no_grad():
                    policy._predict(torch.as_tensor(x).reshape(1, -1), deterministic=True)

            torch_ns = _median_ns(torch_step, few)

        size = build.object_size(work / "build" / "policy.o")
    return {
        "export_dir": str(export_dir) if export_dir.parent != work else "(fresh export of the study's actor)",
        "ops": report["ops"],
        "c_ns_per_inference": round(c_ns, 1),
        "onnxruntime_ns_per_inference": round(ort_ns, 1),
        "torch_ns_per_inference": None if torch_ns is None else round(torch_ns, 1),
        "speedup_vs_onnxruntime": round(ort_ns / c_ns, 2),
        "speedup_vs_torch": None if torch_ns is None else round(torch_ns / c_ns, 2),
        "target_speedup_vs_onnxruntime": TARGET_SPEEDUP_VS_ONNXRUNTIME,
        "target_c_ns": TARGET_C_NS,
        "object_text_bytes": size["text"],
        "object_data_bytes": size["data"],
        "object_bss_bytes": size["bss"],
        "compiler": build.compiler()["command"],
    }
