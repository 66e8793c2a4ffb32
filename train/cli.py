"""The training package's subcommands: ``eval``, ``render``, ``train``, ``bench``, ``shaping`` and
``bench-env``.

:func:`register` adds them to the ``embedrl`` command (:mod:`embedrl.cli`).
"""

from __future__ import annotations

import argparse
import functools
import os
import shutil
import sys
from pathlib import Path
from typing import Any

from embedrl.common import on_terminal
from embedrl.train.arguments import (
    PORTABLE_HELP,
    add_policy_arguments,
    add_scenario_argument,
    env_id_of,
    policy_from,
    seed,
)
from embedrl.train.errors import TrainError, UsageError
from embedrl.train.scenarios import DEFAULT_SCENARIO


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def cmd_eval(args: argparse.Namespace) -> int:
    from embedrl.common import write_json
    from embedrl.train.evaluate import evaluate

    policy = policy_from(args)
    name = args.controller or str(args.model)
    from embedrl.train.scenarios import SCENARIOS

    report = evaluate(
        policy, args.episodes, args.seed, name, progress=on_terminal(), env_id=env_id_of(args),
        sample_time=SCENARIOS[args.scenario].sample_time_s,
    )  # fmt: skip
    print(report.table())
    if args.json:
        write_json(report.to_json(), args.json)
        print(f"wrote {args.json}")
    if args.plot:
        from embedrl.train.plots import plot_trajectories

        plot_trajectories(report, args.plot)
        print(f"wrote {args.plot}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    import gymnasium as gym
    import numpy as np

    from embedrl.train.rendering import save_episode
    from embedrl.train.scenarios import SCENARIOS

    sample_time = SCENARIOS[args.scenario].sample_time_s
    wheels = len(SCENARIOS[args.scenario].action) == 2  # the warehouse robots: caption the wheel forces
    if args.out.suffix.lower() not in (".gif", ".png"):
        raise UsageError(f"cannot write {args.out}: use a .gif (animation) or .png (strip) file name")
    policy = policy_from(args)
    robots = SCENARIOS[args.scenario].robots
    extra = {"partner": policy} if robots > 1 else {}  # one policy drives every robot
    env = gym.make(env_id_of(args), render_mode="rgb_array", **extra)
    obs, info = env.reset(seed=args.seed)
    frames: list[np.ndarray] = [env.unwrapped.render()]  # type: ignore[list-item]
    captions = ["t = 0.0 s"]
    while True:
        action = np.asarray(policy(obs), dtype=float).reshape(-1)
        obs, _, terminated, truncated, info = env.step(action)
        frames.append(env.unwrapped.render())  # type: ignore[arg-type]
        forces = f"   F_L {action[0]:+.2f}   F_R {action[1]:+.2f}" if wheels else ""  # what drove this frame
        captions.append(f"t = {len(captions) * sample_time:.{1 if sample_time >= 0.1 else 2}f} s{forces}")
        if terminated or truncated:
            break
    env.close()
    save_episode(frames, args.out, sample_time, captions)
    outcome = "success" if info["is_success"] else "collision" if info["collided"] else "timeout"
    print(f"wrote {args.out}: {len(frames) - 1} steps, {outcome}")
    return 0


def cmd_reward_field(args: argparse.Namespace) -> int:
    from embedrl.train.plots import plot_reward_field
    from embedrl.train.scenarios import WALKER

    if args.scenario == WALKER.name:
        raise UsageError(
            "the walker has no map: its reward is the deck's per-step sum (docs/walker.md); reward-field "
            "draws the warehouse scenarios' potential field"
        )
    if args.out.suffix.lower() != ".png":
        raise UsageError(f"cannot write {args.out}: use a .png file name")
    plot_reward_field(args.scenario, args.out)
    print(f"wrote {args.out}")
    return 0


def cmd_bench_env(args: argparse.Namespace) -> int:
    from embedrl.common import print_measurement
    from embedrl.train.env_throughput import run

    print_measurement(run(args.steps, args.seed), args.json)
    return 0


def cmd_bench_train(args: argparse.Namespace) -> int:
    from embedrl.common import print_measurement
    from embedrl.train.train_throughput import run

    print_measurement(run(args.steps, args.seed, args.scenario), args.json)
    return 0


TRAIN_DEFAULTS: dict[str, Any] = {
    "algo": "td3",
    "scenario": DEFAULT_SCENARIO,
    "preset": "tuned",
    "seed": 0,
    "max_steps": 300_000,
    "max_episodes": 100_000,
    "checkpoint_every": 10_000,
    "eval_every": 5_000,
    "eval_episodes": 100,
    "stop": "validation",
}
"""A new run's defaults. Unset on the command line (None), so that ``--resume`` can tell a flag that was
given from one that was not: a resumed run takes everything from its own config.json."""


def _read_preset(args: argparse.Namespace) -> None:
    """``--preset``: a name, or a preset file (its preset, its changes before those of ``--set``)."""
    from embedrl.train.config import PRESETS
    from embedrl.train.tune import read_preset_file

    if args.preset is None or args.preset in PRESETS:
        return
    if not args.preset.endswith(".json"):
        raise UsageError(f"--preset {args.preset}: use {' or '.join(PRESETS)}, or a preset file (.json)")
    try:
        args.preset, changes = read_preset_file(Path(args.preset))
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    args.set = [*changes, *args.set]


def cmd_tune(args: argparse.Namespace) -> int:
    from embedrl.train.config import preset, untrained_budget
    from embedrl.train.tune import Search, run_tune

    optimize = None
    if args.ray is not None:
        from embedrl.train.sweep import check_ray_address
        from embedrl.train.tune_ray import optimize_on_ray

        check_ray_address(args.ray)
        optimize = functools.partial(optimize_on_ray, address=args.ray, workers=args.workers)
    search = Search(args.algo, args.scenario, args.max_steps, args.out, args.seed, args.preset)
    idle = untrained_budget(preset(args.algo, args.preset, args.scenario), args.max_steps)
    if idle is not None:
        _warn(f"{idle} (in every trial); give a larger --max-steps")
    fresh = not args.out.exists()
    try:
        best = run_tune(search, args.trials, optimize)
    except BaseException as exc:
        if fresh and not any((args.out / "trials").glob("*")):  # nothing trained: leave nothing behind
            shutil.rmtree(args.out, ignore_errors=True)
        if isinstance(exc, RuntimeError):  # no trial finished its budget
            raise UsageError(str(exc)) from None
        raise
    untrained = " (UNTRAINED: no trial had a training update)" if best["untrained"] else ""
    print(f"best: trial {best['trial']}, validation success {100 * best['validation_success']:.0f}%"
          f"{untrained}, {' '.join(best['overrides'])}")  # fmt: skip
    preset_file = args.out / "best_preset.json"
    print(f"wrote {preset_file} (embedrl train --preset {preset_file}), trials.md, study.db, trials/")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from embedrl.train.checkpoints import read_run_config
    from embedrl.train.config import Budget
    from embedrl.train.trainer import train

    if (args.resume is None) == (args.out is None):
        raise UsageError("give --out DIR for a new run or --resume DIR to continue one (not both)")
    if args.workers is not None:
        return _train_with_workers(args)
    if args.portable:
        from embedrl.train.portable import restart_portable

        restart_portable(args.argv, args.as_command)
    if args.keep_training:
        if args.stop not in (None, "budget"):
            raise UsageError(f"--keep-training means --stop budget, not --stop {args.stop}")
        args.stop = "budget"
    _read_preset(args)
    given = {k: getattr(args, k) for k in TRAIN_DEFAULTS if getattr(args, k) is not None}
    if args.resume is not None:
        if args.set:
            raise UsageError("--set changes a new run's hyperparameters; a resumed run keeps its own")
        saved = read_run_config(args.resume)
        if saved.get("machine", {}).get("portable") and not args.portable:
            raise UsageError(f"{args.resume} was trained with --portable: resume it with --portable")
        own = {
            "algo": saved["algo"],
            "scenario": saved.get("scenario", DEFAULT_SCENARIO),
            "preset": saved["preset"],
            "seed": saved["seed"],
            **{
                k: saved["budget"][k] for k in ("max_steps", "max_episodes", "checkpoint_every", "eval_every")
            },
            "eval_episodes": saved["budget"].get("eval_episodes", TRAIN_DEFAULTS["eval_episodes"]),
            "stop": saved["budget"].get("stop", "validation"),
        }
        longer = given.get("max_steps", 0) > own["max_steps"]  # training on past the budget is allowed
        # training on past the budget, and past the stop rule to it (--keep-training), is allowed
        conflicts = [
            f"--{k.replace('_', '-')} {v} (the run has {own[k]})"
            for k, v in given.items()
            if own[k] != v and not (longer and (k == "max_steps" or (k == "stop" and v == "budget")))
        ]
        if conflicts:
            raise UsageError(
                f"--resume continues {args.resume} as it was configured; drop " + ", ".join(conflicts)
            )
        values = {**own, "max_steps": max(own["max_steps"], given.get("max_steps", 0))}
        if longer and given.get("stop") == "budget":
            values["stop"] = "budget"
    else:
        values = {**TRAIN_DEFAULTS, **given}
    budget = Budget(
        max_steps=values["max_steps"],
        max_episodes=values["max_episodes"],
        checkpoint_every=values["checkpoint_every"],
        eval_every=values["eval_every"],
        eval_episodes=values["eval_episodes"],
        stop=values["stop"],
    )
    out = args.resume or args.out
    summary = train(
        values["algo"],
        values["preset"],
        values["seed"],
        out,
        budget,
        resume=args.resume is not None,
        progress=on_terminal(),
        overrides=args.set,
        scenario=values["scenario"],
        warn=lambda why: _warn(f"{why}; give a larger --max-steps or --set learning_starts=N"),
    )
    for key, value in summary.items():
        print(f"{key:<36}  {value}")
    written = sorted(p.name + ("/" if p.is_dir() else "") for p in out.iterdir())
    print(f"wrote {out}/ ({', '.join(written)})")
    if summary["untrained"]:
        _warn(f"{out / 'model.zip'} is an untrained policy: it never had a training update")
    return 0


def _train_with_workers(args: argparse.Namespace) -> int:
    """``train --workers N``: TD3 with Ray experience workers (:mod:`train.parallel`)."""
    from embedrl.train.config import Budget
    from embedrl.train.parallel import train_parallel
    from embedrl.train.sweep import check_ray_address

    if args.resume is not None or args.algo not in (None, "td3") or args.portable:
        raise UsageError("--workers trains TD3 in a new run (--out DIR): no --resume, --algo or --portable")
    check_ray_address(args.ray)
    given = {k: getattr(args, k) for k in TRAIN_DEFAULTS if getattr(args, k) is not None}
    values = {**TRAIN_DEFAULTS, **given}
    budget = Budget(
        max_steps=values["max_steps"], eval_every=values["eval_every"], eval_episodes=values["eval_episodes"],
        stop="budget",
    )  # fmt: skip
    summary = train_parallel(
        values["preset"], values["seed"], args.out, budget, args.workers, args.block, args.ray,
        values["scenario"], args.set,
    )  # fmt: skip
    for key, value in summary.items():
        print(f"{key:<36}  {value}")
    print(f"wrote {args.out}/ ({', '.join(sorted(p.name for p in args.out.iterdir()))})")
    return 0


def _warn(message: str) -> None:
    """One line on stderr that the command goes on although its result may not be what was wanted."""
    print(f"warning: {message}", file=sys.stderr)


def _warn_untrained(algo: str, config: Any, max_steps: int) -> None:
    """A sweep's warning that an algorithm's runs will train nothing (the budget within the warm-up)."""
    from embedrl.train.config import untrained_budget

    idle = untrained_budget(config, max_steps)
    if idle is not None:
        _warn(f"{algo}: {idle} (in every run); give a larger --max-steps or --set learning_starts=N")


def cmd_bench(args: argparse.Namespace) -> int:
    from embedrl.train.config import preset, with_overrides
    from embedrl.train.study_benchmark import run_bench

    if args.portable:
        from embedrl.train.portable import restart_portable

        restart_portable(args.argv, args.as_command)
    for algo in args.algos:  # a bad --set fails here, in one line, before any run starts
        try:
            config = with_overrides(preset(algo, args.preset, args.scenario), args.set)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        if not args.from_runs:
            _warn_untrained(algo, config, args.max_steps)

    if args.ray is not None:
        from embedrl.train.sweep import check_ray_address

        check_ray_address(args.ray)
    if args.from_runs:
        from embedrl.train.study_benchmark import table_from

        print(table_from(args.from_runs, args.out))
        print(f"wrote {args.out}/bench.md and bench.json")
        return 0
    table, failures = run_bench(
        args.algos, args.seeds, args.preset, args.out, args.max_steps, args.eval_episodes, args.workers,
        args.seed_offset, args.scenario, tuple(args.set), args.ray,
    )  # fmt: skip
    print(table)
    print(f"wrote {args.out}/bench.md and bench.json (each run's folder under {args.out}/runs)")
    if failures:
        print(
            f"{len(failures)} run(s) failed (listed under the table); the table holds the others",
            file=sys.stderr,
        )
    return 1 if failures else 0


def cmd_shaping(args: argparse.Namespace) -> int:
    import math

    from embedrl.train.config import preset, with_overrides
    from embedrl.train.shaping_bench import FROM_SCRATCH, run_shaping

    if not (math.isfinite(args.gain) and args.gain >= 0):
        raise UsageError(f"--gain must be a finite number >= 0, got {args.gain}")
    for algo in args.algos:  # a bad --set fails here, in one line, before any run starts
        try:
            config = with_overrides(
                preset(algo, args.preset, args.scenario), [*FROM_SCRATCH[algo], *args.set]
            )
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        _warn_untrained(algo, config, args.max_steps)
    if args.ray is not None:
        from embedrl.train.sweep import check_ray_address

        check_ray_address(args.ray)
    table = run_shaping(
        args.algos, args.seeds, args.seed_offset, args.preset, args.out, args.max_steps, args.eval_episodes,
        args.workers, args.gain, tuple(args.set), args.ray, args.scenario, args.finished_only,
    )  # fmt: skip
    print(table)
    print(f"wrote {args.out}/shaping.md, shaping.json and shaping.png")
    return 0


def _add_run_set_arguments(p: argparse.ArgumentParser, max_steps: int) -> None:
    """The arguments of every command that trains a set of runs: overrides, output, budget, test
    episodes, workers."""
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="change one of the preset's hyperparameters in every run, e.g. --set success_bonus=20",
    )
    p.add_argument("--out", type=Path, required=True, help="the sweep's folder (tables, plots, runs/)")
    p.add_argument("--max-steps", type=_positive, default=max_steps, help="each run's training budget")
    p.add_argument(
        "--eval-episodes", type=_positive, default=200, help="test episodes of each trained policy"
    )
    p.add_argument("--workers", type=_positive, default=os.cpu_count() or 1,
                   help="runs at once on this machine (with --ray local: the CPUs Ray may use)")  # fmt: skip
    p.add_argument(
        "--ray", metavar="ADDRESS",
        help="run each (algorithm, seed) as a Ray task: local (a Ray instance here), auto (the cluster this "
        "machine joined with `ray start`) or HOST:PORT (default: a process pool on this machine)",
    )  # fmt: skip


