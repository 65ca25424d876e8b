"""Rendered data sets: parallel generation seeded per chunk, and the ``.npz`` cache."""

from __future__ import annotations

import json
import math
import multiprocessing as mp
from collections.abc import Callable
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..engine import ray_installed, run_tasks

CHUNK = 50  # samples per job; job k draws from np.random.default_rng([seed, k])


def render_many(render_chunk: Callable, n: int, seed: int, conf: dict | None, workers: int, desc: str, unit: str = "img") -> list:
    """``n`` samples from ``render_chunk((seed, k, count, conf)) -> list``, in order.

    Chunks are seeded by (seed, chunk index), so the result does not depend on ``workers``
    nor on where they run: on Ray's ``workers`` CPUs where it is installed
    (:func:`markerpose.engine.run_tasks`), else in ``workers`` forked processes (a
    machine without Ray, e.g. a GPU machine that trains), or in this process for 1.
    """
    jobs = [(seed, k, min(CHUNK, n - k * CHUNK), conf) for k in range(math.ceil(n / CHUNK))]
    with tqdm(total=n, desc=desc, unit=unit) as bar:
        tasks = [(render_chunk, job) for job in jobs]
        if workers > 1 and len(jobs) > 1 and not ray_installed():
            with mp.get_context("fork").Pool(min(workers, len(jobs))) as pool:
                chunks = []
                for chunk in pool.imap(_chunk, tasks):
                    chunks.append(chunk)
                    bar.update(len(chunk))
        else:
            chunks = run_tasks(_chunk, tasks, workers=workers, on_result=lambda i, r: bar.update(len(r)), strict=True)
    return [sample for chunk in chunks for sample in chunk]


def _chunk(task, report=None) -> list:  # module level: Ray and the pool pickle it by name
    render_chunk, job = task
    return render_chunk(job)


def cached(path: Path, key: dict, make: Callable[[], dict]) -> dict:
    """The arrays stored at ``path`` if they were made with the same ``key``; else ``make()``, saved."""
    text = json.dumps(key, sort_keys=True, default=str)
    path = Path(path)
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            if "key" in z.files and str(z["key"]) == text:
                return {k: z[k] for k in z.files if k != "key"}
    data = make()
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, key=np.array(text), **data)
    return data


def draw(rng: np.random.Generator, conf: dict, key: str, default: Callable[[], float]):
    """``conf[key]`` if it is a value, a uniform draw if it is a (lo, hi) range, else ``default()``."""
    v = conf.get(key)
    if v is None:
        return default()
    return float(rng.uniform(*v)) if isinstance(v, (tuple, list)) else v


__all__ = ["CHUNK", "cached", "draw", "render_many"]
