"""Compile the numerical kernels before the first real run: ``reconstruct warm-up``.

The compiled kernels (numba, ``cache=True``) are compiled on first use and cached beside the
sources (or in ``NUMBA_CACHE_DIR``), once per argument types. A fresh installation, container
or cluster node therefore pays tens of seconds of compilation in its first run. :func:`warm_up`
pays it ahead: it reconstructs small synthetic captures (8-bit JPEG and 16-bit TIFF, whose
photographs reach the kernels as different types) with the options that reach the other
kernels (each normal method and fit, the integrators, the PTM formats), in a temporary folder
that is removed afterwards. ``make install`` (and so ``make demo`` and ``make test``) runs it.

Only the kernels compiled with their types fixed by a run are warmed; a kernel called from
Python code of one's own with other types compiles once on that first call, as usual.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["WARM_UP_RUNS", "WarmUp", "warm_up"]

#: The runs of a warm-up: the photographs' encoding, and the options (of
#: :class:`~reconstruct.pipeline.RunOptions`) beyond the defaults that reach further kernels.
WARM_UP_RUNS: tuple[tuple[str, dict], ...] = (
    ("tiff16", {}),
    ("jpeg8", {}),
    ("tiff16", {"normals": "ptm", "fit": "trimmed", "ptm_format": "rgb", "integrator": "bilateral", "hsh": True}),
    ("jpeg8", {"normals": "ptm-debiased", "fit": "plain", "integrator": "dct"}),
    ("tiff16", {"fit": "irls", "integrator": "fc"}),
)

#: The captures' size (width is the second number) and number of lights: small enough to take
#: a fraction of a second once compiled, enough lights for every basis and normal method.
SHAPE = (40, 48)
LIGHTS = 24


@dataclass(frozen=True)
class WarmUp:
    """What :func:`warm_up` did.

    Attributes
    ----------
    runs : int
        Captures reconstructed.
    seconds : float
        Wall time of the whole warm-up.
    failed : list of str
        The runs that stopped with an error (their options), which a warm-up reports and goes
        on from: a kernel it did not reach compiles in the first real run instead.
    """

    runs: int
    seconds: float
    failed: list[str] = field(default_factory=list)


def warm_up(runs: Sequence[tuple[str, dict]] = WARM_UP_RUNS, *,
            progress: Callable[[int, int], None] | None = None) -> WarmUp:
    """Reconstruct small synthetic captures so that the kernels a run uses are compiled and cached.

    Parameters
    ----------
    runs : sequence of (encoding, options)
        The captures' encodings (``"tiff16"``, ``"jpeg8"``) and the
        :class:`~reconstruct.pipeline.RunOptions` arguments of each run (default:
        :data:`WARM_UP_RUNS`).
    progress : callable, optional
        Called as ``progress(done, total)`` after each run.

    Returns
    -------
    WarmUp
    """
    from data_synthetic import write_capture
    from ptmcore.errors import InputError
    from reconstruct.pipeline.options import RunOptions
    from reconstruct.pipeline.run import run_capture

    start = time.perf_counter()
    failed = []
    with tempfile.TemporaryDirectory(prefix="reconstruct-warm-up-") as tmp:
        captures: dict[str, tuple[Path, float]] = {}
        for i, (encoding, extra) in enumerate(runs):
            if encoding not in captures:
                folder = Path(tmp) / encoding
                info = write_capture(folder, scene="tablet", shape=SHAPE, n_lights=LIGHTS, encoding=encoding, seed=1)
                captures[encoding] = (folder, info.pixel_size)
            folder, pixel_size = captures[encoding]
            try:
                run_capture(folder, Path(tmp) / f"out{i}", RunOptions(pixel_size=pixel_size, **extra))
            except (InputError, ValueError, OSError) as exc:
                failed.append(f"{encoding} {extra}: {exc}")
            if progress is not None:
                progress(i + 1, len(runs))
    return WarmUp(len(runs), time.perf_counter() - start, failed)
