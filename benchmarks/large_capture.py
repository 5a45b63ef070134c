"""A capture larger than memory: ``reconstruct run`` on 100 JPEGs of 50 megapixels, measured
from outside, optionally inside a memory limit.

The README promises that such a capture runs on a 16 GB laptop: its stack (1 byte per sample,
4.7 GB) goes to a file whose pages leave the process, and the run's own peak is about
``400 MB + 70 bytes × W × H`` (``reconstruct.pipeline.capture.plan_stack``). This checks both
claims on a synthetic clay tablet (``benchmarks/speed.py``'s, rendered once; ``--capture DIR``
keeps and reuses it). Each run is a separate process, ``--threads 2``; measured from outside:

* wall time and CPU, and the peak resident memory (``wait4``);
* with ``--limit-mb`` (root, cgroup v1 or v2), the run inside a memory cgroup of that size and
  the cgroup's own peak, which counts the file cache as well (the stack's pages, the output
  files): on a machine of that size this is what the run may take before pages have to go to
  the disk. Without a cgroup (not root, or no memory controller) this is said and skipped;
* the most disk the output folder's file system lost while the run went on (``statvfs``,
  sampled every 0.2 s), against the README's ``N × W × H`` bytes of stack plus the outputs.

Run: ``.venv/bin/python benchmarks/large_capture.py --capture /tmp/cap50 --limit-mb 16000``
(``--size 8688x5792 --images 100`` by default). Writes
``benchmarks/results/large_<size>x<images>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from procinfo import cpu_model, measured_run  # noqa: E402
from speed import PIXEL_SIZE, make_capture  # noqa: E402

from reconstruct.pipeline import RunOptions  # noqa: E402
from reconstruct.pipeline.capture import plan_stack  # noqa: E402


class MemoryCgroup:
    """A memory cgroup of ``limit_mb`` MiB made for one process (v2 or v1), or None-like when
    this machine or user cannot make one (:attr:`why_not` says why)."""

    def __init__(self, limit_mb: int) -> None:
        self.path: Path | None = None
        self.why_not = ""
        root = Path("/sys/fs/cgroup")
        if (root / "cgroup.controllers").exists():  # v2
            path, limit_file, self.peak_file = root / f"ptm-bench-{os.getpid()}", "memory.max", "memory.peak"
        else:
            path, limit_file, self.peak_file = (root / "memory" / f"ptm-bench-{os.getpid()}", "memory.limit_in_bytes",
                                                "memory.max_usage_in_bytes")
        try:
            path.mkdir()
            (path / limit_file).write_text(str(limit_mb << 20))
        except OSError as exc:
            self.why_not = f"no memory cgroup ({path}: {exc.strerror})"
            if path.is_dir():
                path.rmdir()
            return
        self.path = path

    def enter(self) -> None:
        """Move the calling process into the cgroup (a ``preexec_fn``: the child, before exec)."""
        (self.path / "cgroup.procs").write_text(str(os.getpid()))

    def peak_mb(self) -> float | None:
        """The cgroup's peak usage, MiB (the file cache counted), or None when unknown."""
        try:
            return int((self.path / self.peak_file).read_text()) / 2**20
        except (OSError, ValueError):
            return None

    def remove(self) -> None:
        if self.path is not None:
            self.path.rmdir()


class DiskWatch:
    """The most disk a file system lost while it was watched (``statvfs``, every 0.2 s)."""

    def __init__(self, folder: Path) -> None:
        self.folder, self.most = folder, 0
        self._base = self._free()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _free(self) -> int:
        st = os.statvfs(self.folder)
        return st.f_bavail * st.f_frsize

    def _watch(self) -> None:
        while not self._stop.wait(0.2):
            self.most = max(self.most, self._base - self._free())

    def stop(self) -> float:
        """Stop watching; the most disk used, MB."""
        self._stop.set()
        self._thread.join()
        return self.most / 1e6


