"""Per-stage wall time and peak memory, for ``report.json`` and the benchmarks."""

from __future__ import annotations

import resource
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field


def _reset_peak_rss() -> bool:
    # Writing 5 to clear_refs resets the kernel's high-water mark of this process's RSS
    # (Linux ≥ 4.0), which is what makes a per-stage peak measurable.
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float:
    """Peak resident memory (MiB) since the last reset, or since the process started."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


@dataclass
class StageTimer:
    """Records the wall time and peak RSS of named stages.

    Use ``with timer.stage("fit"): ...``; ``timer.stages`` then maps each name to
    ``{"seconds": …, "peak_rss_mb": …}``.
    """

    stages: dict[str, dict[str, float]] = field(default_factory=dict)
    per_stage_peak: bool = True

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        if not _reset_peak_rss():
            self.per_stage_peak = False
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.stages[name] = {
                "seconds": round(time.perf_counter() - t0, 3),
                "peak_rss_mb": round(peak_rss_mb(), 1),
            }
