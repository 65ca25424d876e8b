"""Independent tasks over a few processes, with a progress bar."""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor, as_completed


def run_tasks(worker, tasks: list, jobs: int | None = None, desc: str = "", unit: str = "task", progress: bool = True) -> list:
    """``worker(task)`` for every task, in ``jobs`` processes (default: up to 2; 1: in this
    process). Results in the order they finish."""
    jobs = jobs or max(1, min(2, os.cpu_count() or 1, len(tasks)))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), desc=desc, unit=unit)
    out = []
    if jobs == 1:
        for t in tasks:
            out.append(worker(t))
            if bar:
                bar.update()
    else:
        with ProcessPoolExecutor(jobs) as ex:
            for f in as_completed([ex.submit(worker, t) for t in tasks]):
                out.append(f.result())
                if bar:
                    bar.update()
    if bar:
        bar.close()
    return out


__all__ = ["run_tasks"]
