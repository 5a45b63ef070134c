"""Where the decoding stage's time goes: the one decoding pass with and without each of its products.

``reconstruct run``'s decoding stage decodes each photograph once and reduces it
(:func:`ptmcore.reduce.reduce_photographs`) to the luminance stack (8-bit, in a file) and the
colour sums, and to the sums of HP's LRGB PTM. This times that pass on the speed benchmark's
capture (``benchmarks/speed.py --capture DIR`` makes it) in four ways, each in a fresh process
with 2 threads, alternating, ``--repeat`` times: the pass making nothing (decoding and the
kernel's loop alone), the stack only, the PTM sums only, and both (what a run does). Wall time
and the process's user and system CPU (``wait4``); medians.

Run: ``.venv/bin/python benchmarks/decode_parts.py --capture /tmp/speedcap [--repeat 3]``
Writes ``benchmarks/results/decode_parts.json``.
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

from procinfo import measured_run

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import glob, sys, tempfile, time
import numpy as np
from ptmcore.lp import read_lp
from ptmcore.ptmencoded import EncodedFit
from ptmcore.reduce import reduce_photographs
mode, capture = sys.argv[1], sys.argv[2]
lights = read_lp(glob.glob(capture + "/*.lp")[0])
paths = [str(p) for p in lights.paths]
fit = EncodedFit(np.asarray(lights.directions), "lrgb", encoding="srgb") if mode in ("ptm", "both") else None
stack = mode in ("stack", "both")
with tempfile.TemporaryDirectory(dir=capture) as scratch:
    t0 = time.perf_counter()
    reduce_photographs(paths, stack=stack, storage="auto", fit=fit, threads=2, on_disk=scratch if stack else None)
    print(time.perf_counter() - t0)
"""

MODES = {
    "none": "decoding and the kernel's loop, nothing made",
    "stack": "the 8-bit stack (in a file) and the colour sums",
    "ptm": "HP's LRGB PTM sums",
    "both": "both: what a run's decoding stage does",
}


def one(mode: str, capture: Path) -> dict:
    _, out, usage = measured_run([sys.executable, "-c", _CHILD, mode, str(capture)], stdout=subprocess.PIPE, cwd=ROOT,
                                 env={**os.environ, "PYTHONPATH": str(ROOT)})
    return {"seconds": float(out), "user_s": usage.ru_utime, "system_s": usage.ru_stime}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, required=True, help="a capture of benchmarks/speed.py")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    runs: dict[str, list[dict]] = {m: [] for m in MODES}
    for _ in range(args.repeat):
        for mode in MODES:
            runs[mode].append(one(mode, args.capture))
    med = {m: {k: statistics.median(r[k] for r in rs) for k in ("seconds", "user_s", "system_s")}
           for m, rs in runs.items()}
    meta = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "machine": f"{platform.machine()}, {os.cpu_count()} cores", "capture": str(args.capture),
            "repeat": args.repeat}
    print(f"medians of {args.repeat} ({meta['date']}, {meta['machine']}):")
    print("| the pass makes | seconds | user CPU s | system CPU s |\n| --- | ---: | ---: | ---: |")
    for m, v in med.items():
        print(f"| {MODES[m]} | {v['seconds']:.2f} | {v['user_s']:.1f} | {v['system_s']:.1f} |")
    out = ROOT / "benchmarks" / "results" / "decode_parts.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"meta": meta, "median": med, "runs": runs}, indent=2) + "\n")


if __name__ == "__main__":
    main()
