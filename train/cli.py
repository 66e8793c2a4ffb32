"""The ``embedrl`` command. Each package owns its subcommands; this module gathers them.

``train`` contributes ``eval``, ``render`` and ``bench-env``; ``export`` and ``hil`` add theirs
with a ``register(subparsers)`` function in their own ``cli`` module when they exist.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import traceback
from pathlib import Path
from typing import Any

from train.errors import TrainError, UsageError

CONTROLLERS = ("potential-field",)
"""Built-in scripted controllers, usable wherever a policy is expected."""
OTHER_PACKAGES = ("export", "hil")


def _controller(name: str):  # type: ignore[no-untyped-def]
    from train.potential_field import PotentialFieldController

    if name == "potential-field":
        return PotentialFieldController()
    raise UsageError(f"unknown controller {name!r}; available: {', '.join(CONTROLLERS)}")


def _policy(args: argparse.Namespace):  # type: ignore[no-untyped-def]
    if args.model is not None:
        return load_model_policy(args.model)
    return _controller(args.controller)


def load_model_policy(path: Path):  # type: ignore[no-untyped-def]
    """A trained SB3 model as a deterministic policy (VecNormalize statistics beside it are applied)."""
    if path.suffix != ".zip":
        raise UsageError(f"cannot evaluate {path}: give a Stable-Baselines3 model (.zip)")
    from export.errors import ExportError
    from export.pipeline import vecnormalize_beside
    from export.sb3_onnx import load_sb3

    try:
        loaded = load_sb3(path, vecnormalize_beside(path))
    except ExportError as exc:
        raise UsageError(str(exc)) from None

    def act(obs):  # type: ignore[no-untyped-def]
        return loaded.predict(obs.reshape(1, -1))[0]

    return act


def _add_policy_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("model", nargs="?", type=Path, help="a trained Stable-Baselines3 model (.zip)")
    src.add_argument("--controller", choices=CONTROLLERS, help="a built-in scripted controller")


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def cmd_eval(args: argparse.Namespace) -> int:
    from train.evaluate import evaluate, write_json

    policy = _policy(args)
    name = args.controller or str(args.model)
    report = evaluate(policy, args.episodes, args.seed, name, progress=True)
    print(report.table())
    if args.json:
        write_json(report.to_json(), args.json)
        print(f"wrote {args.json}")
    if args.plot:
        from train.plots import plot_trajectories

        plot_trajectories(report, args.plot)
        print(f"wrote {args.plot}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    import gymnasium as gym
    import numpy as np

    from train import ENV_ID
    from train.rendering import save_episode
    from train.robot import SAMPLE_TIME

    if args.out.suffix.lower() not in (".gif", ".png"):
        raise UsageError(f"cannot write {args.out}: use a .gif (animation) or .png (strip) file name")
    policy = _policy(args)
    env = gym.make(ENV_ID, render_mode="rgb_array")
    obs, info = env.reset(seed=args.seed)
    frames: list[np.ndarray] = [env.unwrapped.render()]  # type: ignore[list-item]
    while True:
        obs, _, terminated, truncated, info = env.step(policy(obs))
        frames.append(env.unwrapped.render())  # type: ignore[arg-type]
        if terminated or truncated:
            break
    env.close()
    save_episode(frames, args.out, SAMPLE_TIME)
    outcome = "success" if info["is_success"] else "collision" if info["collided"] else "timeout"
    print(f"wrote {args.out}: {len(frames) - 1} steps, {outcome}")
    return 0


def print_measurement(result: dict[str, Any], json_path: Path | None) -> None:
    """A benchmark's numbers as aligned lines; with ``json_path`` also as JSON with provenance."""
    from train.evaluate import provenance, write_json

    width = max(len(k) for k in result)
    for key, value in result.items():
        print(f"{key:<{width}}  {' '.join(value) if isinstance(value, list) else value}")
    if json_path:
        write_json({**result, "provenance": provenance()}, json_path)
        print(f"wrote {json_path}")


