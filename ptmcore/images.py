"""Reading photographs and holding a capture's stack in bounded memory.

A capture of 50 photographs of 50 megapixels is 7.5 GB as 8-bit RGB and 30 GB as float32, so the
stack is never held like that. Each photograph is decoded once (in parallel threads) and reduced,
in one compiled pass over its pixels (:mod:`ptmcore.reduce`), to what the later stages need:

* its linear luminance as ``uint16`` (value × 65534; 65535 marks a sample where a channel
  clipped), which is finer than an 8-bit sRGB step everywhere and half the size of float32; or,
  with ``storage="auto"`` and 8-bit photographs, as an 8-bit sRGB code (255 marks a clip);
* a running per-pixel sum of its linear RGB, which becomes the pixel's colour (chromaticity);
* with :func:`load_stack_and_fits`, the sums of the fits viewers' files need
  (:class:`ptmcore.ptmencoded.EncodedFit`), so the photographs are not read a second time.

Whatever the storage, :attr:`ImageStack.table` maps a stored code to linear luminance.

Photographs are decoded by :mod:`ptmcore.decoders`: JPEG, PNG and TIFF only, each by a decoder
chosen from the file's content, every header's claimed size checked before anything is allocated.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from .bands import run_bands
from .decoders import MAX_PIXELS, allow_large_images, image_size, read_raster  # noqa: F401 - their home before decoders.py
from .diskstack import is_disk_array, release_rows
from .errors import InputError, first_few
from .lp import MIN_PHOTOGRAPHS

if TYPE_CHECKING:
    from .align import DriftProbe
    from .corrections import Corrections
    from .ptmencoded import EncodedFit, EncodedFits
    from .raw import RawDevelopment

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMA_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
#: Code of a stored luminance sample that was clipped in some channel.
SATURATED = np.uint16(65535)
_LUM_SCALE = 65534.0
#: The uint16 stack's code → linear luminance: code / 65534, and 1 for the clip mark 65535
#: (read-only; shared by every uint16 stack).
UINT16_TABLE = np.minimum(np.arange(65536, dtype=np.float32) * np.float32(1.0 / _LUM_SCALE), np.float32(1.0))
UINT16_TABLE.flags.writeable = False
#: How :func:`load_stack` stores the luminance: always uint16, or 8-bit where that loses nothing
#: the photographs had (8-bit sRGB photographs, no channel gains).
Storage = Literal["uint16", "auto"]


def _float(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v)
    return v if v.dtype == np.float64 else v.astype(np.float32, copy=False)


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """Decode sRGB values in [0, 1] to linear light (IEC 61966-2-1, exact piecewise form).

    float64 input stays float64; anything else is computed in float32.
    """
    v = _float(v)
    curve = ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(v <= 0.04045, v / 12.92, curve).astype(v.dtype, copy=False)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    """Encode linear values as sRGB (IEC 61966-2-1), clipping to [0, 1] first.

    float64 input stays float64; anything else is computed in float32.
    """
    v = np.clip(_float(v), 0.0, 1.0)
    curve = 1.055 * np.maximum(v, 0.0031308) ** (1 / 2.4) - 0.055
    return np.where(v <= 0.0031308, v * 12.92, curve).astype(v.dtype, copy=False)


def read_image(path: str | os.PathLike, *, buffer: np.ndarray | None = None,
               min_side: int | None = None, raw: RawDevelopment | None = None) -> np.ndarray:
    """Read a photograph as it is stored, or in linear sRGB when its colour profile says
    it is in another space.

    Parameters
    ----------
    path : str or PathLike
        JPEG, PNG or TIFF file (told by its content; anything else is refused, see
        :mod:`ptmcore.decoders`); 8 or 16 bit (TIFF may also be float); grey, RGB(A), palette
        or min-is-white grey. Or a camera RAW file (DNG, CR2, NEF, ..., told by its name:
        :func:`ptmcore.raw.is_raw`), developed by LibRaw (:func:`ptmcore.raw.read_raw`).
    buffer : ndarray of uint8, optional
        A JPEG is decoded into it when it is large enough, and the result is a view of it.
        Reusing one buffer saves a fresh array's page faults for every photograph, which on
        some (virtual) machines cost as much time as decoding.
    min_side : int, optional
        A JPEG is decoded at the smallest of libjpeg's DCT scales (1/8 to 1) whose sides are
        both at least this long: a thumbnail for a fraction of the work; a RAW file at half
        size when both its halved sides are that long. Other formats are read whole.
    raw : RawDevelopment, optional
        How a RAW file is developed: the capture's white balance and orientation
        (:func:`ptmcore.raw.raw_development` of its first photograph), so its photographs stay
        comparable. Default: each file's own. Ignored for other formats.

    Returns
    -------
    ndarray
        ``(H, W)`` for grey or ``(H, W, 3)`` for colour, in the file's own dtype (uint8,
        uint16 or float32). An alpha channel is dropped. With an embedded ICC profile that is
        not sRGB (Adobe RGB, ProPhoto, a grey gamma 2.2, ...), float32 linear light in sRGB's
        primaries and D65 white instead, clipped below at 0 but not above 1
        (:func:`ptmcore.decoders.apply_colour_profile`); an sRGB profile changes nothing.
        A RAW file: ``(H, W, 3)`` uint16, linear light in sRGB's primaries.

    Raises
    ------
    InputError
        If the file is missing, not a regular file, unreadable, not a JPEG, PNG or TIFF, of an
        unsupported depth or colour model, claims more pixels than its bytes or the memory
        available allow, or embeds a colour profile that cannot be used (damaged, too large,
        CMYK or Lab, or refused by littlecms); a RAW file that LibRaw cannot read.
    """
    from .decoders import apply_colour_profile, read_raster_and_profile

    path = Path(path)
    img, profile = read_raster_and_profile(path, buffer=buffer, min_side=min_side, raw=raw)
    if img.ndim == 3:
        if img.shape[2] == 1 or img.shape[2] == 2:
            img = img[..., 0]
        else:
            img = img[..., :3]
    if img.ndim not in (2, 3) or min(img.shape[:2]) < 1:
        raise InputError(f"unsupported image layout {img.shape}", path)
    if img.dtype.kind == "f":
        img = img.astype(np.float32, copy=False)
        if not np.all(np.isfinite(img)):
            raise InputError("image contains NaN or infinite values", path)
    elif img.dtype == np.int16 or img.dtype == np.int32 or img.dtype == np.uint32:
        raise InputError(f"unsupported sample type {img.dtype} (use 8 or 16 bit unsigned)", path)
    elif img.dtype != np.uint8 and img.dtype != np.uint16:
        raise InputError(f"unsupported sample type {img.dtype}", path)
    if profile is not None:
        # An sRGB profile returns the image itself (8-bit bit-identical); any other is applied.
        img = apply_colour_profile(img, profile, path)
    return img


@dataclass
class ImageStack:
    """A capture's photographs reduced to what the fit needs.

    Attributes
    ----------
    luminance : ndarray, shape (N, H, W), uint16 or uint8
        Each photograph's linear luminance as a code: ``value × 65534`` (uint16), or
        ``round(255 · sRGB_encode(value))`` (uint8, ``load_stack(storage="auto")``). The last
        code (65535 or 255, :attr:`saturated_code`) marks a sample where a channel clipped.
    chroma : ndarray, shape (H, W, 3), float32
        Per-pixel colour of unit luminance (Σ RGB / Σ luminance over the photographs; neutral
        grey where all were black): multiplying it by a luminance gives linear RGB.
    paths : list of Path
        The photographs, in order.
    bit_depth : int
        8 or 16 (32 for float TIFF); the highest among the photographs.
    linearized : bool
        Whether 8-bit sRGB values were decoded to linear light.
    saturated : ndarray, shape (N,), int64
        Number of clipped pixels in each photograph.
    table : ndarray, float32
        Code → linear luminance in [0, 1], one entry per code (65536 or 256); the last code
        (the clip mark) reads as 1. Compiled kernels read the stack through it. Default: the
        table of the codes' type (:data:`UINT16_TABLE`, or sRGB decoding for uint8).
    """

    luminance: np.ndarray
    chroma: np.ndarray
    paths: list[Path]
    bit_depth: int
    linearized: bool
    saturated: np.ndarray
    table: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.table is None:
            self.table = default_table(self.luminance.dtype)
        if self.table.dtype != np.float32 or self.table.shape != (np.iinfo(self.luminance.dtype).max + 1,):
            raise ValueError(f"a {self.luminance.dtype} stack needs a float32 table of "
                             f"{np.iinfo(self.luminance.dtype).max + 1} entries, not {self.table.dtype} {self.table.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        """Image height and width."""
        return self.luminance.shape[1], self.luminance.shape[2]

    @property
    def saturated_code(self) -> int:
        """The code that marks a clipped sample: the last one of the codes' type."""
        return int(np.iinfo(self.luminance.dtype).max)

    def __len__(self) -> int:
        return self.luminance.shape[0]

    def select(self, keep: np.ndarray) -> ImageStack:
        """The stack of the photographs where ``keep`` (N,) is true (the colour stays)."""
        keep = np.asarray(keep, dtype=bool)
        if keep.all():
            return self
        return ImageStack(self.luminance[keep], self.chroma, [p for p, k in zip(self.paths, keep) if k],
                          self.bit_depth, self.linearized, self.saturated[keep], self.table)

    def grid(self, step: int) -> np.ndarray:
        """The codes of every ``step``-th row and column of every photograph (from the middle
        of the first step), (N, ⌈H/step⌉, ⌈W/step⌉), a copy.

        A stack on disk is read a few rows at a time, each stretch's pages dropped before the
        next: the system maps 64 KB around each page read, so a sparse grid read at once
        would map most of the stack into the run's memory.
        """
        if not is_disk_array(self.luminance):
            return np.array(self.luminance[:, step // 2::step, step // 2::step])
        h = self.shape[0]
        rows = np.arange(step // 2, h, step)
        out = np.empty((len(self), len(rows), len(range(step // 2, self.shape[1], step))), self.luminance.dtype)
        per = max(1, (1 << 20) // (len(self) * self.shape[1]) // step)  # about a megabyte of rows
        done = 0
        for i in range(0, len(rows), per):
            out[:, i:i + per] = self.luminance[:, rows[i:i + per]][:, :, step // 2::step]
            end = min(h, int(rows[min(i + per, len(rows)) - 1]) + step)
            release_rows(self.luminance, done, end)
            done = end
        release_rows(self.luminance, 0, h)
        return out

    def band(self, r0: int, r1: int, c0: int | None = None, c1: int | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """Linear luminance of rows ``r0:r1`` (columns ``c0:c1``, default all) of every photograph.

        Only that box is converted to float, so a small window of a large capture stays small.

        Returns
        -------
        values : ndarray, shape (N, r1 - r0, c1 - c0), float32
            Luminance in [0, 1] (:attr:`table`); clipped samples read as 1.
        saturated : ndarray, shape (N, r1 - r0, c1 - c0), bool
            Where a channel clipped.
        """
        raw = self.luminance[:, r0:r1, c0:c1]
        saturated = raw == self.saturated_code
        values = self.table[raw]
        if c0 is None and c1 is None:
            # Whole rows are converted: a stack on disk no longer needs them in memory.
            release_rows(self.luminance, r0, r1)
        return values, saturated


def default_table(dtype: np.dtype) -> np.ndarray:
    """The code → linear luminance table of a stack stored as ``dtype`` (uint16 or uint8)."""
    if np.dtype(dtype) == np.uint16:
        return UINT16_TABLE
    if np.dtype(dtype) == np.uint8:
        table = srgb_to_linear(np.arange(256, dtype=np.float32) / np.float32(255.0))
        table[255] = 1.0
        return table
    raise ValueError(f"a stack is stored as uint16 or uint8, not {np.dtype(dtype)}")


def _chroma_in_place(channel_sum: np.ndarray, threads: int | None = None) -> np.ndarray:
    """Turn sums of luminance contributions ``w_c · C_c`` into colour of unit luminance.

    Done in place and in bands (in ``threads``): at 24 megapixels a whole-image expression
    would need a gigabyte of temporaries.
    """
    h, w = channel_sum.shape[:2]
    inv_w = (1.0 / LUMA_WEIGHTS).astype(np.float32)

    def work(r0: int, r1: int) -> None:
        band = channel_sum[r0:r1]
        lum = band.sum(axis=2, keepdims=True)
        black = lum[..., 0] <= 0
        band /= np.where(lum > 0, lum, 1.0)
        band *= inv_w
        band[black] = 1.0

    run_bands(h, max(1, (1 << 18) // w), work, threads=threads)
    return channel_sum


def load_stack(
    paths: Sequence[str | os.PathLike],
    *,
    linearize: bool = True,
    channel_gains: np.ndarray | None = None,
    min_photographs: int = MIN_PHOTOGRAPHS,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    storage: Storage = "uint16",
    on_disk: str | os.PathLike | None = None,
    corrections: Corrections | None = None,
    probe: DriftProbe | None = None,
) -> ImageStack:
    """Decode a capture's photographs into an :class:`ImageStack`.

    Parameters
    ----------
    paths : sequence of path
        The photographs, all of the same size.
    linearize : bool
        Take 8-bit images as sRGB and decode them to linear light (16-bit and float images
        are always taken as linear).
    channel_gains : ndarray, shape (N, 3), optional
        Factors for each photograph's linear R, G, B (e.g. 1 / light intensity), applied
        before the reduction to luminance; at most 1, so no sample leaves the stored range.
    min_photographs : int
        Fewer photographs are an error (three determine a normal; calibration needs fewer).
    threads : int, optional
        Decoding threads; default: the number of CPUs.
    progress : callable, optional
        Called with 1 for each photograph.
    storage : {"uint16", "auto"}
        ``"uint16"``: luminance × 65534. ``"auto"``: 8-bit sRGB codes (half the memory) when the
        first photograph is 8-bit, ``linearize`` is true and there are no channel gains, else
        uint16; a later photograph of more than 8 bits is then stored at 8 bits too.
    on_disk : path, optional
        A folder with room for the stack (N·H·W bytes, twice that as uint16): the stack is then
        a memory-mapped file there, for captures larger than memory
        (:func:`ptmcore.diskstack.disk_array`; the file is never visible in the folder).
    corrections : Corrections, optional
        Done to each photograph before it is reduced (:mod:`ptmcore.corrections`).
    probe : DriftProbe, optional
        Sees each photograph, to measure the camera's drift (:mod:`ptmcore.align`).

    Returns
    -------
    ImageStack

    Raises
    ------
    InputError
        If fewer than three photographs are given, one cannot be read, or sizes differ.
    """
    return load_stack_and_fits(paths, linearize=linearize, channel_gains=channel_gains,
                               min_photographs=min_photographs, threads=threads, progress=progress,
                               storage=storage, on_disk=on_disk, corrections=corrections, probe=probe)[0]


def _check_depths(paths: list[Path], depths: np.ndarray) -> None:
    """Refuse photographs of mixed bit depth: an 8-bit one among 16-bit ones is decoded as
    sRGB and comes out several times darker than its neighbours, with nothing to say so."""
    values, counts = np.unique(depths, return_counts=True)
    if len(values) < 2:
        return
    common = int(values[np.argmax(counts)])
    odd = [p.name for p, d in zip(paths, depths) if d != common]
    bits = ", ".join(f"{int(d)}-bit" for d in values if d != common)
    raise InputError(f"photographs of mixed bit depth: {first_few(odd)} ({bits}) among {common}-bit ones; "
                     "convert them alike", paths[0].parent)


def check_content(stack: ImageStack, grid: int = 256) -> None:
    """Refuse photographs that cannot take part in a fit: black or clipped everywhere (a flash
    that did not fire, a gross overexposure), or the same as another (a file copied over
    another), judged on a grid of about ``grid`` × ``grid`` samples and the clipped counts.

    Raises
    ------
    InputError
        Naming the photographs' folder, the photographs and what is wrong with them.
    """
    n, (h, w) = len(stack), stack.shape
    where = stack.paths[0].parent if stack.paths else None

    def refuse(names: list[str], what: str, advice: str) -> None:
        if names:
            which = f"all {n} photographs" if len(names) == n else first_few(names)
            raise InputError(f"{what} everywhere: {which}; {advice}", where)

    refuse([p.name for p, c in zip(stack.paths, stack.saturated) if c >= h * w], "clipped (white)",
           "leave them out or take them with less exposure")
    sample = stack.grid(max(1, min(h, w) // grid)).reshape(n, -1)
    refuse([p.name for p, s in zip(stack.paths, sample) if not s.any()], "black", "leave them out")
    seen: dict[bytes, Path] = {}
    same = []
    for p, s in zip(stack.paths, sample):
        key = s.tobytes()
        # A photograph the .lp lists twice is the same file, not a copy (the .lp reader warns).
        if key in seen and seen[key] != p:
            same.append(f"{p.name} = {seen[key].name}")
        seen.setdefault(key, p)
    if len(seen) == 1:
        raise InputError(f"all {n} photographs are identical: the light must move between them", where)
    if same:
        raise InputError(f"photographs identical to another ({first_few(same, sep='; ')}): one was copied over "
                         "the other", where)


def load_stack_and_fits(
    paths: Sequence[str | os.PathLike],
    *,
    fit: EncodedFit | None = None,
    linearize: bool = True,
    channel_gains: np.ndarray | None = None,
    min_photographs: int = MIN_PHOTOGRAPHS,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    storage: Storage = "uint16",
    on_disk: str | os.PathLike | None = None,
    corrections: Corrections | None = None,
    probe: DriftProbe | None = None,
) -> tuple[ImageStack, EncodedFits | None]:
    """:func:`load_stack`, and in the same decoding pass the fits viewers' files need.

    Parameters
    ----------
    paths : sequence of path
        The photographs, all of the same size.
    fit : EncodedFit, optional
        The PTM (LRGB or RGB format) and HSH to fit to the photographs as encoded, with their
        light directions (one per photograph). Each photograph is decoded once for the stack
        and these fits: the results equal :func:`ptmcore.ptmencoded.fit_ptm_encoded`,
        :func:`~ptmcore.ptmencoded.fit_ptm_rgb_encoded` and :func:`ptmcore.rtifile.fit_rti_hsh`
        of the files, bit for bit.
    linearize, channel_gains, min_photographs, threads, progress, storage, on_disk, corrections, probe
        As :func:`load_stack`.

    Returns
    -------
    stack : ImageStack
    fits : EncodedFits or None
        None without ``fit``.

    Raises
    ------
    InputError
        As :func:`load_stack`.
    """
    from .ptmencoded import EncodedFits, finish_lrgb
    from .reduce import reduce_photographs  # numba's import costs a second; `import ptmcore` does not need it

    paths = [Path(p) for p in paths]
    if not paths:
        raise InputError("no photographs given")
    if len(paths) < min_photographs:
        raise InputError(
            f"{len(paths)} photograph(s) given; at least {min_photographs} are needed to recover normals",
            paths[0].parent)
    if storage not in ("uint16", "auto"):
        raise ValueError(f"storage must be 'uint16' or 'auto', not {storage!r}")
    if channel_gains is not None:
        channel_gains = np.asarray(channel_gains, dtype=np.float32).reshape(len(paths), 3)
        if not (np.all(np.isfinite(channel_gains)) and np.all(channel_gains > 0) and channel_gains.max() <= 1):
            raise ValueError("channel gains must be finite, positive and at most 1")
    if fit is not None:
        fit.matrices(len(paths))  # bad directions fail before any photograph is decoded
    done = reduce_photographs(paths, linearize=linearize, channel_gains=channel_gains, storage=storage,
                              fit=fit, threads=threads, progress=progress, on_disk=on_disk,
                              corrections=corrections, probe=probe)
    _check_depths(paths, done.depths)
    stack = ImageStack(done.luminance, done.chroma, paths, int(done.depths.max()), linearize, done.saturated,
                       done.table)
    if fit is None:
        return stack, None
    fits = EncodedFits(paths, fit, hsh=done.hsh)
    if done.ptm_sums is not None:
        fits.coefficients, fits.rgb = finish_lrgb(done.ptm_sums, done.ptm_aux, threads=threads)
    else:
        fits.coefficients = done.channel_sums
    return stack, fits

