"""What this process may use of the machine: its CPUs and its memory.

``os.cpu_count()`` and the memory the system reports available describe the whole machine. A
run inside a cluster's job (Slurm binds a job to its CPUs and limits its memory with a cgroup),
a container (``docker run --cpus --memory``) or after ``taskset`` may use less: sized by the
machine, its threads would crowd a few CPUs and its stack, or a batch's workers, would be
killed for memory. :func:`cpu_count` and :func:`available_memory_mb` read the process's CPU
affinity and its cgroup (v1 or v2, from ``/proc/self/cgroup``: the job's own group, not only the
root a container sees) and give the smaller figure.

Why not ``dask.system.cpu_count`` (which reads the affinity and a CPU quota too): importing dask
takes about 0.09 s, at the start of every run, and it reads a version-1 quota only at the
hierarchy's root, not a job's group.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

__all__ = ["RUN_BASE_MB", "RUN_BYTES_PER_PIXEL", "available_memory_mb", "cpu_count", "thread_count"]

#: A run's peak memory beside its stack (the README's formula, 400 MB + 70 bytes per pixel):
#: the interpreter and libraries, and per pixel the fits' sums, colour, normals, height, mesh
#: and texture (benchmarks/speed.py). The pipeline plans a capture's stack with it; the
#: reduction sizes its groups of decoded photographs within it.
RUN_BASE_MB = 400
RUN_BYTES_PER_PIXEL = 70

#: A version-1 cgroup without a memory limit reports this or more (the largest page-aligned
#: 64-bit value): no limit.
_V1_NO_LIMIT = 1 << 62


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except (OSError, UnicodeDecodeError):
        return None


def _number(text: str | None) -> int | None:
    """A cgroup file's integer; None for ``max``, a negative (v1's ``-1``), a v1 "no limit" or
    anything unreadable."""
    try:
        value = int(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return value if 0 <= value < _V1_NO_LIMIT else None


def _cgroup_dirs(root: Path, controller: str) -> list[Path]:
    """The process's cgroup folders for ``controller`` (``memory`` or ``cpu``), innermost first,
    up to the hierarchy's mount point: a limit set on any of them applies.

    Version 2 (one hierarchy, ``/sys/fs/cgroup/cgroup.controllers``) and version 1 (a mount per
    controller, ``/sys/fs/cgroup/memory``, ``/sys/fs/cgroup/cpu``). A container that does not
    see its own group's path under the mount (a v1 bind mount) is the mount point itself.
    """
    lines = (_read(root / "proc/self/cgroup") or "").splitlines()
    fs = root / "sys/fs/cgroup"
    if (fs / "cgroup.controllers").exists():
        mount, rel = fs, next((ln.split(":", 2)[2] for ln in lines if ln.startswith("0::")), "/")
    else:
        mount = fs / controller
        rel = next((parts[2] for parts in (ln.split(":", 2) for ln in lines)
                    if len(parts) == 3 and controller in parts[1].split(",")), "/")
    if not mount.is_dir():
        return []
    here = mount / rel.strip("/")
    while not here.is_dir() and here != mount:
        here = here.parent
    dirs = [here]
    while here != mount:
        here = here.parent
        dirs.append(here)
    return dirs


def _cgroup_cpus(root: Path) -> float | None:
    """The CPU quota of the process's cgroup, in CPUs (quota / period), or None without one."""
    quotas = []
    for d in _cgroup_dirs(root, "cpu"):
        v2 = _read(d / "cpu.max")
        if v2 is not None:
            quota, _, period = v2.partition(" ")
            q, p = _number(quota), _number(period)
        else:
            q, p = _number(_read(d / "cpu.cfs_quota_us")), _number(_read(d / "cpu.cfs_period_us"))
        if q and p:
            quotas.append(q / p)
    return min(quotas, default=None)


def _cgroup_available(root: Path) -> float | None:
    """Bytes the process's cgroup may still take (its limit less what it holds, less the file
    cache it can drop), the least over the group and its parents; None without a limit."""
    room = []
    for d in _cgroup_dirs(root, "memory"):
        if (d / "memory.max").exists():  # v2
            limit, usage, inactive = _read(d / "memory.max"), _read(d / "memory.current"), "inactive_file"
        else:
            limit, usage, inactive = _read(d / "memory.limit_in_bytes"), _read(d / "memory.usage_in_bytes"), \
                "total_inactive_file"
        limit_b = _number(limit)
        if limit_b is None:
            continue
        stat = dict(ln.split(" ", 1) for ln in (_read(d / "memory.stat") or "").splitlines() if " " in ln)
        held = (_number(usage) or 0) - (_number(stat.get(inactive)) or 0)
        room.append(max(0, limit_b - max(0, held)))
    return min(room, default=None)


def cpu_count() -> int:
    """CPUs this process may use: those it may run on (its affinity: ``taskset``, Slurm's
    binding), no more than its cgroup's CPU quota (rounded up), at least one.

    The default number of threads of every parallel step (``threads=None``).
    """
    try:
        count = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        count = os.cpu_count() or 1
    quota = _cgroup_cpus(Path("/"))
    if quota is not None:
        count = min(count, math.ceil(quota))
    return max(1, count)


def thread_count(threads: int | None = None) -> int:
    """The threads of a parallel step: ``threads`` when the caller gives them (at least one),
    else :func:`cpu_count` (``threads=None``, the default of every step and of ``--threads``)."""
    return max(1, threads) if threads else cpu_count()


def available_memory_mb() -> float:
    """Memory this process may still take, MiB: the machine's available memory, no more than
    its cgroup's limit less what the group holds (the file cache it can drop not counted).

    The default ``--memory-limit`` of a run, and what ``reconstruct batch`` sizes a local
    cluster by.
    """
    import psutil  # 10 ms; only runs that plan their memory ask

    available = float(psutil.virtual_memory().available)
    group = _cgroup_available(Path("/"))
    if group is not None:
        available = min(available, group)
    return available / 2**20
