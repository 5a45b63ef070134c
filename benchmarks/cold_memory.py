"""What the first touch of fresh memory costs on this machine, against memory touched again.

A virtual machine whose balloon driver hands free pages back to the host (free page reporting)
pays, the first time a process touches such a page, a fault in the host as well as in the
guest. This measures it from outside the pipeline: a child process allocates ``--gb`` of
memory and writes one byte per page, after a pause long enough for the host to have taken back
what earlier runs freed; the same process then frees and touches as much again (warm). The
system CPU time of each touch is what a run pays for each gigabyte it holds at its peak (the
stack, the sums of the fits, the output files in the page cache).

Each is measured twice: with NumPy's default on Linux (``madvise(MADV_HUGEPAGE)`` on large
arrays: 2 MB pages where the kernel's transparent huge pages allow it), and with 4 KB pages
(NumPy's ``NUMPY_MADVISE_HUGEPAGE=0``).

    .venv/bin/python benchmarks/cold_memory.py --gb 1 --repeat 3
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The page sizes measured, by NumPy's NUMPY_MADVISE_HUGEPAGE.
_PAGES = {"huge": "1", "small": "0"}

_CHILD = r"""
import resource, sys, time
import numpy as np
def system(): return resource.getrusage(resource.RUSAGE_SELF).ru_stime
n = int(float(sys.argv[1]) * (1 << 30))
out = []
for _ in range(2):
    s0, t0 = system(), time.perf_counter()
    a = np.empty(n, np.uint8)
    a[::4096] = 1
    out.append((time.perf_counter() - t0, system() - s0))
    huge = sum(int(line.split()[1]) for line in open("/proc/self/smaps_rollup") if line.startswith("AnonHugePages"))
    del a
print(out[0][0], out[0][1], out[1][0], out[1][1], huge)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gb", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--pause", type=float, default=10.0, help="seconds before each run (the host takes pages back)")
    args = ap.parse_args()
    runs = []
    for _ in range(args.repeat):
        for pages, flag in _PAGES.items():
            time.sleep(args.pause)
            env = dict(os.environ, NUMPY_MADVISE_HUGEPAGE=flag)
            text = subprocess.run([sys.executable, "-c", _CHILD, str(args.gb)], capture_output=True, text=True,
                                  check=True, env=env).stdout
            cold_s, cold_sys, warm_s, warm_sys, huge_kb = (float(v) for v in text.split())
            runs.append({"pages": pages, "cold_s": cold_s, "cold_system_s": cold_sys, "warm_s": warm_s,
                         "warm_system_s": warm_sys, "huge_mb": huge_kb / 1024})
            print(f"{args.gb:g} GB, {pages} pages ({huge_kb / 1024:.0f} MB in huge pages): first touch {cold_s:.2f} s "
                  f"({cold_sys:.2f} s system), again {warm_s:.2f} s ({warm_sys:.2f} s system)", flush=True)
    med = {pages: {k: statistics.median(r[k] for r in runs if r["pages"] == pages) for k in runs[0] if k != "pages"}
           for pages in _PAGES}
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "gb": args.gb, "repeat": args.repeat, "pause_s": args.pause,
            "transparent_hugepage": _thp_setting()}
    for pages in _PAGES:
        print(f"medians, {pages} pages: first touch {med[pages]['cold_s'] / args.gb:.2f} s per GB, "
              f"again {med[pages]['warm_s'] / args.gb:.2f} s per GB")
    out = ROOT / "benchmarks" / "results" / "cold_memory.json"
    out.write_text(json.dumps({"meta": meta, "median": med, "runs": runs}, indent=2) + "\n")


def _thp_setting() -> str:
    """The kernel's transparent huge page mode (the bracketed word), or "unknown"."""
    try:
        text = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return "unknown"
    return text[text.find("[") + 1:text.find("]")] if "[" in text else text.strip()


if __name__ == "__main__":
    main()
