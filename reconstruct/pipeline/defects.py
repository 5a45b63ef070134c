"""A capture's defects: found, said, and undone before fitting where the photographs allow.

What a museum capture brings besides the object (issue 37): a camera that moved between
photographs (a bumped tripod), light in the room, lamps that do not light the frame evenly, a
colour profile, RAW files. :func:`capture_corrections` gathers what is known before decoding
(the ambient frame) into a :class:`ptmcore.corrections.Corrections`; the decoding pass
measures the camera's drift (:class:`ptmcore.align.DriftProbe`), and :func:`drift_finding`
says whether the photographs were resampled onto one frame; :func:`stray_light_finding` looks
for room light in the decoded stack's attached shadows. Each finding is a dict for
``report.json``'s ``capture_checks`` and, when the user should act, a warning line.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ptmcore.corrections import Corrections
from ptmcore.errors import InputError
from ptmcore.images import ImageStack, image_size, read_image

__all__ = [
    "ALIGN_MIN_SIDE",
    "capture_corrections",
    "drift_finding",
    "exposure_finding",
    "frame_shape",
    "colour_of",
    "new_probe",
    "sampled_luminance",
    "stray_light_finding",
]

#: Pixels sampled for a run's exposure and stray-light findings (a grid over the frame).
_SAMPLES = 20000
#: Frames smaller than this on either side are not measured for drift: the probe's tiles (the
#: shorter side ÷ 2.5, at most 192 px) would hold too little detail for a sub-pixel offset
#: (a steady 128 × 96 synthetic tablet under 24 lights read 1.1 px with 38-px tiles; from 64-px
#: tiles on, steady captures read under 0.4 px). Such frames are thumbnails, not photographs.
ALIGN_MIN_SIDE = 160
#: A photograph with more of its pixels clipped (any channel at its top) than this is reported.
CLIPPED_SHARE = 0.01
#: A photograph with more of its pixels nearly black (linear luminance under 0.5 %) than this.
DARK_SHARE = 0.5
#: A photograph whose brightness, divided by what its light's elevation explains (the sine),
#: is off the capture's median by more than this factor either way.
EXPOSURE_FACTOR = 2.0
#: ... and off its peers by as much: the photographs whose lights are within this many degrees
#: of its elevation (a dome's ring), when it has two or more. A glossy flat object under a ring of
#: high lights shows its sheen on most pixels of all of them (a steady rendered glossy tablet: the
#: 75° ring 2.9× what the sine explains); a lamp or exposure that changed lifts one photograph.
EXPOSURE_PEER_DEG = 5.0


def frame_shape(paths: Sequence[Path]) -> tuple[int, int]:
    """``(H, W)`` of the capture's photographs, from the first one's header (decoded only when
    its header does not say, as for a RAW file)."""
    size = image_size(paths[0])
    if size is not None:
        return int(size[1]), int(size[0])
    return read_image(paths[0]).shape[:2]


def capture_corrections(paths: Sequence[Path], *, ambient: Path | None, flat_field: Path | None = None,
                        directions: np.ndarray | None = None) -> tuple[Corrections, dict]:
    """What is known before decoding: the ambient frame (``--ambient``, a photograph with the
    lamps off), checked against the photographs' size and brightness, and the lamps' gains over
    the frame from a board's capture (``--flat-field``; needs the lights' ``directions``).

    Returns
    -------
    corrections : Corrections
    checks : dict
        What ``report.json``'s ``capture_checks`` says of them (and of the colour profile).
    """
    from ptmcore.raw import is_raw, raw_development

    corrections = Corrections()
    if is_raw(paths[0]):
        # One development for the whole capture (and its ambient frame and board): the first
        # photograph's white balance and orientation.
        corrections.raw = raw_development(paths[0])
    checks: dict = {"colour": colour_of(paths[0], corrections.raw)}
    if ambient is None and flat_field is None:
        return corrections, checks
    from ptmcore.illumination import check_ambient, load_flat_field, read_ambient

    shape = frame_shape(paths)
    if ambient is not None:
        corrections.ambient = read_ambient(ambient, shape, raw=corrections.raw)
        check_ambient(corrections.ambient, paths, ambient, raw=corrections.raw)
        checks["ambient"] = {"frame": str(ambient), "mean_level": float(corrections.ambient.mean())}
    if flat_field is not None:
        if directions is None:
            raise InputError("--flat-field needs the lights before decoding: give the capture an .lp file "
                             "(a capture calibrated from spheres has none yet)", flat_field)
        corrections.flat = load_flat_field(flat_field, [p.name for p in paths], directions, shape,
                                           raw=corrections.raw)
        found = corrections.flat.describe()
        checks["flat_field"] = {"capture": str(flat_field),
                                **{k: v for k, v in found.items() if not isinstance(v, (list, tuple, np.ndarray))}}
    return corrections, checks


def colour_of(path: Path, raw=None) -> str:
    """The colour profile of a photograph in words (:func:`ptmcore.decoders.colour_description`;
    a RAW photograph's development, ``raw``, :func:`ptmcore.raw.raw_description`)."""
    from ptmcore.decoders import colour_description
    from ptmcore.raw import is_raw, raw_description

    return raw_description(path, raw) if raw is not None and is_raw(path) else colour_description(path)


def new_probe(paths: Sequence[Path]):
    """A :class:`ptmcore.align.DriftProbe` for these photographs, or None when the frame is
    too small to measure (or its size cannot be read before decoding)."""
    if len(paths) < 3:
        return None
    size = image_size(paths[0])
    if size is None or min(size) < ALIGN_MIN_SIDE:
        return None
    from ptmcore.align import DriftProbe

    return DriftProbe((int(size[1]), int(size[0])), len(paths))


def drift_finding(drift, names: Sequence[str], align: str, scale: float = 1.0) -> tuple[dict, list[str], bool]:
    """What the measured drift means for the run (or for ``reconstruct check``).

    Parameters
    ----------
    drift : ptmcore.align.Drift
    names : sequence of str
        The photographs' file names.
    align : {"auto", "off", "check"}
        ``--align``, or ``"check"`` for ``reconstruct check``, which only advises.
    scale : float
        Pixels of the full frame per pixel the drift was measured in (``reconstruct check``
        measures reduced photographs): offsets are given in the full frame's pixels, and the
        threshold is :data:`ptmcore.align.ALIGN_THRESHOLD_PX` of the measured pixels when
        those are larger (the measurement's own noise, scaled up).

    Returns
    -------
    finding : dict
        For ``capture_checks["drift"]``: the threshold, the largest displacement, whether the
        photographs were aligned, how many were measured, and each photograph's offset (x
        right, y up, pixels), rotation (degrees, counter-clockwise) and the measurement's
        confidence.
    warnings : list of str
    resample : bool
        Whether the photographs are to be resampled onto the common frame.
    """
    from ptmcore.align import ALIGN_THRESHOLD_PX

    threshold = ALIGN_THRESHOLD_PX * max(1.0, scale)
    displacement = drift.displacement() * scale
    k = int(np.argmax(displacement))
    largest = float(displacement[k])
    needed = largest > threshold
    resample = needed and align == "auto"
    finding = {
        "threshold_px": float(threshold),
        "largest_px": largest,
        "largest_photograph": names[k],
        "aligned": resample,
        "measured": int(np.count_nonzero(np.asarray(drift.confidence) > 0)),
        "photographs": [
            {"name": name, "dx": round(float(dx), 3), "dy": round(float(dy), 3),
             "rotation_deg": round(float(rot), 4), "confidence": round(float(conf), 3)}
            for name, (dx, dy), rot, conf in zip(names, np.asarray(drift.offsets) * scale, drift.rotation_deg,
                                                 drift.confidence)
        ],
    }
    if scale != 1.0:
        finding["measured_at"] = f"1/{scale:.3g} scale"
    warnings = []
    if needed:
        moved = int(np.count_nonzero(displacement > threshold))  # rotation included
        what = (f"the camera moved during the capture: {moved} photograph(s) are displaced, up to {largest:.1f} px "
                f"({names[k]})")
        if align == "check":
            warnings.append(f"{what}; `reconstruct run` aligns them (--align auto)")
        else:
            warnings.append(f"{what}; they were aligned onto the other photographs' frame before fitting" if resample
                            else f"{what}; not aligned: expect blurred normals and height")
    return finding, warnings, resample


def exposure_finding(luminance: np.ndarray, clipped: np.ndarray, directions: np.ndarray,
                     names: Sequence[str]) -> tuple[dict, list[str]]:
    """Photographs clipped, mostly black, or brighter or darker than their light explains.

    Parameters
    ----------
    luminance : ndarray, shape (N, h, w)
        Linear luminance of each photograph, reduced or sampled on a grid.
    clipped : ndarray, shape (N,)
        The share of each photograph's pixels where a channel clipped.
    directions : ndarray, shape (N, 3)
        The lights (for the elevation a photograph's brightness is divided by).
    names : sequence of str

    Returns
    -------
    finding : dict
        ``clipped`` and ``dark`` (name → share, for those over :data:`CLIPPED_SHARE` and
        :data:`DARK_SHARE`) and ``odd_brightness`` (name → brightness over the capture's median,
        for those off by more than :data:`EXPOSURE_FACTOR`, and as much off the photographs of
        their elevation, :data:`EXPOSURE_PEER_DEG`, where there are two or more).
    warnings : list of str
        For the dark and oddly bright photographs (clipping is warned of by the caller, whose
        advice depends on what it does with clipped samples).
    """
    from ptmcore.errors import first_few

    n = len(luminance)
    flat = luminance.reshape(n, -1)
    dark = (flat < 0.005).mean(axis=1)
    z = np.asarray(directions, np.float64)[:, 2]
    level = np.median(flat, axis=1)
    brightness = level / np.maximum(z, 0.1)
    relative = brightness / max(float(np.median(brightness)), 1e-9)
    odd = np.flatnonzero((relative > EXPOSURE_FACTOR) | (relative < 1 / EXPOSURE_FACTOR))
    elevation = np.degrees(np.arcsin(np.clip(z, -1.0, 1.0)))
    peers = np.abs(elevation[:, None] - elevation[None, :]) <= EXPOSURE_PEER_DEG
    np.fill_diagonal(peers, False)

    def like_its_peers(k: int) -> bool:
        if peers[k].sum() < 2:
            return False
        local = level[k] / max(float(np.median(level[peers[k]])), 1e-9)
        return 1 / EXPOSURE_FACTOR <= local <= EXPOSURE_FACTOR

    odd = np.array([k for k in odd if not like_its_peers(int(k))], dtype=np.int64)
    finding = {
        "clipped": {m: round(float(c), 4) for m, c in zip(names, clipped) if c > CLIPPED_SHARE},
        "dark": {m: round(float(d), 4) for m, d in zip(names, dark) if d > DARK_SHARE},
        "odd_brightness": {names[k]: round(float(relative[k]), 3) for k in odd},
    }
    warnings = []
    if finding["dark"]:
        many = finding["dark"]
        warnings.append(f"{len(many)} photograph(s) are mostly black ({first_few(list(many))}): a lamp that did "
                        "not fire, or a light below the object's horizon")
    if len(odd):
        warnings.append(f"{len(odd)} photograph(s) are more than {EXPOSURE_FACTOR:g}× brighter or darker than their "
                        f"light's elevation explains ({first_few([names[k] for k in odd])}): exposure or lamp power "
                        "changed during the capture (--intensities estimate, or --reference-region, evens them out)")
    return finding, warnings


def sampled_luminance(stack: ImageStack) -> np.ndarray:
    """``(N, M)`` float32 linear luminance of every photograph on a grid of about
    :data:`_SAMPLES` pixels, read once for the run's findings."""
    h, w = stack.shape
    step = max(1, int(np.sqrt(h * w / _SAMPLES)))
    return stack.table[stack.grid(step)].reshape(len(stack), -1).astype(np.float32)


def stray_light_finding(samples: np.ndarray, directions: np.ndarray, ambient_given: bool
                        ) -> tuple[dict, list[str]]:
    """Room light seen in the attached shadows of the ``samples`` (:func:`sampled_luminance`;
    :func:`ptmcore.illumination.estimate_stray_light`), and the warning when it is raised."""
    from ptmcore.illumination import estimate_stray_light

    found = estimate_stray_light(samples, np.asarray(directions, np.float64))
    if found.level is None:
        return {"level": None, "pixels": int(found.pixels),
                "note": "too few samples in attached shadow to tell (no low lights, or a flat object)"}, []
    finding = {"level": round(float(found.level), 4), "pixels": int(found.pixels), "warned": bool(found.warn)}
    if not found.warn:
        return finding, []
    after = " after the ambient frame was subtracted" if ambient_given else ""
    advice = ("check that the ambient frame was taken with the same exposure" if ambient_given
              else "give --ambient FILE (a photograph with the lamps off) to subtract it")
    return finding, [f"stray light: the shadows receive about {found.level:.0%} of the lamps' light{after} "
                     f"(room light or a reflection), which flattens the normals; {advice}"]
