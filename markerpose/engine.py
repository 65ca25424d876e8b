"""Independent tasks on Ray where it is installed, one after the other where it is not.

Ray (the ``ray`` extra) runs the tasks on this machine's cores by default (a local Ray
started for the run and stopped after it) or on a running cluster (``address``: what
``ray start --head`` printed, or ``auto``). A task whose worker dies (killed, out of
memory, its machine gone) is run again, up to ``max_retries`` times; an exception that the
task itself raises is not retried: it is that task's result, for the caller to report.
Without Ray the tasks run in this process, in order, with the same results.

The package imports Ray only here, and only when a run asks for it.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass


def ray_installed() -> bool:
    return importlib.util.find_spec("ray") is not None


@dataclass
class Failed:
    """A task that raised, or whose worker died more often than the retries allow."""

    reason: str


def _reason(exc: BaseException) -> str:
    """One line: the task's own exception where Ray wrapped it."""
    cause = getattr(exc, "cause", None)
    exc = cause if isinstance(cause, BaseException) else exc
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[-1] if text else ''}".rstrip(": ")


def _call(fn, task, report):
    try:
        return fn(task, report)
    except Exception as exc:  # the task's own failure: its result, not a retry
        return Failed(_reason(exc))


def run_tasks(
    fn: Callable,
    tasks: Sequence,
    *,
    workers: int | None = None,
    use_ray: bool | None = None,
    address: str | None = None,
    cpus_per_task: float = 1.0,
    max_retries: int = 3,
    on_result: Callable | None = None,
    on_progress: Callable[[int], None] | None = None,
    desc: str | None = None,
    unit: str = "task",
    progress: bool = False,
    strict: bool = False,
) -> list:
    """``fn(task, report)`` for every task; the results in the tasks' order, a :class:`Failed`
    for each task that raised (or whose worker died ``max_retries`` + 1 times); ``strict``
    raises instead, naming the task's error (for experiments, where a failure is a bug).

    ``fn`` must be importable by name (a module-level function) and its tasks picklable.
    ``report(n)`` inside a task adds ``n`` to the run's progress (e.g. frames done);
    ``on_progress(total)`` sees the total as it grows, ``on_result(i, result)`` each result
    as it arrives; with ``progress`` and ``desc``, a bar over the tasks.

    Where: ``use_ray`` None runs on Ray when it is installed (or ``address`` names a
    cluster) and there is more than one task and ``workers`` is not 1; else in this process,
    in order (with a one-line hint, where more workers were wanted and Ray is missing).
    ``workers``: the local Ray's CPUs (default: every core)."""
    parallel = len(tasks) > 1 and workers != 1
    if use_ray is None:
        use_ray = address is not None or (parallel and ray_installed())
        if not use_ray and parallel and progress:
            _hint()
    bar = None
    if progress and desc:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), desc=desc, unit=unit)

    def arrived(i, result):
        if strict and isinstance(result, Failed):
            raise RuntimeError(f"{desc or 'task'} {i} failed: {result.reason}")
        if bar is not None:
            bar.update()
        if on_result:
            on_result(i, result)

    try:
        if not use_ray:
            return _serial(fn, tasks, arrived, on_progress)
        return _on_ray(fn, tasks, address, workers, cpus_per_task, max_retries, arrived, on_progress)
    finally:
        if bar is not None:
            bar.close()


_HINTED: list = []


def _hint() -> None:
    if not _HINTED:
        _HINTED.append(True)
        print(
            "Ray is not installed: the tasks run here, one after the other (pip install 'markerpose[ray]' for every core)", file=sys.stderr
        )


def _serial(fn, tasks, on_result, on_progress) -> list:
    done = [0]

    def report(n: int) -> None:
        done[0] += n
        if on_progress:
            on_progress(done[0])

    out = []
    for i, task in enumerate(tasks):
        out.append(_call(fn, task, report))
        if on_result:
            on_result(i, out[-1])
    return out


def _on_ray(fn, tasks, address, workers, cpus_per_task, max_retries, on_result, on_progress) -> list:
    try:
        import ray
    except ImportError as exc:
        raise ValueError("Ray is not installed: pip install 'markerpose[ray]' (or leave out --address to run here)") from exc

    started = not ray.is_initialized()
    if started:
        os.environ.setdefault("RAY_DEDUP_LOGS", "0")
        kwargs = {"include_dashboard": False, "log_to_driver": False, "logging_level": "ERROR"}
        if address is None:
            kwargs["num_cpus"] = workers or os.cpu_count() or 1
        try:
            ray.init(address=address, **kwargs)
        except ConnectionError as exc:
            raise ValueError(f"no Ray cluster at {address}: {exc}") from exc
    try:
        counter = ray.remote(num_cpus=0)(_Counter).remote()
        remote = ray.remote(num_cpus=cpus_per_task, max_retries=max_retries)(_ray_task)
        refs = {remote.remote(fn, task, counter): i for i, task in enumerate(tasks)}
        out: list = [None] * len(tasks)
        pending, shown = list(refs), 0
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=0.5)
            for ref in ready:
                i = refs[ref]
                try:
                    out[i] = ray.get(ref)
                except ray.exceptions.RayError as exc:  # the worker died past its retries
                    out[i] = Failed(_reason(exc))
                if on_result:
                    on_result(i, out[i])
            if on_progress:
                total = ray.get(counter.total.remote())
                if total != shown:
                    shown = total
                    on_progress(total)
        return out
    finally:
        if started:
            ray.shutdown()


class _Counter:
    """The run's progress, added to by the tasks (a Ray actor)."""

    def __init__(self):
        self.n = 0

    def add(self, n: int) -> None:
        self.n += n

    def total(self) -> int:
        return self.n


class _Report:
    """``report(n)`` inside a Ray task: sent to the counter at most a few times a second."""

    def __init__(self, counter):
        self.counter, self.held, self.last = counter, 0, time.monotonic()

    def __call__(self, n: int) -> None:
        self.held += n
        if time.monotonic() - self.last > 0.25:
            self.flush()

    def flush(self) -> None:
        if self.held:
            self.counter.add.remote(self.held)
            self.held, self.last = 0, time.monotonic()


def _ray_task(fn, task, counter):
    report = _Report(counter)
    try:
        return _call(fn, task, report)
    finally:
        report.flush()


__all__ = ["Failed", "ray_installed", "run_tasks"]