def register(sub: Any) -> None:
    p = sub.add_parser("eval", help="evaluate a policy on seeded episodes; table, JSON report, plot")
    add_policy_arguments(p)
    p.add_argument("--episodes", type=_positive, default=200, help="episodes to run")
    p.add_argument("--seed", type=seed, default=0, help="episode i is reset with seed + i")
    p.add_argument("--json", type=Path, help="write the JSON report here")
    p.add_argument("--plot", type=Path, help="write the trajectories over the map here (PNG)")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("render", help="write one episode as an animated GIF or a PNG strip")
    add_policy_arguments(p)
    p.add_argument("--seed", type=seed, default=0, help="the episode's reset seed")
    p.add_argument("--out", type=Path, required=True, help="file.gif (animation) or file.png (strip)")
    p.set_defaults(func=cmd_render)
    _register_train(sub)
    _register_sweeps(sub)
    _register_tune(sub)

    p = sub.add_parser("reward-field", help="plot the potential-field reward over a scenario's map (PNG)")
    add_scenario_argument(p)
    p.add_argument("--out", type=Path, required=True, help="file.png")
    p.set_defaults(func=cmd_reward_field)

    p = sub.add_parser(
        "bench-train", help="TD3's env steps per CPU second while learning: SB3's torch against sbx-rl's JAX"
    )
    p.add_argument("--scenario", choices=["walker"], default="walker", help="the scenario (default: walker)")
    p.add_argument(
        "--steps", type=_positive, default=5_000, help="learning steps per backend (default: 5000)"
    )
    p.add_argument("--seed", type=int, default=0, help="the runs' seed (default: 0)")
    p.add_argument("--json", type=Path, help="write the result here")
    p.set_defaults(func=cmd_bench_train)

    p = sub.add_parser("bench-env", help="benchmark env steps per second (random actions, one core)")
    p.add_argument("--steps", type=_positive, default=50_000, help="env steps to time")
    p.add_argument("--seed", type=seed, default=0, help="the env's and the random actions' seed")
    p.add_argument("--json", type=Path, help="write the measurement here")
    p.set_defaults(func=cmd_bench_env)


