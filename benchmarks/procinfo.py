"""Machine, memory and process figures shared by the benchmark scripts (Linux ``/proc``,
``wait4``)."""

from __future__ import annotations

import os
import platform
import resource
import subprocess
import time
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo``, else :func:`platform.processor`."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:  # not Linux
        lines = []
    return next((ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name")),
                platform.processor() or "cpu")


def status_mb(field: str) -> float:
    """A memory figure of this process (``VmRSS``, ``VmHWM``…) from ``/proc/self/status``, in
    MB; NaN when absent."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024  # kB
    return float("nan")


def measured_run(cmd: list[str], **popen) -> tuple[float, bytes | None, resource.struct_rusage]:
    """Run a command; its wall seconds, its standard output (with ``stdout=PIPE``) and its
    resource usage from ``wait4``: CPU times and peak RSS measured from outside the process.

    The child's peak starts at this process's own peak, which Linux copies into it at the fork:
    a benchmark that had rendered a large capture reported that as the run's peak (3468 MB for
    an 18-megapixel run that peaked at 1663). This process's peak is reset to its present
    resident memory first (``/proc/self/clear_refs``), so the figure is the child's, as long as
    the benchmark itself holds little at that moment.

    Raises SystemExit when the command fails.
    """
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:  # not Linux, or not allowed: the figure may then include this process's peak
        pass
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, **popen)
    out = proc.stdout.read() if proc.stdout is not None else None
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t0
    if status != 0:
        raise SystemExit(f"{' '.join(map(str, cmd[:3]))} … failed with status {status}")
    return seconds, out, usage
