"""``reconstruct relight``: render a PTM or HSH file under any light, or a sweep as a GIF.

The maths is in :mod:`ptmcore.relight` (RTIViewer's default rendering, specular enhancement
and diffuse gain); this module finds the PTM of a source, converts RGB-format PTMs for the
modes that need a single luminance polynomial, and writes images and animations.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.colourtags import srgb_save_options
from ptmcore.errors import InputError
from ptmcore.normals import normals_from_ptm
from ptmcore.ptmfile import PTMFile, read_ptm
from ptmcore.relight import (
    DEFAULT_EXPONENT,
    DEFAULT_GAIN,
    DEFAULT_KD,
    DEFAULT_KS,
    as_lrgb,
    check_parameters,
    diffuse_gain,
    relight,
    specular_enhancement,
)
from ptmcore.rtifile import RTIFile, read_rti_hsh

MODES = ("default", "specular", "diffuse-gain")
#: The most frames of a sweep: one per degree, a turn of 29 s at :func:`write_gif`'s pace.
#: Every frame is a full rendering, and the GIF holds them all.
MAX_SWEEP = 360
#: The most pixels a sweep's frames hold together (one byte each once reduced to a palette):
#: 360 frames of 6 megapixels.
MAX_SWEEP_PIXELS = 2**31
#: A GIF's width and height are 16-bit numbers.
MAX_GIF_SIDE = 65535


def holds_linear_light(source: str | os.PathLike) -> bool:
    """Whether a relightable file, or an output folder's, holds linear light.

    Its run's ``report.json`` (in the folder, or beside the file) says so in ``ptm.encoding``
    (``--ptm-encoding linear``, and 16-bit captures before their files were display-encoded);
    renderings of it are then encoded as sRGB for display
    (:func:`ptmcore.relight.display_srgb`). A file without a report is taken as display-encoded,
    as RTIViewer takes it.
    """
    from reconstruct.report.figures import linear_ptm

    source = Path(source)
    try:
        report = json.loads(((source if source.is_dir() else source.parent) / "report.json").read_text("utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(report, dict) and linear_ptm(report)


def load_source(source: str | os.PathLike, basis: str = "ptm") -> PTMFile | RTIFile:
    """Read a relightable file: a ``.ptm`` or HSH ``.rti`` file, or from an output folder of
    ``reconstruct run`` its ``coefficients.ptm`` (``basis="ptm"``) or ``coefficients.rti``
    (``basis="hsh"``)."""
    source = Path(source)
    if source.is_dir():
        name = "coefficients.rti" if basis == "hsh" else "coefficients.ptm"
        candidate = source / name
        if not candidate.is_file():
            hint = " (run with --hsh to write it)" if basis == "hsh" else ""
            raise InputError(f"no {name} in this folder{hint}; give a .ptm or .rti file or an output folder", source)
        source = candidate
    elif not source.exists():
        raise InputError("not found", source)
    return read_rti_hsh(source) if source.suffix.lower() == ".rti" else read_ptm(source)


def render(
    ptm: PTMFile | RTIFile,
    light: np.ndarray,
    mode: str = "default",
    *,
    kd: float = DEFAULT_KD,
    ks: float = DEFAULT_KS,
    exponent: float = DEFAULT_EXPONENT,
    gain: float = DEFAULT_GAIN,
) -> np.ndarray:
    """Render a PTM under one light in one of RTIViewer's modes.

    Parameters
    ----------
    ptm : PTMFile or RTIFile
        A PTM (every mode) or an HSH file (default mode).
    light : ndarray, shape (3,)
        Unit vector towards the light.
    mode : {"default", "specular", "diffuse-gain"}
    kd, ks, exponent : float
        Specular enhancement: diffuse weight, specular weight, Phong exponent.
    gain : float
        Diffuse gain.

    Returns
    -------
    ndarray, shape (H, W, 3), uint8
    """
    return next(renders(ptm, [light], mode, kd=kd, ks=ks, exponent=exponent, gain=gain))


def renders(
    ptm: PTMFile | RTIFile,
    lights: Sequence[np.ndarray],
    mode: str = "default",
    *,
    kd: float = DEFAULT_KD,
    ks: float = DEFAULT_KS,
    exponent: float = DEFAULT_EXPONENT,
    gain: float = DEFAULT_GAIN,
) -> Iterator[np.ndarray]:
    """Render a PTM under each of several lights (a sweep's frames), as :func:`render` does.

    What does not depend on the light is done once, when this is called: an RGB-format PTM's
    conversion to LRGB, the diffuse gain's coefficients and, for more than one light, the
    polynomials' maxima for the specular lobe (one light finds them band by band, holding no
    full-size array of them). Each image is then made as it is asked for. A 12-frame
    diffuse-gain sweep of a 6-megapixel PTM took 1.8 times as long when each frame redid it.

    Parameters
    ----------
    ptm : PTMFile or RTIFile
    lights : sequence of ndarray, shape (3,)
        Unit vectors towards the lights.
    mode, kd, ks, exponent, gain
        As :func:`render`.

    Returns
    -------
    iterator of ndarray, shape (H, W, 3), uint8
        One image per light, in order.

    Raises
    ------
    ValueError
        For an unknown mode, or a parameter out of its range
        (:func:`ptmcore.relight.check_parameters`), before any work.
    """
    # Before the long work (the conversion to LRGB, the maxima), not in the first frame.
    check_parameters(kd=kd, ks=ks, exponent=exponent, gain=gain)
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
    if isinstance(ptm, RTIFile):
        if mode != "default":
            raise InputError(f"the {mode} mode needs a PTM; an HSH file renders in the default mode only")
        return (ptm.render(light) for light in lights)
    if mode == "default" and not ptm.is_lrgb:
        return (ptm.render(light) for light in lights)
    coef, rgb = as_lrgb(ptm)
    if mode == "specular":
        # float32, as specular_enhancement finds them itself.
        maximum = normals_from_ptm(coef.astype(np.float32, copy=False)) if len(lights) > 1 else None
        return (specular_enhancement(coef, rgb, light, kd=kd, ks=ks, exponent=exponent, maximum=maximum)
                for light in lights)
    if mode == "diffuse-gain":
        coef = diffuse_gain(coef, gain)
    return (relight(coef, rgb, light) for light in lights)


def check_sweep(count: int, width: int, height: int, source: str | os.PathLike | None = None) -> None:
    """Refuse a sweep of ``count`` frames of ``width`` × ``height`` that a GIF cannot hold, or
    whose frames would be more than :data:`MAX_SWEEP_PIXELS`.

    Raises
    ------
    InputError
        Naming ``source``, the bound, and how many frames would fit.
    """
    if max(width, height) > MAX_GIF_SIDE:
        raise InputError(f"{width}×{height} pixels: a GIF is at most {MAX_GIF_SIDE} pixels wide and high; "
                         "relight it under single lights instead", source)
    if count * width * height > MAX_SWEEP_PIXELS:
        fit = max(1, MAX_SWEEP_PIXELS // (width * height))
        raise InputError(f"{count} frames of {width}×{height} pixels are more than a sweep holds "
                         f"({MAX_SWEEP_PIXELS / 2**30:g} gigapixels): give --sweep {fit} or fewer", source)


def sweep_lights(count: int, elevation_deg: float = 30.0) -> np.ndarray:
    """``count`` unit light vectors circling the object at one elevation, from the right.

    Raises
    ------
    ValueError
        For a ``count`` outside 1 to :data:`MAX_SWEEP`.
    """
    if not 1 <= count <= MAX_SWEEP:
        raise ValueError(f"a sweep has 1 to {MAX_SWEEP} frames, not {count}")
    az = np.radians(np.arange(count) * 360.0 / count)
    el = np.radians(elevation_deg)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(count, np.sin(el))], axis=1)


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an 8-bit RGB image; the format follows the extension (PNG, JPEG, TIFF...), tagged
    as sRGB where the format can say so (:func:`ptmcore.colourtags.srgb_save_options`)."""
    from PIL import Image

    path = Path(path)
    fmt = Image.registered_extensions().get(path.suffix.lower())
    if fmt is None:
        raise InputError(f"unknown image extension {path.suffix!r} (use .png, .jpg or .tif)", path)
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format=fmt, **srgb_save_options(fmt))
    with atomic_write(path, "wb") as f:
        f.write(buf.getbuffer())


def write_gif(path: str | os.PathLike, frames: Iterable[np.ndarray], *, frame_ms: int = 80) -> None:
    """Write frames as a looping animated GIF (adaptive palette per frame).

    Each RGB frame is reduced to its palette as it comes, so a sweep holds one byte per
    pixel of each frame, not four (the RGB frames beside their palettes). Untagged: GIF has
    no colour profile in practice, and viewers take it as sRGB.
    """
    from PIL import Image

    images = [Image.fromarray(f).quantize(colors=256, method=Image.Quantize.MEDIANCUT) for f in frames]
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=frame_ms, loop=0)
    with atomic_write(path, "wb") as f:
        f.write(buf.getbuffer())
