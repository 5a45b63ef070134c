"""The compiled robust photometric stereo and the 8-bit stack against the NumPy steps they replace.

For each synthetic scene (tablet, sphere; 512×384, 48 lights, cast shadows, noise, and a
specular highlight so the robust weights have work to do) and encoding (16-bit TIFF, 8-bit
JPEG), the default normals (robust photometric stereo, IRLS) are computed three ways:

* ``numpy``: the NumPy steps of ``ptmcore.robust`` on the uint16 stack (the code before the
  kernel; ``compiled=False``);
* ``kernel``: ``ptmcore.robust_photometric_stereo`` (the numba kernel) on the same stack;
* ``kernel 8-bit``: the kernel on the stack as the pipeline now stores 8-bit photographs
  (``load_stack(storage="auto")``; TIFFs stay 16-bit).

Reports the mean angular error against the ground truth, the largest difference from the NumPy
result, and the time of each (one thread, after a warm-up call). Target: within 0.01° of the
NumPy steps' mean error.

Then the kernels' speed at the pipeline's width: the 8-bit stack of each JPEG scene tiled to 6000
columns (the width of a 24-megapixel photograph), as seconds per 24 megapixels with one and two
threads (medians of three), for the default normals, the robust PTM with its debiased normals,
and the robust PTM's maxima (``ptmcore.normals.normals_from_ptm``, ``--normals ptm``).

Last, the robust PTM (``ptmcore.robustptm.robust_ptm``, ``--normals ptm-debiased``) the same
three ways: the NumPy steps (``compiled=False``), and the kernel that fits the PTM with each
pixel's final robust weights, on the uint16 and the 8-bit stack: the debiased normals' mean
error, their largest difference from the NumPy steps', the coefficients' largest difference
(relative to the largest coefficient) and the time (one thread, after a warm-up call).

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/robust_kernel.py`` (one thread for the
NumPy steps' matrix products too); writes ``benchmarks/results/robust_kernel.json``.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import ptmcore  # noqa: E402
from data_synthetic import write_capture  # noqa: E402
from ptmcore.normals import normals_from_ptm  # noqa: E402
from ptmcore.robustptm import robust_ptm  # noqa: E402
from reconstruct.surface.accuracy import load_ground_truth, normal_accuracy  # noqa: E402

#: Columns of a 24-megapixel photograph (6000×4000).
WIDE = 6000


def angle(a, b):
    a, b = a.astype(np.float64), b.astype(np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def timed(f):
    f()  # warm-up: compilation or caches
    t0 = time.perf_counter()
    out = f()
    return out, time.perf_counter() - t0


def seconds_per_24mp(stack: ptmcore.ImageStack, directions: np.ndarray, threads: int,
                     fit=ptmcore.robust_photometric_stereo) -> float:
    """``fit``'s time on ``stack`` tiled to :data:`WIDE` columns, scaled to 24 megapixels."""
    _, h, w = stack.luminance.shape
    codes = np.ascontiguousarray(np.tile(stack.luminance, (1, 1, -(-WIDE // w)))[:, :, :WIDE])
    wide = ptmcore.ImageStack(codes, np.ones((h, WIDE, 3), np.float32), [], stack.bit_depth, stack.linearized,
                              stack.saturated, stack.table)
    times = [timed(lambda: fit(wide, directions, threads=threads))[1] for _ in range(3)]
    return statistics.median(times) * 24e6 / (h * WIDE)


def ptm_normals(stack: ptmcore.ImageStack, directions: np.ndarray, threads: int) -> np.ndarray:
    """``--normals ptm``: the robust PTM's maxima."""
    return normals_from_ptm(robust_ptm(stack, directions, threads=threads).ptm.coefficients, threads=threads)


def main() -> None:
    rows = []
    speed = []
    ptm_rows = []
    for scene in ("tablet", "sphere"):
        for encoding in ("tiff16", "jpeg8"):
            with tempfile.TemporaryDirectory() as tmp:
                info = write_capture(Path(tmp) / "cap", scene=scene, shape=(384, 512), n_lights=48,
                                     encoding=encoding, specular=0.4, seed=0)
                lights = ptmcore.read_lp(info.lp_path)
                truth = load_ground_truth(info.ground_truth_dir)
                stack16 = ptmcore.load_stack(lights.paths)
                stack8 = ptmcore.load_stack(lights.paths, storage="auto")
                ref, t_ref = timed(lambda: ptmcore.robust_photometric_stereo(stack16, lights.directions, threads=1,
                                                                          compiled=False).normals)
                results = {"numpy": (ref, t_ref)}
                for name, stack in (("kernel", stack16), ("kernel 8-bit", stack8)):
                    results[name] = timed(lambda stack=stack: ptmcore.robust_photometric_stereo(
                        stack, lights.directions, threads=1).normals)
                for name, (normals, seconds) in results.items():
                    rows.append({"scene": scene, "encoding": encoding, "method": name,
                                 "stack": str(stack8.luminance.dtype if name == "kernel 8-bit" else stack16.luminance.dtype),
                                 "mean_deg": normal_accuracy(normals, truth)["mean_deg"],
                                 "max_diff_from_numpy_deg": float(angle(normals, ref).max()),
                                 "seconds": seconds})
                ref_ptm, t_ref = timed(lambda: robust_ptm(stack16, lights.directions, threads=1, compiled=False))
                scale = float(np.abs(ref_ptm.ptm.coefficients).max())
                for name, stack in (("numpy", stack16), ("kernel", stack16), ("kernel 8-bit", stack8)):
                    fitted, seconds = ((ref_ptm, t_ref) if name == "numpy" else
                                       timed(lambda stack=stack: robust_ptm(stack, lights.directions, threads=1)))
                    ptm_rows.append({"scene": scene, "encoding": encoding, "method": name,
                                     "stack": str(stack.luminance.dtype),
                                     "mean_deg": normal_accuracy(fitted.normals, truth)["mean_deg"],
                                     "max_diff_from_numpy_deg": float(angle(fitted.normals, ref_ptm.normals).max()),
                                     "max_coefficient_diff": float(np.abs(fitted.ptm.coefficients
                                                                          - ref_ptm.ptm.coefficients).max()) / scale,
                                     "seconds": seconds})
                if encoding == "jpeg8":
                    for fit_name, fit in (("robust photometric stereo", ptmcore.robust_photometric_stereo),
                                          ("robust PTM, debiased normals", robust_ptm),
                                          ("robust PTM, maxima (--normals ptm)", ptm_normals)):
                        speed.append({"scene": scene, "fit": fit_name, "stack": str(stack8.luminance.dtype),
                                      **{f"seconds_per_24mp_{t}_threads": seconds_per_24mp(stack8, lights.directions,
                                                                                           t, fit)
                                         for t in (1, 2)}})
    print("| scene | encoding | method | stack | mean ° | max difference from NumPy ° | seconds (1 thread) |")
    print("| --- | --- | --- | --- | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['scene']} | {r['encoding']} | {r['method']} | {r['stack']} | {r['mean_deg']:.4f} | "
              f"{r['max_diff_from_numpy_deg']:.5f} | {r['seconds']:.3f} |")
    print(f"\n| scene | fit | stack | seconds per 24 MP, {WIDE} wide, 1 thread | 2 threads |")
    print("| --- | --- | --- | ---: | ---: |")
    for r in speed:
        print(f"| {r['scene']} | {r['fit']} | {r['stack']} | {r['seconds_per_24mp_1_threads']:.2f} | "
              f"{r['seconds_per_24mp_2_threads']:.2f} |")
    print("\nRobust PTM (debiased normals):\n")
    print("| scene | encoding | method | stack | mean ° | max difference from NumPy ° | max coefficient difference "
          "(relative) | seconds (1 thread) |")
    print("| --- | --- | --- | --- | ---: | ---: | ---: | ---: |")
    for r in ptm_rows:
        print(f"| {r['scene']} | {r['encoding']} | {r['method']} | {r['stack']} | {r['mean_deg']:.4f} | "
              f"{r['max_diff_from_numpy_deg']:.5f} | {r['max_coefficient_diff']:.1e} | {r['seconds']:.3f} |")
    meta = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "python": platform.python_version()}
    out = ROOT / "benchmarks" / "results" / "robust_kernel.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"meta": meta, "rows": rows, "speed": speed, "robust_ptm": ptm_rows}, indent=2) + "\n")
    print(f"\n{meta['date']}, {meta['machine']}; written {out}")


if __name__ == "__main__":
    main()
