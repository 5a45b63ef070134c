"""Where the decoding stage's time goes: the one decoding pass with and without each of its products.

``reconstruct run``'s decoding stage decodes each photograph once and reduces it
(:func:`ptmcore.reduce.reduce_photographs`) to the luminance stack (8-bit, in a file) and the
colour sums, and to the sums of HP's LRGB PTM. This times that pass on the speed benchmark's
capture (``benchmarks/speed.py --capture DIR`` makes it) in four ways, each in a fresh process
with 2 threads, alternating, ``--repeat`` times: the pass making nothing (decoding and the
kernel's loop alone), the stack only, the PTM sums only, and both (what a run does). Wall time
and the process's user and system CPU (``wait4``); medians.

Then the reduction kernel alone (``ptmcore.reduce._reduce_rows``, one thread, no decoding and no
fresh memory): a few photographs of the capture, decoded once, added to sums and a stack already
touched, as if they were 48 photographs, for each product and for groups of 2, 4 and 8
photographs. The sums are read and written once per group, so a cost per sample that falls with
larger groups is the sums' memory traffic, and one that does not is the kernel's arithmetic.

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
sys.path.insert(0, str(ROOT))

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


#: The kernel alone: photographs per group, and what it makes (as MODES, without decoding).
GROUPS = (2, 4, 8)
KERNEL_MODES = {
    "none": "nothing (the kernel's loop)",
    "stack": "the 8-bit stack and the colour sums",
    "ptm": "HP's LRGB PTM sums",
    "both": "both",
}


def kernel_alone(capture: Path, repeat: int, rows: int = 1024) -> dict[str, dict[int, float]]:
    """Nanoseconds per sample (pixel × photograph) of the reduction kernel alone, by product
    and group size: medians of ``repeat``; ``rows`` rows of the capture's photographs."""
    import numpy as np
    import simplejpeg

    from ptmcore import reduce as rd
    from ptmcore.lp import read_lp
    from ptmcore.ptmencoded import HP_LUMA_WEIGHTS, EncodedFit

    lights = read_lp(next(capture.glob("*.lp")))
    n, big = len(lights.paths), max(GROUPS)
    photos = [simplejpeg.decode_jpeg(Path(p).read_bytes())[:rows].copy() for p in lights.paths[:big]]
    h, w = photos[0].shape[:2]
    u8 = np.dtype(np.uint8)
    tables = rd._Tables(True, None, n, "srgb")
    to8, _ = rd.srgb8_tables()
    hp = HP_LUMA_WEIGHTS.astype(np.float32)
    pinv = EncodedFit(np.asarray(lights.directions), "lrgb", encoding="srgb").matrices(n)[0]
    # Touched once here, so that no mode pays for fresh memory (that is the table above).
    lum8 = np.ones((n, h, w), np.uint8)
    sums = [np.ones(shape, np.float32) for shape in ((h, w, 3), (h, w, 6), (h, w, 5))]

    def timed(mode: str, group: int) -> float:
        stack, ptm = mode in ("stack", "both"), mode in ("ptm", "both")
        images = tuple(photos[:group] + [photos[0]] * (rd._BATCH - group))
        t0 = time.perf_counter()
        for k0 in range(0, n - group + 1, group):
            ks = np.arange(k0, k0 + group, dtype=np.int64)
            luts, wscale = tables.for_photographs(u8, ks)
            rd._reduce_rows(images, group, ks, 0, h, luts, wscale, rd._top(u8), rd._encoded_scale(u8),
                            tables.encoded(u8), None, lum8 if stack else None, to8 if stack else None,
                            sums[0] if stack else None, hp, pinv if ptm else None,
                            sums[1] if ptm else None, sums[2] if ptm else None, None, None, None, None)
        return (time.perf_counter() - t0) / (h * w * (n - n % group)) * 1e9

    cases = [(m, g) for m in KERNEL_MODES for g in GROUPS]
    for m, g in cases:
        timed(m, g)  # compiled (or loaded from numba's cache) before timing
    times: dict[tuple[str, int], list[float]] = {c: [] for c in cases}
    for _ in range(repeat):
        for c in cases:
            times[c].append(timed(*c))
    return {m: {g: statistics.median(times[m, g]) for g in GROUPS} for m in KERNEL_MODES}


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
    kernel = kernel_alone(args.capture, args.repeat)
    print(f"\nthe kernel alone, one thread, ns per sample (pixel × photograph), medians of {args.repeat}:")
    print("| the kernel makes | " + " | ".join(f"groups of {g}" for g in GROUPS) + " |")
    print("| --- |" + " ---: |" * len(GROUPS))
    for m, by_group in kernel.items():
        print(f"| {KERNEL_MODES[m]} | " + " | ".join(f"{by_group[g]:.2f}" for g in GROUPS) + " |")
    out = ROOT / "benchmarks" / "results" / "decode_parts.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"meta": meta, "median": med, "runs": runs, "kernel_ns_per_sample": kernel},
                              indent=2) + "\n")


if __name__ == "__main__":
    main()
