"""``reconstruct check``: what is wrong with a capture, in seconds, before a long run.

The photographs are read reduced (JPEGs at libjpeg's DCT scales, which cost a fraction of a full
decoding; other formats decoded and averaged down) to about :data:`CHECK_SIDE` pixels on the
longer side, and looked at for what museum captures bring: a camera that moved (drift, measured
as in a run by :mod:`ptmcore.align`, on the reduced frame), light in the room
(:func:`ptmcore.illumination.estimate_stray_light`), clipped or black photographs,
photographs much brighter or darker than their light direction explains (exposure changed, a
lamp misfired), the colour profile and the light layout's weak directions
(:func:`reconstruct.calibration.lightcheck.check_lights`). A run reports the drift and the colour
profile and the stray light too (``capture_checks``), measured on the full photographs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptmcore.corrections import to_linear_rgb
from ptmcore.errors import first_few
from ptmcore.images import LUMA_WEIGHTS, read_image
from ptmcore.lp import read_lp
from ptmcore.raw import is_raw, raw_development
from ptmcore.resources import thread_count
from reconstruct.pipeline.capture import find_lp
from reconstruct.pipeline.defects import ALIGN_MIN_SIDE, CLIPPED_SHARE, drift_finding, exposure_finding

__all__ = ["CHECK_SIDE", "CheckResult", "check_capture", "check_text"]

#: The reduced photographs' longer side, pixels: enough for a drift of a pixel of the full frame
#: to show on a 24-megapixel photograph, little enough to read 50 of them in seconds.
CHECK_SIDE = 1024


@dataclass
class CheckResult:
    """What :func:`check_capture` found.

    Attributes
    ----------
    capture : Path
    photographs : int
    size : tuple of int
        ``(width, height)`` of the full photographs.
    checks : dict
        As a run's ``report.json`` ``capture_checks`` (drift in full-frame pixels), plus
        ``exposure`` (clipped, dark and odd photographs) and ``lights`` (the layout's report).
    warnings : list of str
        What the user should act on, one line each.
    """

    capture: Path
    photographs: int
    size: tuple[int, int]
    checks: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        from reconstruct.pipeline.report import json_safe

        return json_safe({"capture": str(self.capture), "photographs": self.photographs,
                          "width": self.size[0], "height": self.size[1], "checks": self.checks,
                          "warnings": self.warnings})


def _reduced(path: Path, raw=None) -> tuple[np.ndarray, tuple[int, int]]:
    """A photograph's linear luminance about :data:`CHECK_SIDE` long (1 where a channel
    clipped), and the size ``(H, W)`` it was decoded at."""
    img = read_image(path, min_side=CHECK_SIDE // 2, raw=raw)
    top = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}.get(img.dtype, 1.0)
    rgb = img if img.ndim == 3 else img[:, :, None]
    clipped = (rgb >= top).any(axis=2)
    lin = to_linear_rgb(img)
    block = max(1, int(np.ceil(max(lin.shape[:2]) / CHECK_SIDE)))
    h, w = (lin.shape[0] // block) * block, (lin.shape[1] // block) * block
    lin = lin[:h, :w].reshape(h // block, block, w // block, block, 3).mean(axis=(1, 3))
    clipped = clipped[:h, :w].reshape(h // block, block, w // block, block).any(axis=(1, 3))
    lum = (lin @ LUMA_WEIGHTS).astype(np.float32)
    lum[clipped] = np.float32(1.0)
    return lum, img.shape[:2]


def check_capture(capture: str | os.PathLike, *, lp: str | os.PathLike | None = None,
                  threads: int | None = None) -> CheckResult:
    """Look at a capture (a folder with its ``.lp``, or the ``.lp``) for the defects of real captures.

    Parameters
    ----------
    capture : path
    lp : path, optional
        The light file (default: the one ``.lp`` in the folder).
    threads : int, optional
        Decoding threads.

    Returns
    -------
    CheckResult

    Raises
    ------
    InputError
        For a capture that cannot be read (no ``.lp``, a photograph that does not decode,
        photographs of different sizes).
    """
    from concurrent.futures import ThreadPoolExecutor

    from ptmcore.errors import InputError
    from reconstruct.calibration.lightcheck import check_lights
    from reconstruct.pipeline.defects import colour_of, frame_shape
    from reconstruct.pipeline.projects import locate_photographs

    capture = Path(capture)
    lights = locate_photographs(read_lp(find_lp(capture, None if lp is None else Path(lp))), capture)
    paths, directions = lights.paths, lights.directions
    with ThreadPoolExecutor(thread_count(threads)) as pool:
        # Camera RAW: one development (the first photograph's white balance) for all of them.
        raw = raw_development(paths[0]) if is_raw(paths[0]) else None
        reduced = list(pool.map(lambda p: _reduced(p, raw), paths))
    first = reduced[0][1]
    for path, (_, full) in zip(paths, reduced):
        if full != first:
            raise InputError(f"image is {full[1]}×{full[0]} but {paths[0].name} is {first[1]}×{first[0]}; all "
                             "photographs of a capture must have the same size", path)
    full_shape = frame_shape(paths)
    luminance = np.stack([r[0] for r in reduced])  # (N, h, w) linear
    del reduced
    factor = full_shape[1] / luminance.shape[2]
    names = [p.name for p in paths]
    result = CheckResult(capture, len(paths), (full_shape[1], full_shape[0]))
    checks, warnings = result.checks, result.warnings
    checks["colour"] = colour_of(paths[0])

    # Exposure: clipped, dark, and brightness the light's elevation does not explain.
    checks["exposure"], said = exposure_finding(luminance, (luminance >= 1.0).mean(axis=(1, 2)), directions, names)
    if checks["exposure"]["clipped"]:
        many = checks["exposure"]["clipped"]
        warnings.append(f"{len(many)} photograph(s) have more than {CLIPPED_SHARE:.0%} clipped pixels "
                        f"({first_few(list(many))}): lower the exposure, or they are left out where clipped")
    warnings += said

    # Drift, measured on the reduced frame and given in the full frame's pixels.
    if min(luminance.shape[1:3]) >= ALIGN_MIN_SIDE and len(paths) >= 3:
        from ptmcore.align import DriftProbe, measure_drift

        probe = DriftProbe(luminance.shape[1:3], len(paths))
        for k in range(len(paths)):  # grey, as the reduction's grey photographs: a stride-0 view
            probe.take(k, np.broadcast_to(luminance[k][:, :, None], luminance.shape[1:] + (3,)), False)
        drift = measure_drift(probe, directions, threads=threads)
        checks["drift"], said, _ = drift_finding(drift, names, "check", factor)
        warnings += said

    # Stray light, from a grid of the reduced pixels.
    from ptmcore.illumination import estimate_stray_light

    step = max(1, int(np.sqrt(luminance.shape[1] * luminance.shape[2] / 20000)))
    stray = estimate_stray_light(luminance[:, step // 2::step, step // 2::step].reshape(len(paths), -1),
                                 np.asarray(directions, np.float64))
    if stray.level is None:
        checks["stray_light"] = {"level": None, "pixels": int(stray.pixels),
                                 "note": "too few samples in attached shadow to tell (no low lights, or a flat object)"}
    else:
        checks["stray_light"] = {"level": round(float(stray.level), 4), "pixels": int(stray.pixels),
                                 "warned": bool(stray.warn)}
        if stray.warn:
            warnings.append(f"stray light: the shadows receive about {stray.level:.0%} of the lamps' light (room "
                            "light or a reflection); photograph the object with the lamps off and give it to "
                            "`reconstruct run --ambient`")

    report = check_lights(directions)
    checks["lights"] = {"count": report.count, "rank": int(report.rank.rank), "condition": float(report.condition),
                        "elevation_range_deg": [float(v) for v in report.elevation_range],
                        "largest_azimuth_gap_deg": float(report.azimuth_gap), "warnings": list(report.warnings)}
    warnings += [f"lights: {w}" for w in report.warnings]
    return result


def check_text(result: CheckResult) -> str:
    """The findings as lines for a terminal."""
    from reconstruct.report.html import capture_check_rows

    lines = [f"{result.capture}: {result.photographs} photographs, {result.size[0]}×{result.size[1]}"]
    lines += [f"  {label}: {text}" for label, text in capture_check_rows(result.checks)]
    lights = result.checks.get("lights")
    if lights:
        lines.append(f"  Lights: {lights['count']}, elevations {lights['elevation_range_deg'][0]:.0f}°–"
                     f"{lights['elevation_range_deg'][1]:.0f}°, largest azimuth gap {lights['largest_azimuth_gap_deg']:.0f}°, "
                     f"PTM rank {lights['rank']} of 6")
    if result.warnings:
        lines.append(f"{len(result.warnings)} finding(s) to act on:")
        lines += [f"  - {w}" for w in result.warnings]
    else:
        lines.append("Nothing to act on: the capture looks ready for `reconstruct run`.")
    return "\n".join(lines)
