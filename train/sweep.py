"""Independent training runs of a sweep (``bench``, ``shaping``), on this machine's process pool or on Ray.

Ray (``--ray local``: a Ray instance on this machine; ``--ray auto``: the cluster this machine joined with
``ray start``; ``--ray HOST:PORT``: a cluster's head) runs one task per job with its resources declared
(one CPU each: the env and the networks are single-threaded). Results come back as each task ends; a task
that fails is reported with its error and the others go on. Every node of a cluster needs the same
installation and the sweep's output folder on a shared file system: each run writes its own folder.
"""

from __future__ import annotations

import multiprocessing
import socket
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any, TypeVar

from embedrl.common import on_terminal
from embedrl.train.errors import TrainError, UsageError

Job = TypeVar("Job")
CPUS_PER_RUN = 1
"""The resources a run declares to Ray: one core (torch is limited to one thread per run)."""
RAY_CONNECT_TIMEOUT_S = 3.0
"""How long ``--ray HOST:PORT`` may take to resolve and accept a TCP connection before it is refused (Ray
itself retries an unreachable head for minutes)."""


@dataclass(frozen=True)
class Failure:
    job: Any
    error: str
    """The exception's last line (``Type: message``)."""


def run_all(
    fn: Callable[[Job], dict[str, Any]], jobs: Sequence[Job], workers: int, ray: str | None = None,
    label: Callable[[Job], str] = str,
) -> tuple[list[dict[str, Any] | None], list[Failure]]:  # fmt: skip
    """``fn`` on every job: results in job order (None where it failed) and the failures; TrainError when
    every job failed (there is nothing to tabulate). One worker runs them here; more run in a pool of
    fresh interpreters (``spawn``: a forked child can inherit a lock some thread of this process held);
    ``ray`` runs them as Ray tasks."""
    from tqdm import tqdm

    results: list[dict[str, Any] | None] = [None] * len(jobs)
    failures: list[Failure] = []
    bar = tqdm(total=len(jobs), desc="runs", unit="run", disable=not on_terminal())

    def record(index: int, outcome: Callable[[], dict[str, Any]]) -> None:
        try:
            results[index] = outcome()
        except Exception as exc:  # one run's failure is reported; the sweep goes on
            failures.append(Failure(jobs[index], _last_line(exc)))
            bar.write(f"failed: {label(jobs[index])}: {_last_line(exc)}")
        bar.update()

    try:
        if ray is not None:
            _on_ray(fn, jobs, workers, ray, record)
        elif workers == 1:
            for index, job in enumerate(jobs):
                record(index, lambda: fn(job))  # noqa: B023  (called at once, within this turn)
        else:
            context = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
                futures = {pool.submit(fn, job): index for index, job in enumerate(jobs)}
                for future in as_completed(futures):
                    record(futures[future], future.result)
    finally:
        bar.close()
    if jobs and len(failures) == len(jobs):
        raise TrainError(
            f"every run failed ({len(jobs)}); the first: {label(failures[0].job)}: {failures[0].error}"
        )
    return results, failures


def _on_ray(
    fn: Callable[[Job], dict[str, Any]], jobs: Sequence[Job], workers: int, address: str,
    record: Callable[[int, Callable[[], dict[str, Any]]], None],
) -> None:  # fmt: skip
    import ray

    local = address == "local"
    if not ray.is_initialized():
        ray.init(
            address=None if local else address, num_cpus=workers if local else None,
            include_dashboard=False, log_to_driver=False, configure_logging=False,
        )  # fmt: skip
    try:
        task = ray.remote(num_cpus=CPUS_PER_RUN, max_retries=0)(fn)
        pending = {task.remote(job): index for index, job in enumerate(jobs)}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            index = pending.pop(done[0])
            ref = done[0]
            record(index, lambda: dict(ray.get(ref)))  # noqa: B023  (called at once, within this turn)
    finally:
        if local:
            ray.shutdown()


def check_ray_address(address: str, timeout_s: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """Refuse a ``--ray`` address that is not ``local``, ``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``, or
    whose head does not accept a TCP connection within ``timeout_s`` (name lookup included): UsageError."""
    if address in ("local", "auto"):
        return
    host, _, port_text = address.removeprefix("ray://").rpartition(":")
    host = host.strip("[]")  # an IPv6 address in brackets
    if not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise UsageError(f"--ray {address}: give local, auto, HOST:PORT or ray://HOST:PORT")
    outcome: list[OSError | None] = []

    def connect() -> None:
        try:
            socket.create_connection((host, int(port_text)), timeout=timeout_s).close()
            outcome.append(None)
        except OSError as exc:
            outcome.append(exc)

    # in a thread: the name lookup has no timeout of its own
    worker = threading.Thread(target=connect, daemon=True)
    worker.start()
    worker.join(timeout_s + 0.5)
    if not outcome:
        raise UsageError(f"--ray {address}: no answer in {timeout_s:.0f} s (is a Ray head running there?)")
    if outcome[0] is not None:
        reason = outcome[0].strerror or str(outcome[0])
        raise UsageError(f"--ray {address}: cannot connect ({reason}; is a Ray head running there?)")


def _last_line(exc: BaseException) -> str:
    """An error's last meaningful line (Ray wraps a task's exception with the remote traceback)."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, BaseException):
        exc = cause
    lines = [line for line in str(exc).strip().splitlines() if line.strip()]
    return f"{type(exc).__name__}: {lines[-1] if lines else ''}"
