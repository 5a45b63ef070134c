"""The first run on a machine: CPU seconds with an empty compiled-code cache, after
``reconstruct warm-up``, and warm.

A synthetic 512 × 384 capture of 49 photographs (16-bit TIFF, and 8-bit JPEG), reconstructed by
``reconstruct run`` as a separate process with the default options and with ``--normals ptm``,
its numba cache in a fresh folder (``NUMBA_CACHE_DIR``):

1. cold: the cache empty, as on a new machine, container or cluster node;
2. ``reconstruct warm-up`` in that cache (its own CPU seconds reported), then each run again:
   the first run after an installation that ran the warm-up (``make install`` does);
3. warm: each run once more.

CPU seconds (user + system, of the child, from ``wait4``), which the machine's other load does
not inflate as it does wall time; the median of ``--repeat`` for the warm runs.

Run: ``.venv/bin/python benchmarks/first_run.py [--repeat 3]``. Writes
``benchmarks/results/first_run.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_synthetic import write_capture  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from procinfo import cpu_model, measured_run  # noqa: E402

SHAPE = (384, 512)
LIGHTS = 49
#: The runs measured: label, encoding, extra options.
RUNS = (("default, 16-bit TIFF", "tiff16", ()), ("default, 8-bit JPEG", "jpeg8", ()),
        ("--normals ptm, 16-bit TIFF", "tiff16", ("--normals", "ptm")))


def cpu_seconds(args: list[str], env: dict) -> float:
    """User + system CPU seconds of a child process (and its children), from wait4."""
    usage = measured_run(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)[2]
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    exe = [sys.executable, "-m", "reconstruct"]
    result = {"machine": f"{cpu_model()}, {os.cpu_count()} CPUs", "date": time.strftime("%Y-%m-%d"),
              "shape": list(SHAPE), "lights": LIGHTS, "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        captures = {}
        for encoding in ("tiff16", "jpeg8"):
            info = write_capture(tmp / encoding, scene="tablet", shape=SHAPE, n_lights=LIGHTS, encoding=encoding,
                                 seed=2)
            captures[encoding] = (tmp / encoding, info.pixel_size)
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / "numba_cache"))

        def run(encoding: str, extra: tuple[str, ...], name: str) -> float:
            folder, pixel_size = captures[encoding]
            return cpu_seconds([*exe, "run", str(folder), "-o", str(tmp / name), "-q", "--pixel-size",
                                str(pixel_size), *extra], env)

        for label, encoding, extra in RUNS:
            result["runs"][label] = {"cold": round(run(encoding, extra, "cold"), 2)}
            print(f"{label}: cold {result['runs'][label]['cold']} s CPU", file=sys.stderr)
        # The cold runs filled the cache: a warm-up is measured in a cache of its own.
        env["NUMBA_CACHE_DIR"] = str(tmp / "numba_cache_warmed")
        result["warm_up"] = round(cpu_seconds([*exe, "warm-up"], env), 2)
        for label, encoding, extra in RUNS:
            r = result["runs"][label]
            r["after_warm_up"] = round(run(encoding, extra, "after"), 2)
            r["warm"] = round(statistics.median(run(encoding, extra, "warm") for _ in range(args.repeat)), 2)
            print(f"{label}: {r}", file=sys.stderr)
    print(f"Machine: {result['machine']}; {result['date']}; {SHAPE[1]} × {SHAPE[0]}, {LIGHTS} photographs")
    print(f"reconstruct warm-up: {result['warm_up']} s CPU\n")
    print("| run | cold cache | first run after warm-up | warm (median) |\n| --- | --- | --- | --- |")
    for label, r in result["runs"].items():
        print(f"| {label} | {r['cold']} s | {r['after_warm_up']} s | {r['warm']} s |")
    out = ROOT / "benchmarks" / "results" / "first_run.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