def _register_train(sub: Any) -> None:
    from embedrl.train.config import ALGOS, PRESETS, STOP_RULES

    p = sub.add_parser("train", help="train an SB3 agent on the warehouse env (stop criterion, checkpoints)")
    p.add_argument("--algo", choices=ALGOS, help=f"the algorithm {_default('algo')}")
    add_scenario_argument(p, default=None)
    p.add_argument(
        "--preset", metavar="NAME|FILE",
        help=f"{' or '.join(PRESETS)}, or a preset file that `embedrl tune` wrote (best_preset.json: a "
        f"preset and its changes) {_default('preset')}",
    )  # fmt: skip
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="change one of the preset's hyperparameters, e.g. --set learning_rate=3e-4 (repeatable)",
    )
    p.add_argument("--seed", type=seed, help=f"the run's seed {_default('seed')}")
    p.add_argument("--out", type=Path, help="new run directory")
    p.add_argument(
        "--resume",
        type=Path,
        help="continue the run in this directory from its last checkpoint, with its own configuration "
        "(flags that contradict it are refused, except a larger --max-steps: training on)",
    )
    p.add_argument("--max-steps", type=_positive, help=f"env steps at most {_default('max_steps')}")
    p.add_argument("--max-episodes", type=_positive, help=f"episodes at most {_default('max_episodes')}")
    p.add_argument("--checkpoint-every", type=_positive,
                   help=f"env steps between checkpoints {_default('checkpoint_every')}")  # fmt: skip
    p.add_argument("--eval-every", type=_positive,
                   help=f"env steps between validation evaluations {_default('eval_every')}")  # fmt: skip
    p.add_argument("--eval-episodes", type=_positive,
                   help=f"episodes per validation evaluation {_default('eval_episodes')}")  # fmt: skip
    p.add_argument(
        "--stop",
        choices=STOP_RULES,
        help="what ends the run before --max-steps: validation (a validation evaluation reaches the target "
        f"success), study (the scenario's criterion: the study's 50-episode average >= 2; the walker's, the "
        f"deck's 250-episode average >= 1000) or budget {_default('stop')}",
    )
    p.add_argument("--keep-training", action="store_true", help="the same as --stop budget")
    p.add_argument("--portable", action="store_true", help=PORTABLE_HELP)
    p.add_argument(
        "--workers", type=_positive,
        help="TD3 with N asynchronous experience workers (Ray actors) and one learner, as the deck's "
        "parallel training; a new run only",
    )  # fmt: skip
    p.add_argument(
        "--block", type=_positive, default=32, help="transitions a worker sends at a time (default: 32)"
    )
    p.add_argument(
        "--ray", default="local", metavar="ADDRESS",
        help="with --workers: local (Ray on this machine) or a running cluster's address (HOST:PORT, auto) "
        "(default: local)",
    )  # fmt: skip
    p.set_defaults(func=cmd_train)


