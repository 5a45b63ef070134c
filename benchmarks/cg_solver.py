"""Conjugate gradients of the masked integrator: a hand-written loop against scipy's ``cg``.

Both solvers get the same normal equations (those :func:`masked_poisson` builds), the same
warm start (the bounding-box DCT solution), the same preconditioner object and the same
stopping rule (relative residual 1e-6, at most 200 iterations); they differ only in the CG
code, and the scipy side (the package's ``_pcg``) also recomputes the final residual from its
solution, one more product. Problems: the synthetic clay tablet's normals (with 0.5 %
gradient noise) on its mask at 1000×1000 and 2000×2000, and at 2000×2000 with 40 holes
punched in the mask. Setup (problem, warm start, preconditioner) is not timed.

Each pair of runs alternates which solver goes first, so a load change on the shared machine
hits both alike, after one untimed run of each; the ratio hand/scipy is taken per pair and
its median reported. Iterations and the final relative residual ‖b − Az‖/‖b‖ (recomputed for
both) come from the last run; "max abs Δz" is the largest height difference between the two
solutions after removing each connected component's mean, in pixel units.

Run: ``.venv/bin/python benchmarks/cg_solver.py [--runs 5] [--sizes 1000 2000]``
Prints Markdown.
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import scipy

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_synthetic.tablet import clay_tablet  # noqa: E402
from procinfo import cpu_model  # noqa: E402
from reconstruct.surface import gradients_from_normals  # noqa: E402
from reconstruct.surface.masked import (  # noqa: E402
    _component_means_removed,
    _edge_weights,
    _masked_inputs,
    _normal_equations,
    _pcg,
    _preconditioner,
    _warm_start,
)

TOL = 1e-6
MAXITER = 200


def hand_pcg(grid, b, precond, x0, *, tol, maxiter):
    """The loop masked_poisson used before scipy's cg (kept here as the reference)."""
    x = x0
    r = b - grid.matvec(x)
    bnorm = math.sqrt(float(np.vdot(b, b))) or 1.0
    z = precond(r)
    p = z.copy()
    rz = float(np.vdot(r, z))
    ap = np.empty_like(x)
    it = 0
    res = math.sqrt(float(np.vdot(r, r))) / bnorm
    while res > tol and it < maxiter:
        grid.matvec(p, out=ap)
        pap = float(np.vdot(p, ap))
        if pap <= 0:
            break  # p lies in the null space (constants): nothing left to reduce
        alpha = rz / pap
        x += alpha * p
        r -= alpha * ap
        it += 1
        res = math.sqrt(float(np.vdot(r, r))) / bnorm
        if res <= tol:
            break
        z = precond(r)
        rz_new = float(np.vdot(r, z))
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, {"iterations": it, "residual": res}


SOLVERS = {"hand": hand_pcg, "scipy": _pcg}


def _problem(size: int, holes: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    surface = clay_tablet((size, size))
    p, q = gradients_from_normals(surface.normals)
    rng = np.random.default_rng(0)
    s = 0.005 * float(np.sqrt(np.mean(p[surface.mask] ** 2 + q[surface.mask] ** 2)))
    p = p + rng.normal(0, s, p.shape).astype(np.float32)
    q = q + rng.normal(0, s, q.shape).astype(np.float32)
    mask = surface.mask.copy()
    if holes:
        rows, cols = np.nonzero(mask)
        rr, cc = np.ogrid[:size, :size]
        for i in rng.integers(0, rows.size, 40):
            radius = rng.uniform(0.008, 0.04) * size
            mask &= (rr - rows[i]) ** 2 + (cc - cols[i]) ** 2 > radius**2
    return p, q, mask


def _system(p, q, mask, preconditioner):
    """What masked_poisson hands to the CG solver, built once for both solvers."""
    g_row, g_col, m, box = _masked_inputs(p, q, mask, 1.0)
    wx, wy = _edge_weights(None, m, box, p.shape)
    tx = 0.5 * (g_col[:, :-1].astype(np.float64) + g_col[:, 1:])
    ty = 0.5 * (g_row[:-1, :].astype(np.float64) + g_row[1:, :])
    x0 = _warm_start(g_row, g_col, m)
    grid, b = _normal_equations(wx, tx, wy, ty)
    precond = _preconditioner(preconditioner, grid, m, -1)
    return grid, b, precond, np.where(m, x0, 0.0), m


def _measure(system, runs: int) -> dict:
    grid, b, precond, x0, m = system
    times = {name: [] for name in SOLVERS}
    ratios, out = [], {}
    for solver in SOLVERS.values():  # untimed: FFT plans, caches, lazy imports
        solver(grid, b, precond, x0.copy(), tol=TOL, maxiter=MAXITER)
    for run in range(runs):
        order = list(SOLVERS) if run % 2 == 0 else list(SOLVERS)[::-1]
        for name in order:
            x = x0.copy()
            t = time.perf_counter()
            out[name] = SOLVERS[name](grid, b, precond, x, tol=TOL, maxiter=MAXITER)
            times[name].append(time.perf_counter() - t)
        ratios.append(times["hand"][-1] / times["scipy"][-1])
    bnorm = float(np.linalg.norm(b))
    z = {}
    row = {"ratio": (statistics.median(ratios), min(ratios), max(ratios))}
    for name, (x, info) in out.items():
        row[name] = (statistics.median(times[name]), info["iterations"],
                     float(np.linalg.norm(b - grid.matvec(x))) / bnorm)
        z[name], _, _ = _component_means_removed(x.copy(), m)
    row["dz"] = float(np.abs(z["hand"] - z["scipy"])[m].max())
    row["range"] = float(np.ptp(z["hand"][m]))
    return row


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--sizes", type=int, nargs="*", default=[1000, 2000])
    ap.add_argument("--preconditioners", nargs="*", default=["dct", "multigrid"])
    args = ap.parse_args()
    cpu = cpu_model()
    print(f"# CG solver: hand loop vs scipy.sparse.linalg.cg\n\n"
          f"{datetime.date.today().isoformat()} — {cpu}, {platform.machine()}, "
          f"{os.cpu_count()} cores, Python {platform.python_version()}, NumPy {np.__version__}, "
          f"SciPy {scipy.__version__}; median of {args.runs} alternating runs, "
          f"tol {TOL:g}\n")
    print("| problem | mask pixels | preconditioner | hand (s) | scipy (s) | hand/scipy "
          "(min–max) | iterations hand/scipy | residual hand | residual scipy | max abs Δz (px) "
          "| height range (px) |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    problems = [(s, False) for s in args.sizes] + [(max(args.sizes), True)]
    for size, holes in problems:
        p, q, mask = _problem(size, holes)
        name = f"tablet {size}²" + (", 40 holes" if holes else "")
        for pc in args.preconditioners:
            r = _measure(_system(p, q, mask, pc), args.runs)
            (th, ih, rh), (ts, is_, rs) = r["hand"], r["scipy"]
            mid, lo, hi = r["ratio"]
            print(f"| {name} | {int(mask.sum())} | {pc} | {th:.3f} | {ts:.3f} | "
                  f"{mid:.3f} ({lo:.2f}–{hi:.2f}) | {ih}/{is_} | {rh:.1e} | {rs:.1e} | "
                  f"{r['dz']:.1e} | {r['range']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