def cmd_bench_env(args: argparse.Namespace) -> int:
    from train.bench_env import run

    print_measurement(run(args.steps, args.seed), args.json)
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from train.config import Budget
    from train.trainer import train

    budget = Budget(
        max_steps=args.max_steps,
        max_episodes=args.max_episodes,
        checkpoint_every=args.checkpoint_every,
        eval_every=args.eval_every,
        stop_at_criterion=not args.keep_training,
    )
    out = args.resume or args.out
    if out is None:
        raise UsageError("give --out DIR for a new run or --resume DIR to continue one")
    summary = train(
        args.algo, args.preset, args.seed, out, budget, resume=args.resume is not None, progress=True
    )
    for key, value in summary.items():
        print(f"{key:<36}  {value}")
    print(f"wrote {out}/ (model.zip, config.json, curve.csv, summary.json, progress.png, checkpoint/, tb/)")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from train.bench import run_bench

    table = run_bench(
        args.algos, args.seeds, args.preset, args.out, args.max_steps, args.eval_episodes, args.workers
    )
    print(table)
    print(f"wrote {args.out}/bench.md and bench.json")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="embedrl", description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("eval", help="evaluate a policy on seeded episodes; table, JSON report, plot")
    _add_policy_arguments(p)
    p.add_argument("--episodes", type=_positive, default=200)
    p.add_argument("--seed", type=int, default=0, help="episode i is reset with seed + i")
    p.add_argument("--json", type=Path, help="write the JSON report here")
    p.add_argument("--plot", type=Path, help="write the trajectories over the map here (PNG)")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("render", help="write one episode as an animated GIF or a PNG strip")
    _add_policy_arguments(p)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True, help="file.gif (animation) or file.png (strip)")
    p.set_defaults(func=cmd_render)

    from train.config import ALGOS, PRESETS

    p = sub.add_parser("train", help="train an SB3 agent on the warehouse env (stop criterion, checkpoints)")
    p.add_argument("--algo", choices=ALGOS, default="td3")
    p.add_argument("--scenario", choices=["static"], default="static")
    p.add_argument("--preset", choices=PRESETS, default="tuned")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, help="new run directory")
    p.add_argument("--resume", type=Path, help="continue the run in this directory from its last checkpoint")
    p.add_argument("--max-steps", type=_positive, default=300_000)
    p.add_argument("--max-episodes", type=_positive, default=100_000)
    p.add_argument("--checkpoint-every", type=_positive, default=10_000)
    p.add_argument("--eval-every", type=_positive, default=5_000)
    p.add_argument(
        "--keep-training",
        action="store_true",
        help="record the stop criterion but train on to --max-steps (for policies to ship)",
    )
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("bench", help="train K seeds per algorithm in parallel; the study's table")
    p.add_argument("--scenario", choices=["static"], default="static")
    p.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS))
    p.add_argument("--seeds", type=_positive, default=5)
    p.add_argument("--preset", choices=PRESETS, default="tuned")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--max-steps", type=_positive, default=300_000)
    p.add_argument("--eval-episodes", type=_positive, default=200)
    p.add_argument("--workers", type=_positive, default=os.cpu_count() or 1)
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("bench-env", help="benchmark env steps per second (random actions, one core)")
    p.add_argument("--steps", type=_positive, default=50_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="write the measurement here")
    p.set_defaults(func=cmd_bench_env)

    for module in _package_clis():
        module.register(sub)
    return parser


def _package_clis() -> list[Any]:
    """The ``cli`` modules of the other packages that have one."""
    modules = []
    for name in OTHER_PACKAGES:
        try:
            modules.append(importlib.import_module(f"{name}.cli"))
        except ModuleNotFoundError as exc:
            if exc.name != f"{name}.cli":
                raise
    return modules


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handled: tuple[type[Exception], ...] = (TrainError, OSError, ValueError, json.JSONDecodeError)
    for module in _package_clis():
        handled += getattr(module, "ERRORS", ())
    try:
        return int(args.func(args))
    except handled as exc:
        if args.debug:
            traceback.print_exc()
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