def _default(name: str) -> str:
    """A new run's default as the help states it (the option itself defaults to None: see TRAIN_DEFAULTS)."""
    return f"(default: {TRAIN_DEFAULTS[name]})"


def _register_tune(sub: Any) -> None:
    from embedrl.train.config import ALGOS, PRESETS

    p = sub.add_parser(
        "tune", help="search an algorithm's hyperparameters with Optuna; success on validation seeds"
    )
    p.add_argument("--algo", choices=ALGOS, required=True, help="the algorithm whose preset is searched")
    add_scenario_argument(p)
    p.add_argument("--preset", choices=PRESETS, default="tuned", help="the preset the search changes")
    p.add_argument("--trials", type=_positive, default=20, help="trials in total (a resumed search counts "
                   "the ones it has)")  # fmt: skip
    p.add_argument("--max-steps", type=_positive, default=100_000, help="each trial's training budget")
    p.add_argument("--seed", type=seed, default=0, help="the sampler's and every trial's training seed")
    p.add_argument("--out", type=Path, required=True, help="the study's folder (study.db, trials/, results)")
    p.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="run the trials with Ray Tune: local (a Ray instance "
        "here), auto (the cluster this machine joined) or HOST:PORT (default: one by one here)",
    )
    p.add_argument("--workers", type=_positive, default=os.cpu_count() or 1,
                   help="with --ray local: trials at once (the CPUs Ray may use)")  # fmt: skip
    p.set_defaults(func=cmd_tune)


