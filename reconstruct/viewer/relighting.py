"""``reconstruct relight``: render a relightable image under any light, or a sweep as a GIF.

A source is the relighting basis an output folder publishes in ``web/`` (the one chosen for the
capture, ``reconstruct run --basis``: PTM, HSH, RBF or bilinear; read by
:func:`reconstruct.report.webread.read_relightable`), a ``web/`` folder itself, or a PTM or HSH
file (``coefficients.ptm``, ``coefficients.rti``, or any ``.ptm``/``.rti``). The published basis
renders as its page shows it (:meth:`ptmcore.published.PublishedBasis.display`); PTM and HSH files
in RTIViewer's modes, whose maths is in :mod:`ptmcore.relight` (default rendering, specular
enhancement and diffuse gain — the last two defined on the PTM's biquadratic, so they always
render a PTM). This module finds what a source holds, converts RGB-format PTMs for the modes that
need a single luminance polynomial, and writes images and animations.
"""

from __future__ import annotations

import io
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.colourtags import srgb_save_options
from ptmcore.errors import InputError
from ptmcore.normals import normals_from_ptm
from ptmcore.ptmfile import PTMFile, read_ptm
from ptmcore.published import PublishedBasis
from ptmcore.relight import (
    DEFAULT_EXPONENT,
    DEFAULT_GAIN,
    DEFAULT_KD,
    DEFAULT_KS,
    as_lrgb,
    check_parameters,
    diffuse_gain,
    light_direction,
    relight,
    specular_enhancement,
)
from ptmcore.rtifile import RTIFile, read_rti_hsh

MODES = ("default", "specular", "diffuse-gain")
#: What ``--basis`` picks in an output folder: ``auto`` the basis published in ``web/`` (else
#: ``coefficients.ptm``), ``ptm`` its ``coefficients.ptm``, ``hsh`` its ``coefficients.rti``.
BASES = ("auto", "ptm", "hsh")

#: A relightable image as read: a PTM or HSH file, or a published basis.
Relightable = PTMFile | RTIFile | PublishedBasis
#: The most frames of a sweep: one per degree, a turn of 29 s at :func:`write_gif`'s pace.
#: Every frame is a full rendering, and the GIF holds them all.
MAX_SWEEP = 360
#: The most pixels a sweep's frames hold together (one byte each once reduced to a palette):
#: 360 frames of 6 megapixels.
MAX_SWEEP_PIXELS = 2**31
#: A GIF's width and height are 16-bit numbers.
MAX_GIF_SIDE = 65535


def _web_source(source: Path) -> bool:
    """Whether ``source`` is a ``web/`` folder itself or its ``info.json``."""
    return (source.is_dir() and (source / "info.json").is_file()) or source.suffix.lower() == ".json"


def load_source(source: str | os.PathLike, basis: str = "auto", *, mode: str = "default") -> Relightable:
    """Read what ``reconstruct relight`` renders.

    Parameters
    ----------
    source : str or os.PathLike
        A ``.ptm`` or HSH ``.rti`` file; a ``web/`` folder (or its ``info.json``), read as its
        published basis; or an output folder of ``reconstruct run``, read as ``basis`` says.
    basis : {"auto", "ptm", "hsh"}
        In an output folder: ``"auto"`` the basis published in its ``web/`` (the one chosen for
        the capture, :func:`reconstruct.report.webread.published_folder`), else its
        ``coefficients.ptm``, else a ``web/`` of the PTM itself (a run from a ``.ptm`` file);
        ``"ptm"`` its ``coefficients.ptm``; ``"hsh"`` its ``coefficients.rti``. A file is read
        as what it is.
    mode : {"default", "specular", "diffuse-gain"}
        The rendering asked for: specular enhancement and diffuse gain are defined on a PTM's
        biquadratic, so with ``"auto"`` they take the folder's ``coefficients.ptm``.

    Returns
    -------
    PTMFile, RTIFile or PublishedBasis

    Raises
    ------
    InputError
        If the source is missing or unreadable, the folder holds nothing of what is asked, or
        the mode needs a PTM and the source is a ``web/`` folder.
    ValueError
        For a ``basis`` or ``mode`` not among :data:`BASES` and :data:`MODES`.
    """
    from reconstruct.report.webread import find_web_folder, published_folder, read_relightable

    if basis not in BASES:
        raise ValueError(f"unknown basis {basis!r}; choose from {', '.join(BASES)}")
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
    source = Path(source)
    if not source.exists():
        raise InputError("not found", source)
    if _web_source(source):
        if basis != "auto":
            raise InputError(f"--basis {basis} picks a file of an output folder; this is a web/ folder, "
                             "whose published basis is read as it is: give the output folder", source)
        if mode != "default":
            raise InputError(f"the {mode} mode is RTIViewer's, defined on a PTM's polynomial, and a web/ folder "
                             "holds only the published basis: give the output folder (its coefficients.ptm) "
                             "or a .ptm file", source)
        return read_relightable(source)
    if source.is_dir():
        if basis == "auto" and mode == "default":
            web = published_folder(source)
            if web is not None:
                return read_relightable(web)
        name = "coefficients.rti" if basis == "hsh" else "coefficients.ptm"
        candidate = source / name
        if not candidate.is_file():
            web = find_web_folder(source)
            if basis == "auto" and mode == "default" and web is not None:
                return read_relightable(web)  # a run from a .ptm file: web/ holds that PTM
            if mode != "default":
                raise InputError(f"no {name} in this folder, and the {mode} mode is RTIViewer's, defined on a "
                                 "PTM's polynomial: give a .ptm file", source)
            hint = " (run with --hsh to write it)" if basis == "hsh" else ""
            where = "no web/ and " if basis == "auto" and web is None else ""
            raise InputError(f"{where}no {name} in this folder{hint}; give a .ptm or .rti file, a web/ folder "
                             "or an output folder", source)
        source = candidate
    return read_rti_hsh(source) if source.suffix.lower() == ".rti" else read_ptm(source)


