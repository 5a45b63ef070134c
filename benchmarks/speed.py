"""Speed and memory of ``reconstruct run`` on a large JPEG capture, against decoding alone.

Generates (once; ``--capture DIR`` keeps and reuses it) a synthetic clay tablet of 48 JPEGs of
6000×4000 pixels, then, ``--repeat`` times in alternation:

* decode-only: the 48 JPEGs decoded with 2 threads by the project's decoder, nothing else;
* the whole ``reconstruct run`` as a separate process with ``--threads 2``: wall time, peak RSS
  (from ``wait4``, outside the process), and the per-stage times and sampled peaks from its
  ``report.json``.

Reports medians and the ratio run / decode-only (target ≤ 3, stretch 1.5; peak RSS ≤ 2 GB), and
the time of one run before them with an empty numba cache: the first run after installation,
which compiles the kernels.

Run: ``.venv/bin/python benchmarks/speed.py [--size 6000x4000] [--images 48] [--repeat 3]``
Writes ``benchmarks/results/speed_<size>.json``.
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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_synthetic.encoding import write_jpeg8  # noqa: E402
from data_synthetic.lights import dome_lights  # noqa: E402
from data_synthetic.render import render  # noqa: E402
from data_synthetic.surfaces import SCENES  # noqa: E402
from ptmcore.images import read_image  # noqa: E402
from ptmcore.lp import write_lp  # noqa: E402
from procinfo import measured_run  # noqa: E402

PIXEL_SIZE = 0.02


def make_capture(folder: Path, shape: tuple[int, int], n: int) -> list[Path]:
    """Render the tablet one light at a time (a 24-megapixel stack would not fit as float32)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"img_{k:03d}.jpg" for k in range(n)]
    lights = dome_lights(n)
    if (folder / "lights.lp").exists() and all((folder / nm).exists() for nm in names):
        return [folder / nm for nm in names]
    surface = SCENES["tablet"](shape, pixel_size=PIXEL_SIZE, seed=0)
    for k, name in enumerate(names):
        img = render(surface, lights[k : k + 1], cast_shadows=False, noise=0.01, seed=k)[0]
        write_jpeg8(folder / name, img, quality=95)
        print(f"\rrendered {k + 1}/{n}", end="", flush=True)
    print()
    write_lp(folder / "lights.lp", names, lights)
    return [folder / nm for nm in names]


def decode_only(paths: list[Path], threads: int) -> float:
    t0 = time.perf_counter()
    with ThreadPoolExecutor(threads) as pool:
        for _ in pool.map(read_image, paths):
            pass
    return time.perf_counter() - t0


def full_run(capture: Path, out: Path, threads: int, numba_cache: Path) -> dict:
    exe = Path(sys.executable).with_name("reconstruct")
    cmd = [str(exe), "run", str(capture), "-o", str(out), "--pixel-size", str(PIXEL_SIZE),
           "--threads", str(threads), "-q"]
    # numba's compiled kernels are cached here: an empty folder is the first run after
    # installation (compilation included), a filled one every later run.
    env = {**os.environ, "NUMBA_CACHE_DIR": str(numba_cache)}
    seconds, _, usage = measured_run(cmd, stdout=subprocess.DEVNULL, env=env)
    report = json.loads((out / "report.json").read_text())
    # The whole run's peak from outside (wait4); the per-stage peaks in report.json are the
    # resident memory the run sampled while each stage ran.
    # CPU time too: system time is mostly the first touch of memory (benchmarks/cold_memory.py).
    return {"seconds": seconds, "peak_rss_mb": usage.ru_maxrss / 1024, "user_s": usage.ru_utime,
            "system_s": usage.ru_stime, "stages": report["stages"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="6000x4000")
    ap.add_argument("--images", type=int, default=48)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--capture", type=Path, help="keep the generated capture here and reuse it")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    tmp = Path(tempfile.mkdtemp(prefix="ptm-speed-"))
    capture = args.capture or tmp / "capture"
    try:
        paths = make_capture(capture, (h, w), args.images)
        size_mb = sum(p.stat().st_size for p in paths) / 1e6
        decodes, runs = [], []
        first = full_run(capture, tmp / "out", args.threads, tmp / "numba-cache")
        print(f"first run after installation (kernels compiled): {first['seconds']:.1f} s", flush=True)
        for r in range(args.repeat):
            decodes.append(decode_only(paths, args.threads))
            runs.append(full_run(capture, tmp / "out", args.threads, tmp / "numba-cache"))
            print(f"repeat {r + 1}: decode-only {decodes[-1]:.1f} s, run {runs[-1]['seconds']:.1f} s, "
                  f"peak RSS {runs[-1]['peak_rss_mb']:.0f} MB", flush=True)
        stage_names = list(runs[0]["stages"])
        med = {
            "decode_only_s": statistics.median(decodes),
            "run_s": statistics.median(r["seconds"] for r in runs),
            "peak_rss_mb": statistics.median(r["peak_rss_mb"] for r in runs),
            "user_s": statistics.median(r["user_s"] for r in runs),
            "system_s": statistics.median(r["system_s"] for r in runs),
            "stages": {s: {"seconds": statistics.median(r["stages"][s]["seconds"] for r in runs),
                           "peak_rss_mb": statistics.median(r["stages"][s]["peak_rss_mb"] for r in runs)}
                       for s in stage_names},
        }
        med["ratio"] = med["run_s"] / med["decode_only_s"]
        med["first_run_s"] = first["seconds"]
        meta = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
                "python": platform.python_version(), "size": args.size, "images": args.images,
                "jpeg_total_mb": round(size_mb, 1), "repeat": args.repeat, "threads": args.threads}
        print(f"\n{args.images} JPEGs of {args.size} ({size_mb:.0f} MB), {args.threads} threads, "
              f"medians of {args.repeat} runs ({meta['date']}, {meta['machine']}):")
        print("| stage | seconds | peak RSS MB |\n| --- | --- | --- |")
        for s, v in med["stages"].items():
            print(f"| {s} | {v['seconds']:.2f} | {v['peak_rss_mb']:.0f} |")
        print(f"| **whole run** | {med['run_s']:.2f} | {med['peak_rss_mb']:.0f} |")
        print(f"| decode only | {med['decode_only_s']:.2f} | |")
        print(f"run CPU: {med['user_s']:.1f} s user, {med['system_s']:.1f} s system")
        print(f"ratio run / decode-only: {med['ratio']:.2f}; first run after installation "
              f"{first['seconds']:.2f} s")
        out = ROOT / "benchmarks" / "results" / f"speed_{args.size}.json"
        out.parent.mkdir(exist_ok=True)
        out.write_text(json.dumps({"meta": meta, "median": med, "runs": runs, "decode_only": decodes}, indent=2) + "\n")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