def _register_sweeps(sub: Any) -> None:
    """``bench`` (the study's table) and ``shaping`` (from scratch, with and without shaping)."""
    from embedrl.train.config import ALGOS, PRESETS, STUDY_ALGOS

    p = sub.add_parser("bench", help="train K seeds per algorithm in parallel; the study's table")
    add_scenario_argument(p)
    p.add_argument(
        "--algos", nargs="+", choices=ALGOS, default=list(STUDY_ALGOS), help="the algorithms to train"
    )
    p.add_argument("--seeds", type=_positive, default=5, help="training seeds per algorithm")
    p.add_argument(
        "--seed-offset",
        type=seed,
        default=0,
        help="train seeds OFFSET .. OFFSET + SEEDS - 1 (new seeds to try)",
    )
    p.add_argument("--preset", choices=PRESETS, default="tuned", help="every run's preset")
    _add_run_set_arguments(p, 300_000)
    p.add_argument("--portable", action="store_true", help=PORTABLE_HELP)
    p.add_argument(
        "--from", dest="from_runs", nargs="+", type=Path, metavar="DIR",
        help="train nothing: the table again from benches' run folders (DIR/runs/*/result.json), e.g. those "
        "machines of a cluster wrote",
    )  # fmt: skip
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser(
        "shaping",
        help="train from scratch with the study's reward and with potential-based shaping (the walker: the "
        "deck's four reward stages); table and curves",
    )
    add_scenario_argument(p)
    p.add_argument(
        "--algos", nargs="+", choices=ALGOS, default=list(STUDY_ALGOS), help="the algorithms to train"
    )
    p.add_argument("--seeds", type=_positive, default=5, help="training seeds per algorithm")
    p.add_argument("--seed-offset", type=seed, default=300, help="train seeds OFFSET .. OFFSET + SEEDS - 1")
    p.add_argument(
        "--preset", choices=PRESETS, default="tuned", help="every run's preset, without its demonstrations"
    )
    p.add_argument("--gain", type=float, default=1.0, help="shaping potential per metre of way to the goal")
    p.add_argument(
        "--finished-only", action="store_true",
        help="train nothing: the table and curves of the runs that finished this budget (their models tested "
        "again), the others named (the same command without it trains them, resuming interrupted ones)",
    )  # fmt: skip
    _add_run_set_arguments(p, 1_000_000)
    p.set_defaults(func=cmd_shaping)


ERRORS: tuple[type[Exception], ...] = (TrainError,)