def image_size(image: Relightable) -> tuple[int, int]:
    """``(width, height)`` of a relightable image as read by :func:`load_source`."""
    if isinstance(image, PublishedBasis):
        return image.shape[1], image.shape[0]
    return image.width, image.height


def describe(image: Relightable) -> str:
    """What was relit, in a few words: ``"published basis hsh3, sRGB"``, ``"PTM"``."""
    if isinstance(image, PublishedBasis):
        encoding = "linear light encoded for display" if image.encoding == "linear" else "sRGB"
        return f"published basis {image.name or image.type}, {encoding}"
    return "HSH file" if isinstance(image, RTIFile) else "PTM"


def render(
    ptm: Relightable,
    light: np.ndarray,
    mode: str = "default",
    *,
    kd: float = DEFAULT_KD,
    ks: float = DEFAULT_KS,
    exponent: float = DEFAULT_EXPONENT,
    gain: float = DEFAULT_GAIN,
) -> np.ndarray:
    """Render a relightable image under one light: a published basis as its page shows it, a PTM
    or HSH file in one of RTIViewer's modes.

    Parameters
    ----------
    ptm : PTMFile, RTIFile or PublishedBasis
        A PTM (every mode), an HSH file or a published basis (default mode).
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
        A published basis' image is display-encoded (sRGB) whatever its encoding; a file's is
        in the file's values (:func:`reconstruct.report.figures.holds_linear_light` says whether to encode them).
    """
    return next(renders(ptm, [light], mode, kd=kd, ks=ks, exponent=exponent, gain=gain))


def renders(
    ptm: Relightable,
    lights: Sequence[np.ndarray],
    mode: str = "default",
    *,
    kd: float = DEFAULT_KD,
    ks: float = DEFAULT_KS,
    exponent: float = DEFAULT_EXPONENT,
    gain: float = DEFAULT_GAIN,
) -> Iterator[np.ndarray]:
    """Render a relightable image under each of several lights (a sweep's frames), as
    :func:`render` does.

    What does not depend on the light is done once, when this is called: an RGB-format PTM's
    conversion to LRGB, the diffuse gain's coefficients and, for more than one light, the
    polynomials' maxima for the specular lobe (one light finds them band by band, holding no
    full-size array of them). Each image is then made as it is asked for. A 12-frame
    diffuse-gain sweep of a 6-megapixel PTM took 1.8 times as long when each frame redid it.

    Parameters
    ----------
    ptm : PTMFile, RTIFile or PublishedBasis
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
    InputError
        For the specular or diffuse-gain mode of an HSH file or a published basis.
    """
    # Before the long work (the conversion to LRGB, the maxima), not in the first frame.
    check_parameters(kd=kd, ks=ks, exponent=exponent, gain=gain)
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose from {', '.join(MODES)}")
    if isinstance(ptm, PublishedBasis):
        if mode != "default":
            raise InputError(f"the {mode} mode needs a PTM; the published basis {ptm.name or ptm.type} renders "
                             "in the default mode only")
        return (ptm.display(light_direction(light=light)) for light in lights)
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
