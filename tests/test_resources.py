"""CPUs and memory as a cluster's job or a container sees them (ptmcore.resources), from fake
cgroup trees, the real affinity, and the run's memory plan."""

from __future__ import annotations

import os
from pathlib import Path

import psutil
import pytest

from ptmcore import resources
from ptmcore.resources import _cgroup_available, _cgroup_cpus, available_memory_mb, cpu_count, thread_count

GIB = 1 << 30
NO_LIMIT_V1 = "9223372036854771712"


def _files(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")
    return root


def test_cgroup_v2_job_limits_memory_and_cpus(tmp_path):
    # A job's group with a limit, a step inside it without one: the job's limit holds; the
    # file cache it may drop (inactive_file) is room too.
    root = _files(tmp_path, {
        "proc/self/cgroup": "0::/job/step",
        "sys/fs/cgroup/cgroup.controllers": "cpu memory",
        "sys/fs/cgroup/job/memory.max": str(4 * GIB),
        "sys/fs/cgroup/job/memory.current": str(2 * GIB),
        "sys/fs/cgroup/job/memory.stat": f"anon {GIB}\ninactive_file {GIB // 2}",
        "sys/fs/cgroup/job/cpu.max": "150000 100000",
        "sys/fs/cgroup/job/step/memory.max": "max",
        "sys/fs/cgroup/job/step/memory.current": str(2 * GIB),
        "sys/fs/cgroup/job/step/cpu.max": "max 100000",
    })
    assert _cgroup_available(root) == pytest.approx(2.5 * GIB)
    assert _cgroup_cpus(root) == pytest.approx(1.5)


def test_cgroup_v1_slurm_job(tmp_path):
    # Slurm's groups under separate controller mounts: the job's limit, unlimited parents.
    job = "slurm/uid_1000/job_42/step_0"
    root = _files(tmp_path, {
        "proc/self/cgroup": f"7:cpu,cpuacct:/{job}\n4:memory:/{job}\n1:name=systemd:/",
        "sys/fs/cgroup/memory/memory.limit_in_bytes": NO_LIMIT_V1,
        "sys/fs/cgroup/memory/slurm/uid_1000/job_42/memory.limit_in_bytes": str(2 * GIB),
        "sys/fs/cgroup/memory/slurm/uid_1000/job_42/memory.usage_in_bytes": str(GIB + GIB // 2),
        "sys/fs/cgroup/memory/slurm/uid_1000/job_42/memory.stat": f"cache 1\ntotal_inactive_file {GIB}",
        f"sys/fs/cgroup/memory/{job}/memory.limit_in_bytes": NO_LIMIT_V1,
        f"sys/fs/cgroup/cpu/{job}/cpu.cfs_quota_us": "-1",
        f"sys/fs/cgroup/cpu/{job}/cpu.cfs_period_us": "100000",
    })
    assert _cgroup_available(root) == pytest.approx(1.5 * GIB)
    assert _cgroup_cpus(root) is None  # Slurm binds CPUs by affinity, not by quota


def test_cgroup_v1_container_sees_its_group_at_the_mount(tmp_path):
    # docker run --memory 1g --cpus 3 on a v1 host: /proc/self/cgroup names the host's path,
    # which does not exist inside; the mount point is the container's group.
    root = _files(tmp_path, {
        "proc/self/cgroup": "5:memory:/docker/abc\n3:cpu,cpuacct:/docker/abc",
        "sys/fs/cgroup/memory/memory.limit_in_bytes": str(GIB),
        "sys/fs/cgroup/memory/memory.usage_in_bytes": str(GIB // 4),
        "sys/fs/cgroup/cpu/cpu.cfs_quota_us": "300000",
        "sys/fs/cgroup/cpu/cpu.cfs_period_us": "100000",
    })
    assert _cgroup_available(root) == pytest.approx(0.75 * GIB)
    assert _cgroup_cpus(root) == pytest.approx(3.0)


def test_no_cgroup_means_no_limit(tmp_path):
    assert _cgroup_available(tmp_path) is None and _cgroup_cpus(tmp_path) is None
    root = _files(tmp_path / "garbled", {"proc/self/cgroup": "not a cgroup line",
                                         "sys/fs/cgroup/memory/memory.limit_in_bytes": "lots"})
    assert _cgroup_available(root) is None


def test_a_full_group_leaves_no_room(tmp_path):
    root = _files(tmp_path, {
        "proc/self/cgroup": "0::/",
        "sys/fs/cgroup/cgroup.controllers": "memory",
        "sys/fs/cgroup/memory.max": str(GIB),
        "sys/fs/cgroup/memory.current": str(2 * GIB),
    })
    assert _cgroup_available(root) == 0


def test_quota_and_affinity_bound_cpu_count(monkeypatch):
    machine = cpu_count()
    assert 1 <= machine <= (os.cpu_count() or 1)
    monkeypatch.setattr(resources, "_cgroup_cpus", lambda root: 0.5)
    assert cpu_count() == 1  # half a CPU of quota: one thread
    assert thread_count(None) == thread_count(0) == 1 and thread_count(3) == 3  # the caller's choice stands
    monkeypatch.setattr(resources, "_cgroup_cpus", lambda root: None)
    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no CPU affinity on this system")
    before = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {min(before)})  # taskset -c N
        assert cpu_count() == 1
    finally:
        os.sched_setaffinity(0, before)


def test_available_memory_is_the_smaller_of_machine_and_group(monkeypatch):
    machine = psutil.virtual_memory().available / 2**20
    assert 0 < available_memory_mb() <= machine * 1.1  # the machine's figure moves a little
    monkeypatch.setattr(resources, "_cgroup_available", lambda root: 300 * 2**20)
    assert available_memory_mb() == pytest.approx(300)


def test_run_plans_its_stack_by_the_groups_memory(monkeypatch, tmp_path):
    # A small stack stays in memory when the machine has room; inside a job whose group has
    # little left, the same run puts it in a file (and says why).
    import numpy as np

    from ptmcore.png import write_png
    from reconstruct.pipeline import RunOptions
    from reconstruct.pipeline import capture as capture_module

    paths = []
    for k in range(3):
        paths.append(tmp_path / f"p{k}.png")
        write_png(paths[-1], np.full((40, 50, 3), 100, np.uint8))
    monkeypatch.setattr(capture_module, "available_memory_mb", lambda: 1e6)
    assert not capture_module.plan_stack(paths, RunOptions()).on_disk
    monkeypatch.setattr(capture_module, "available_memory_mb", lambda: 100.0)
    plan = capture_module.plan_stack(paths, RunOptions())
    assert plan.short and plan.on_disk
    where, warnings = capture_module._stack_place(paths, RunOptions(), tmp_path)
    assert where == tmp_path and "did not fit in the available memory" in warnings[0]