def one_run(capture: Path, out: Path, threads: int, limit_mb: int | None) -> dict:
    exe = Path(sys.executable).with_name("reconstruct")
    cmd = [str(exe), "run", str(capture), "-o", str(out), "--pixel-size", str(PIXEL_SIZE),
           "--threads", str(threads), "-q"]
    group = MemoryCgroup(limit_mb) if limit_mb else None
    if group is not None and group.path is None:
        print(f"--limit-mb {limit_mb}: {group.why_not}; the run is not limited", flush=True)
    limited = group is not None and group.path is not None
    disk = DiskWatch(out.parent)
    try:
        seconds, _, usage = measured_run(cmd, stdout=subprocess.DEVNULL,
                                         preexec_fn=group.enter if limited else None)
        cgroup_peak = group.peak_mb() if limited else None
    finally:
        disk_mb = disk.stop()
        if limited:
            group.remove()
    report = json.loads((out / "report.json").read_text())
    outputs_mb = sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) / 1e6
    return {"seconds": seconds, "peak_rss_mb": usage.ru_maxrss / 1024, "user_s": usage.ru_utime,
            "system_s": usage.ru_stime, "limit_mb": limit_mb if limited else None,
            "cgroup_peak_mb": cgroup_peak, "disk_most_mb": disk_mb, "outputs_mb": outputs_mb,
            "stack": report["inputs"].get("stack"), "report_peak_rss_mb": report.get("peak_rss_mb"),
            "stages": {k: {"seconds": v["seconds"], "peak_rss_mb": v.get("peak_rss_mb")}
                       for k, v in report["stages"].items()},
            "warnings": report.get("warnings", [])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="8688x5792", help="a 50-megapixel camera's frame (default)")
    ap.add_argument("--images", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--limit-mb", type=int, action="append", default=[],
                    help="run inside a memory cgroup of this size (MiB; root only); repeat for several runs")
    ap.add_argument("--capture", type=Path, help="keep the generated capture here and reuse it")
    ap.add_argument("--work", type=Path, help="where the output folder goes (default: a temporary folder)")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    tmp = Path(tempfile.mkdtemp(prefix="ptm-large-", dir=args.work))
    capture = args.capture or tmp / "capture"
    try:
        paths = make_capture(capture, (h, w), args.images)
        jpeg_mb = sum(p.stat().st_size for p in paths) / 1e6
        # What the run itself plans (the README's formula): its peak beyond the stack, the stack.
        plan = plan_stack(paths, RunOptions())
        predicted_rest, stack_mb = plan.rest_mb, plan.stack_mb
        runs = []
        for limit in args.limit_mb or [None]:
            out = tmp / "out"
            shutil.rmtree(out, ignore_errors=True)
            runs.append(one_run(capture, out, args.threads, limit))
            r = runs[-1]
            print(f"limit {limit or 'none'} MiB: {r['seconds']:.1f} s, peak RSS {r['peak_rss_mb']:.0f} MiB "
                  f"(predicted {predicted_rest:.0f}), cgroup peak {r['cgroup_peak_mb'] or float('nan'):.0f} MiB, "
                  f"disk at most {r['disk_most_mb']:.0f} MB (outputs {r['outputs_mb']:.0f} MB), "
                  f"stack: {r['stack']}", flush=True)
        meta = {"date": time.strftime("%Y-%m-%d %H:%M %Z"), "machine": f"{cpu_model()}, {os.cpu_count()} cores",
                "python": platform.python_version(), "size": args.size, "images": args.images,
                "jpeg_total_mb": round(jpeg_mb, 1), "threads": args.threads,
                "stack_mb": round(stack_mb), "predicted_peak_rss_mb": round(predicted_rest)}
        print(json.dumps(meta))
        for r in runs:
            print("| " + " | ".join(f"{k} {v['seconds']:.1f}" for k, v in r["stages"].items()) + " |")
        out_json = ROOT / "benchmarks" / "results" / f"large_{args.size}x{args.images}.json"
        out_json.parent.mkdir(exist_ok=True)
        out_json.write_text(json.dumps({"meta": meta, "runs": runs}, indent=2) + "\n")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
