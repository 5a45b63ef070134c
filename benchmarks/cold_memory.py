"""What the first touch of fresh memory costs on this machine, against memory touched again.

A virtual machine whose balloon driver hands free pages back to the host (free page reporting)
pays, the first time a process touches such a page, a fault in the host as well as in the
guest. This measures it from outside the pipeline: a child process allocates ``--gb`` of
memory and writes one byte per page, after a pause long enough for the host to have taken back
what earlier runs freed; the same process then frees and touches as much again (warm). The
system CPU time of each touch is what a run pays for each gigabyte it holds at its peak (the
stack, the sums of the fits, the output files in the page cache).

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
    del a
print(out[0][0], out[0][1], out[1][0], out[1][1])
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gb", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--pause", type=float, default=10.0, help="seconds before each run (the host takes pages back)")
    args = ap.parse_args()
    runs = []
    for _ in range(args.repeat):
        time.sleep(args.pause)
        text = subprocess.run([sys.executable, "-c", _CHILD, str(args.gb)], capture_output=True, text=True,
                              check=True).stdout
        cold_s, cold_sys, warm_s, warm_sys = (float(v) for v in text.split())
        runs.append({"cold_s": cold_s, "cold_system_s": cold_sys, "warm_s": warm_s, "warm_system_s": warm_sys})
        print(f"{args.gb:g} GB: first touch {cold_s:.2f} s ({cold_sys:.2f} s system), again {warm_s:.2f} s "
              f"({warm_sys:.2f} s system)", flush=True)
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "gb": args.gb, "repeat": args.repeat, "pause_s": args.pause}
    print(f"medians: first touch {med['cold_s'] / args.gb:.2f} s per GB, again {med['warm_s'] / args.gb:.2f} s per GB")
    out = ROOT / "benchmarks" / "results" / "cold_memory.json"
    out.write_text(json.dumps({"meta": meta, "median": med, "runs": runs}, indent=2) + "\n")


if __name__ == "__main__":
    main()
