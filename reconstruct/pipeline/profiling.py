"""Per-stage wall time and memory of a run, and its progress, for ``report.json``.

Memory is the process's resident set size sampled while a stage runs (every 20 ms, and at the
stage's start and end), not the kernel's high-water mark: resetting that mark is process-wide
(two runs in one process, threads or a Dask worker, would reset each other's) and hides the
true peak from ``/usr/bin/time``, ``wait4`` and cluster schedulers, which measure from outside.
A sampled peak can miss a spike shorter than the interval; the whole-process peak from outside
cannot.
"""

from __future__ import annotations

import os
import resource
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

__all__ = ["ProgressFn", "StageTimer", "Stages", "current_rss_mb", "peak_rss_mb"]

#: ``progress(stage, done, total)``, called as the work of a stage advances.
ProgressFn = Callable[[str, int, int], None]

_SAMPLE_SECONDS = 0.02
_PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20 if hasattr(os, "sysconf") else 0.0


def current_rss_mb() -> float | None:
    """The process's resident memory now (MiB), or None where ``/proc`` is missing."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * _PAGE_MB
    except (OSError, ValueError, IndexError):
        return None


def peak_rss_mb() -> float:
    """The process's peak resident memory since it started (MiB)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


class _Sampler:
    """Samples the resident memory in a daemon thread until stopped; keeps the largest."""

    def __init__(self) -> None:
        self.peak = current_rss_mb()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="rss-sampler")
        if self.peak is not None:
            self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(_SAMPLE_SECONDS):
            self.peak = max(self.peak, current_rss_mb() or 0.0)

    def stop(self) -> float | None:
        if self.peak is None:
            return None
        self._stop.set()
        self._thread.join()
        return max(self.peak, current_rss_mb() or 0.0)


@dataclass
class StageTimer:
    """Records the wall time and the peak resident memory of named stages.

    Use ``with timer.stage("fit"): ...``; ``timer.stages`` then maps each name to
    ``{"seconds": …, "peak_rss_mb": …}``. Where the resident memory cannot be sampled (no
    ``/proc``), the peak is the process's since it started, and :attr:`scope` says so.
    """

    stages: dict[str, dict[str, float]] = field(default_factory=dict)
    scope: str = "per stage (sampled)"
    started: float = field(default_factory=time.perf_counter)

    def elapsed(self) -> float:
        """Wall-clock seconds since the timer was made."""
        return time.perf_counter() - self.started

    def start(self, name: str) -> Callable[[], None]:
        """Start timing stage ``name``; call what is returned when it ends (once). For a stage
        that runs beside others (files written in the background), whose times then overlap."""
        sampler = _Sampler()
        t0 = time.perf_counter()

        def stop() -> None:
            peak = sampler.stop()
            if peak is None:
                peak, self.scope = peak_rss_mb(), "process since start"
            self.stages[name] = {"seconds": round(time.perf_counter() - t0, 3), "peak_rss_mb": round(peak, 1)}

        return stop

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        stop = self.start(name)
        try:
            yield
        finally:
            stop()


class Stages:
    """Times the stages of one run and reports their progress.

    ``with stages("normals", total=h) as advance: ...`` times the stage and calls
    ``progress("normals", done, total)`` as ``advance(k)`` is called; stages without steps of
    their own show 0/1 then 1/1. A stage begun with :meth:`begin` and left open by an error is
    ended by :meth:`close` (``with Stages(progress) as stages:`` closes them all), so that its
    memory sampler stops.
    """

    def __init__(self, progress: ProgressFn | None = None) -> None:
        self.timer = StageTimer()
        self.progress = progress
        self._open: dict[int, Callable[..., None]] = {}

    def __enter__(self) -> Stages:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End the stages still open, without completing their progress."""
        for end in list(self._open.values()):
            end(complete=False)

    @contextmanager
    def __call__(self, name: str, total: int = 1) -> Iterator[Callable[[int], None]]:
        advance, end = self.begin(name, total)
        try:
            yield advance
        except BaseException:
            end(complete=False)
            raise
        end()

    def begin(self, name: str, total: int = 1) -> tuple[Callable[[int], None], Callable[..., None]]:
        """Start stage ``name`` of ``total`` steps; return ``advance(k)`` (callable from any
        thread) and ``end(complete=True)``, which records its time and, unless told not to (a
        failed stage), completes its progress. For a stage that runs beside others;
        :meth:`__call__` is the usual ``with`` form."""
        done = [0]
        lock = threading.Lock()

        def advance(k: int) -> None:
            with lock:
                done[0] += k
                if self.progress is not None:
                    self.progress(name, done[0], total)

        if self.progress is not None:
            self.progress(name, 0, total)
        stop = self.timer.start(name)

        def end(complete: bool = True) -> None:
            if self._open.pop(id(end), None) is None:
                return  # ended already
            stop()
            with lock:
                left = total - done[0] if complete else 0
            if left > 0:
                advance(left)

        self._open[id(end)] = end
        return advance, end
