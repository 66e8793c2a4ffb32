"""Training curves across seeds: each run's ``curve.csv`` put on a common env-step grid, and the median and
band over seeds (``bench``'s learning curves and ``shaping``'s comparison)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

GRID_POINTS = 200
"""Env-step points at which the seeds' curves are compared."""


def load(run: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(env steps, 50-episode average, episode length) per training episode of a run."""
    with (run / "curve.csv").open() as f:
        rows = list(csv.DictReader(f))
    return (
        np.array([int(r["steps"]) for r in rows], dtype=float),
        np.array([float(r["average50"]) for r in rows]),
        np.array([int(r["length"]) for r in rows], dtype=float),
    )


def on_grid(steps: np.ndarray, values: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """The last value at or before each grid point (NaN before the first episode); a run that stopped
    at the criterion keeps its last value."""
    index = np.searchsorted(steps, grid, side="right") - 1
    return np.where(index >= 0, values[np.clip(index, 0, None)], np.nan)


def median_band(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Median, worst and best over seeds (rows) at each grid point (NaN where no seed has a value)."""
    valid = ~np.all(np.isnan(curves), axis=0)
    median = np.full(curves.shape[1], np.nan)
    low, high = median.copy(), median.copy()
    median[valid] = np.nanmedian(curves[:, valid], axis=0)
    low[valid] = np.nanmin(curves[:, valid], axis=0)
    high[valid] = np.nanmax(curves[:, valid], axis=0)
    return median, low, high
