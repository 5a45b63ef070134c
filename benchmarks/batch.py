"""``reconstruct batch`` against a loop of ``reconstruct run``, Dask's overhead, and resuming.

Makes (once; ``--captures DIR`` keeps and reuses them) 24 captures of 48 JPEGs of 1728×1152
(2 MP; one rendered tablet copied under 24 names: the work per object is what counts), then:

* the loop: ``reconstruct run`` of each capture in turn, as separate processes, ``--threads 2``;
* the batch: ``reconstruct batch`` of the 24 on the default local cluster (``--force``);
* resuming: the same batch again, every object complete (all skipped);
* Dask's overhead: 1,000 no-op tasks through the batch's own submission code on a local cluster;
* ``--only-resume N``: only resuming, of a finished batch of N small captures (48 × 64, 12
  photographs, one capture copied under N names), once made (its time is printed too).

Each figure is the median of ``--repeat`` runs (loop and batch alternated); peak memory is the
largest process's, from ``wait4`` (outside the processes; for the batch, the largest of its
workers and itself as the operating system reports them to the parent).

Run: ``.venv/bin/python benchmarks/batch.py [--repeat 3] [--captures DIR] [--only-resume N]``
Writes ``benchmarks/results/batch.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_synthetic.encoding import write_jpeg8  # noqa: E402
from data_synthetic.lights import dome_lights  # noqa: E402
from data_synthetic.render import render  # noqa: E402
from data_synthetic.surfaces import SCENES  # noqa: E402
from ptmcore.lp import write_lp  # noqa: E402

SHAPE = (1152, 1728)
PHOTOGRAPHS = 48
OBJECTS = 24
PIXEL_SIZE = 0.05
EXE = str(Path(sys.executable).with_name("reconstruct"))


def make_captures(root: Path) -> list[Path]:
    """24 capture folders of the same rendered tablet."""
    first = root / "object_00"
    names = [f"img_{k:03d}.jpg" for k in range(PHOTOGRAPHS)]
    if not (first / "lights.lp").exists():
        first.mkdir(parents=True, exist_ok=True)
        lights = dome_lights(PHOTOGRAPHS)
        surface = SCENES["tablet"](SHAPE, pixel_size=PIXEL_SIZE, seed=0)
        for k, name in enumerate(names):
            write_jpeg8(first / name, render(surface, lights[k : k + 1], cast_shadows=False, noise=0.01, seed=k)[0],
                        quality=95)
        write_lp(first / "lights.lp", names, lights)
    folders = [root / f"object_{k:02d}" for k in range(OBJECTS)]
    for folder in folders[1:]:
        if not (folder / "lights.lp").exists():
            shutil.copytree(first, folder, dirs_exist_ok=True)
    return folders


_WRAPPER = ("import resource, subprocess, sys; "
            "code = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL).returncode; "
            "print(code, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")


def timed(cmd: list[str]) -> tuple[float, float]:
    """Wall seconds and the largest process's peak RSS (MiB) of a command, from outside.

    A fresh wrapper process runs the command: its RUSAGE_CHILDREN covers the command and every
    descendant reaped (the batch's Dask workers), and nothing else.
    """
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", _WRAPPER, *cmd], capture_output=True, text=True, check=True)
    seconds = time.perf_counter() - t0
    status, peak_kb = (int(v) for v in done.stdout.split())
    if status != 0:
        raise SystemExit(f"{cmd[:2]} failed with status {status}")
    return seconds, peak_kb / 1024


def loop(folders: list[Path], out: Path) -> tuple[float, float]:
    t0, peak = time.perf_counter(), 0.0
    for folder in folders:
        _, p = timed([EXE, "run", str(folder), "-o", str(out / folder.name), "--pixel-size", str(PIXEL_SIZE),
                      "--threads", "2", "-q"])
        peak = max(peak, p)
    return time.perf_counter() - t0, peak


def batch(folders: list[Path], out: Path, *extra: str) -> tuple[float, float]:
    return timed([EXE, "batch", *map(str, folders), "-o", str(out), "--pixel-size", str(PIXEL_SIZE), "-q", *extra])


def _noop(k: int) -> int:
    return k


def dask_overhead(tasks: int = 1000) -> float:
    """Seconds per 100 no-op tasks submitted and gathered as the batch does it."""
    from distributed import Client, LocalCluster, as_completed

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=40) as cluster, Client(cluster) as client:
        client.submit(_noop, -1, pure=False).result()  # workers warm
        t0 = time.perf_counter()
        futures = [client.submit(_noop, k, pure=False, retries=1, key=f"noop-{k}") for k in range(tasks)]
        for future in as_completed(futures):
            future.result()
        return (time.perf_counter() - t0) * 100 / tasks


def only_resume(objects: int, repeat: int) -> None:
    """Seconds to run a finished batch of ``objects`` small captures again (median of ``repeat``)."""
    from data_synthetic import write_capture

    tmp = Path(tempfile.mkdtemp(prefix="ptm-resume-"))
    try:
        one = tmp / "one"
        write_capture(one, shape=(48, 64), n_lights=12, seed=3)
        drawer = tmp / "drawer"
        for k in range(objects):
            shutil.copytree(one, drawer / f"object_{k:04d}")
        made, _ = timed([EXE, "batch", str(drawer), "-o", str(tmp / "out"), "-q"])
        resumes = [timed([EXE, "batch", str(drawer), "-o", str(tmp / "out"), "-q"])[0] for _ in range(repeat)]
        print(f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores: a batch of {objects} "
              f"captures of 12 photographs of 64x48 made in {made:.1f} s; run again, all complete: "
              f"{statistics.median(resumes):.2f} s (median of {repeat}: {', '.join(f'{r:.2f}' for r in resumes)})")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--captures", type=Path, help="keep the generated captures here and reuse them")
    ap.add_argument("--only-resume", type=int, metavar="N", help="only resuming a finished batch of N small captures")
    args = ap.parse_args()
    if args.only_resume:
        only_resume(args.only_resume, args.repeat)
        return
    tmp = Path(tempfile.mkdtemp(prefix="ptm-batch-"))
    try:
        folders = make_captures(args.captures or tmp / "captures")
        loops, batches, resumes, per_object = [], [], [], []
        for r in range(args.repeat):
            loops.append(loop(folders, tmp / f"loop{r}"))
            batches.append(batch(folders, tmp / "batch", "--force"))
            per_object += [row["seconds"] for row in json.loads((tmp / "batch" / "batch.json").read_text())]
            resumes.append(batch(folders, tmp / "batch"))
            print(f"repeat {r + 1}: loop {loops[-1][0]:.1f} s, batch {batches[-1][0]:.1f} s, "
                  f"resume {resumes[-1][0]:.1f} s", flush=True)
        overhead = dask_overhead()
        med = {
            "loop_s": statistics.median(s for s, _ in loops), "batch_s": statistics.median(s for s, _ in batches),
            "resume_s": statistics.median(s for s, _ in resumes),
            "loop_peak_mb": statistics.median(p for _, p in loops),
            "batch_peak_mb": statistics.median(p for _, p in batches),
            "object_in_batch_s": statistics.median(per_object),
            "dask_s_per_100_tasks": overhead,
        }
        meta = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
                "objects": OBJECTS, "photographs": PHOTOGRAPHS, "size": f"{SHAPE[1]}x{SHAPE[0]}", "repeat": args.repeat}
        print(f"\n{OBJECTS} captures of {PHOTOGRAPHS} JPEGs of {SHAPE[1]}x{SHAPE[0]}, medians of {args.repeat} "
              f"({meta['date']}, {meta['machine']}):")
        print("| | seconds | objects per minute | peak RSS MB (largest process) |\n| --- | --- | --- | --- |")
        print(f"| loop of `reconstruct run` | {med['loop_s']:.1f} | {60 * OBJECTS / med['loop_s']:.1f} | "
              f"{med['loop_peak_mb']:.0f} |")
        print(f"| `reconstruct batch` | {med['batch_s']:.1f} | {60 * OBJECTS / med['batch_s']:.1f} | "
              f"{med['batch_peak_mb']:.0f} |")
        print(f"| resume (all {OBJECTS} complete) | {med['resume_s']:.1f} | | |")
        print(f"one object inside the batch: {med['object_in_batch_s']:.2f} s (median); "
              f"Dask: {overhead:.3f} s per 100 no-op tasks")
        out = ROOT / "benchmarks" / "results" / "batch.json"
        out.parent.mkdir(exist_ok=True)
        out.write_text(json.dumps({"meta": meta, "median": med, "loops": loops, "batches": batches,
                                   "resumes": resumes}, indent=2) + "\n")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
