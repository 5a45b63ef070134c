"""One decoding pass: each photograph reduced, in one read of its pixels, to all the run needs.

A run needs two views of the same photographs: the linear-luminance stack the normals are fitted
to (:func:`ptmcore.images.load_stack`) and the sums of the fits made in the photographs' own
encoding for viewers' files (HP's PTM, :mod:`ptmcore.ptmencoded`; RTIBuilder's HSH,
:func:`ptmcore.rtifile.fit_rti_hsh`). Decoding a 24-megapixel JPEG takes about 0.2 s of CPU;
in NumPy and OpenCV each of the two reductions took as long again, as chains of element-wise
passes over the photograph, and the viewers' fits decoded every photograph a second time.

Here one compiled kernel (:func:`_reduce_rows`, numba) visits each pixel of a band of rows
once per group of photographs and, for every photograph of the group in order:

* linearises each channel through a table (or computes it, for float TIFF) into its
  contribution ``w_c · linear_c · 65534`` to the luminance, marks a pixel where a channel
  clipped, and writes the stack's code (uint16, or 8-bit sRGB with ``storage="auto"``);
* adds the contributions to the colour sums (the chromaticity);
* adds the encoded fits: HP's LRGB sums (luma ``0.2125 R + 0.7154 G + 0.0721 B`` of the bytes,
  the six pseudoinverse-weighted sums, the peak, Σ C·Y, Σ Y²), the 18 per-channel sums of an
  RGB PTM, the 3·K per-channel sums of an HSH.

The arithmetic is the NumPy code's, in float32 and in the same order (numba does not contract a
product and a sum into one fused multiply-add without ``fastmath``), so a ``.ptm`` file's bytes
do not change (``tests/test_one_decode.py`` and HP's fixture in ``tests/test_ptmfile.py``).
The sums are the memory traffic that costs most (14 float32 per pixel with an LRGB PTM): they
are read and written once per group of photographs, a short stretch of a row at a time kept in
the first-level cache while the group's photographs are added to it.

The kernel releases the GIL and runs in the caller's threads on bands of rows
(:func:`ptmcore.streaming.run_in_groups`: the threads decode a group, then add it band by
band), so ``threads`` is respected and numba's threading layer is not involved. Compiled code is cached on disk
(``cache=True``), so only the first run after installation pays for compilation.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np
from numba import types
from numba.extending import overload

from .bands import run_bands
from .diskstack import disk_array, release_rows
from .errors import InputError
from .images import _LUM_SCALE, LUMA_WEIGHTS, UINT16_TABLE, _chroma_in_place, default_table, linear_to_srgb, srgb_to_linear
from .ptmencoded import HP_LUMA_WEIGHTS, EncodedFit
from .resources import RUN_BASE_MB, RUN_BYTES_PER_PIXEL, thread_count
from .streaming import Photographs, check_same_size, run_in_groups

if TYPE_CHECKING:
    from .align import DriftProbe
    from .corrections import Corrections

__all__ = ["Reduced", "reduce_photographs", "srgb8_tables"]

#: Photographs per kernel call (and per group, see :func:`ptmcore.streaming.run_in_groups`):
#: the kernel's tuple of images always has this length, padded, so that numba compiles one
#: version per sample type only.
_BATCH = 8
#: Pixels of a row the kernel works on at a time: its scratch rows (a few dozen of them)
#: then stay in the first-level cache.
_CHUNK = 256
#: Pixels per band of rows: the unit of work of a thread.
_BAND_PIXELS = 1 << 18
#: Memory for the decoded photographs of a group: at most this, and at most what the run's
#: memory bound (:data:`ptmcore.resources.RUN_BASE_MB`, ``RUN_BYTES_PER_PIXEL``) leaves beside
#: the process's own memory and the sums. At 24 megapixels (72 MB as 8-bit RGB) that is 4
#: photographs: each pixel's sums are then read and written once per 4 photographs, which made
#: the reduction 1.6× faster than once per 2. Once per 6 (450 MB) made a 24-megapixel run of 48
#: photographs about 0.9 s (5 %) faster, but its peak, 1960 MiB, passed the 2 GB target read as
#: 2 × 10^9 bytes (as /usr/bin/time's kilobytes show it); 5 photographs (1890 MiB) kept within
#: 1 % of it. With 4 the peak is 1816 MiB (issue 14's notes).
_GROUP_BYTES = 300 << 20
#: The process's own memory while decoding (270–290 MB measured). The peak while decoding is
#: that, the sums and the group, so a group gets what the run's bound leaves beside the other
#: two: for HP's LRGB fit (56 bytes per pixel of sums) 100 MB + 14 bytes per pixel. Eight 8-bit
#: photographs of 18 megapixels (24 bytes per pixel) had peaked at 1663 MiB against that
#: bound's 1602; six at 1520 MiB.
_OWN_BYTES = 300 << 20


def _contribution(lut, wscale, i, ch, v):  # pragma: no cover - replaced in compiled code
    """Channel ``ch``'s contribution ``w · linear · 65534`` (an integer) of sample ``v``."""
    raise NotImplementedError


@overload(_contribution)
def _contribution_impl(lut, wscale, i, ch, v):  # pragma: no cover - typing-time dispatch
    if isinstance(v, types.Integer):
        # 8- and 16-bit: the table built by _Tables (sRGB decoding, weight and gain folded in).
        def table(lut, wscale, i, ch, v):
            return np.int32(lut[ch, v])

        return table

    # float32 TIFF: as the NumPy reduction did it, clip to [0, 1], scale, round half to even.
    def computed(lut, wscale, i, ch, v):
        return np.int32(np.rint(min(max(v, np.float32(0.0)), np.float32(1.0)) * wscale[i, ch]))

    return computed


def _encoded(enc, scale, v):  # pragma: no cover - replaced in compiled code
    """Sample ``v`` in the 0..255 units of the encoded fits."""
    raise NotImplementedError


@overload(_encoded)
def _encoded_impl(enc, scale, v):  # pragma: no cover - typing-time dispatch
    if isinstance(enc, types.NoneType):
        # The samples' own encoding (HP's PTMfitter), or one that only needs scaling.
        def scaled(enc, scale, v):
            return np.float32(v) * scale

        return scaled
    if isinstance(v, types.Integer):
        def table(enc, scale, v):
            return enc[v]

        return table

    # float32 TIFF (linear) shown as sRGB: IEC 61966-2-1 on the clipped value.
    def srgb(enc, scale, v):
        x = min(max(v, np.float32(0.0)), np.float32(1.0))
        if x <= np.float32(0.0031308):
            return np.float32(255.0) * (np.float32(12.92) * x)
        return np.float32(255.0) * (np.float32(1.055) * x ** np.float32(1.0 / 2.4) - np.float32(0.055))

    return srgb


@numba.njit(nogil=True, cache=True, inline="always")
def _channel_sums(sums, acc, r, c0, nc, load):  # pragma: no cover - compiled
    """Copy a per-channel fit's sums (H, W, 3, K) of row ``r``, columns ``c0:c0 + nc``, into
    the scratch rows ``acc`` (3·K, _CHUNK) when ``load``, else back from them."""
    k = sums.shape[3]
    for c in range(nc):
        for ch in range(3):
            for j in range(k):
                if load:
                    acc[ch * k + j, c] = sums[r, c0 + c, ch, j]
                else:
                    sums[r, c0 + c, ch, j] = acc[ch * k + j, c]


@numba.njit(nogil=True, cache=True, inline="always")
def _add_channel_fit(acc, ee, mat, k, nc):  # pragma: no cover - compiled
    """Add photograph ``k``'s encoded samples ``ee`` (3, _CHUNK) to a per-channel fit's
    scratch rows: ``acc[ch·K + j] += ee[ch] · mat[j, k]``."""
    kk = mat.shape[0]
    for ch in range(3):
        for j in range(kk):
            f = mat[j, k]
            for c in range(nc):
                acc[ch * kk + j, c] += ee[ch, c] * f


@numba.njit(nogil=True, cache=True)
def _reduce_rows(images, m, ks, r0, r1, luts, wscale, top, enc_scale, enc, lum16, lum8, to8, chan, hp, ptm_pinv,
                 ptm_sums, ptm_aux, mat_a, sums_a, mat_b, sums_b):  # pragma: no cover - compiled
    """Add rows ``r0:r1`` of the first ``m`` images of ``images`` (photographs ``ks``, in order).

    What is not wanted is passed as None: numba prunes ``x is None`` branches of arguments
    when it compiles, so each combination gets lean code of its own.

    The work goes a chunk of :data:`_CHUNK` pixels of a row at a time. The chunk's sums are
    copied into small scratch rows (one row per sum, so a pixel's sums sit in the same column of
    each), every photograph of the group is added to them, and they are copied back: the large
    arrays are read and written once per group. For each photograph a scalar loop does what
    needs table look-ups (the luminance codes, clip marks and per-channel contributions; LLVM
    emits no gathers for x86 CPUs where they are slow), and the float sums are then loops over
    the scratch rows alone, contiguous, which LLVM vectorises. The chunk of a photograph is read
    as one flat row (``ravel``): indexed as (row, column, channel) LLVM did not vectorise the
    loads, and the kernel was 1.7× slower.

    Parameters
    ----------
    images : tuple of ndarray (H, W, 3)
        One sample type and layout (grey is a view repeating its channel). Padded to
        :data:`_BATCH`; only ``m`` are used.
    ks : ndarray (m,), int64
        Their photograph indices, ascending.
    luts, wscale
        Each channel's luminance contribution of a sample of ``images[i]``: ``luts[i][c, v]``
        for integer samples, ``rint(clip(v, 0, 1) · wscale[i, c])`` for floats.
    top : scalar of the images' type
        A sample above this is clipped (254, 65534, or the float below 1).
    enc_scale : float32
        Sample → 0..255 units of the encoded fits (1, 1/257 or 255).
    enc : ndarray (2^bits,), float32, or None
        Sample → 0..255 units of the encoded fits when they are in another encoding than the
        samples' own (:func:`_encoding_table`); None: ``sample · enc_scale``.
    lum16, lum8, to8, chan : ndarray or None
        The stack: uint16 codes (N, H, W), or 8-bit codes through the table ``to8``
        (65536,); the colour sums (H, W, 3). None without a stack.
    hp, ptm_pinv, ptm_sums, ptm_aux
        HP's luma weights (3,), the LRGB pseudoinverse (6, N), the sums (H, W, 6) and the
        peak, Σ C·Y and Σ Y² (H, W, 5); ``ptm_sums`` None without an LRGB fit.
    mat_a, sums_a, mat_b, sums_b
        Two per-channel fits (RGB-format PTM, HSH): matrices (K, N) and sums (H, W, 3, K);
        ``sums_*`` None when not wanted.

    Returns
    -------
    ndarray (len(images),), int64
        Clipped pixels of each image (with the stack).
    """
    w = images[0].shape[1]
    hr, hg, hb = hp[0], hp[1], hp[2]
    f32 = np.float32
    counts = np.zeros(len(images), np.int64)
    fitted = ptm_sums is not None or sums_a is not None or sums_b is not None
    # Scratch rows: the contributions t (int32) and encoded samples e of one photograph, and
    # the accumulated sums of the chunk.
    tt = np.empty((3, _CHUNK), np.int32)
    ee = np.empty((3, _CHUNK), f32)
    acc_c = np.empty((3, _CHUNK), f32)
    acc_p = np.empty((11, _CHUNK), f32)
    ka = 0 if sums_a is None else mat_a.shape[0]
    kb = 0 if sums_b is None else mat_b.shape[0]
    acc_a = np.empty((3 * ka, _CHUNK), f32)
    acc_b = np.empty((3 * kb, _CHUNK), f32)
    for r in range(r0, r1):
        for c0 in range(0, w, _CHUNK):
            nc = min(_CHUNK, w - c0)
            if chan is not None:
                for c in range(nc):
                    acc_c[0, c] = chan[r, c0 + c, 0]
                    acc_c[1, c] = chan[r, c0 + c, 1]
                    acc_c[2, c] = chan[r, c0 + c, 2]
            if ptm_sums is not None:
                for c in range(nc):
                    for j in range(6):
                        acc_p[j, c] = ptm_sums[r, c0 + c, j]
                    for j in range(5):
                        acc_p[6 + j, c] = ptm_aux[r, c0 + c, j]
            if sums_a is not None:
                _channel_sums(sums_a, acc_a, r, c0, nc, True)
            if sums_b is not None:
                _channel_sums(sums_b, acc_b, r, c0, nc, True)
            for i in range(m):
                img = images[i]
                k = ks[i]
                # The scalar part: what needs tables, and the samples in scratch rows.
                nclip = 0
                lut = luts[i]
                px = img[r, c0:c0 + nc].ravel()
                row16 = lum16[k, r, c0:c0 + nc] if lum16 is not None else None
                row8 = lum8[k, r, c0:c0 + nc] if lum8 is not None else None
                for c in range(nc):
                    v0 = px[3 * c]
                    v1 = px[3 * c + 1]
                    v2 = px[3 * c + 2]
                    if chan is not None:
                        t0 = _contribution(lut, wscale, i, 0, v0)
                        t1 = _contribution(lut, wscale, i, 1, v1)
                        t2 = _contribution(lut, wscale, i, 2, v2)
                        tt[0, c] = t0
                        tt[1, c] = t1
                        tt[2, c] = t2
                        code = min(t0 + t1 + t2, 65534)
                        if v0 > top or v1 > top or v2 > top:
                            code = 65535  # images.SATURATED
                            nclip += 1
                        # Unsigned indices: numba then leaves out the negative-index
                        # wrap-around (6 % off this kernel).
                        if lum16 is not None:
                            row16[np.uintp(c)] = code
                        if lum8 is not None:
                            row8[np.uintp(c)] = to8[np.uintp(code)]
                counts[i] += nclip
                # The vectorised part, in the order of the NumPy arithmetic it replaced.
                if fitted:
                    for c in range(nc):
                        ee[0, c] = _encoded(enc, enc_scale, px[3 * c])
                        ee[1, c] = _encoded(enc, enc_scale, px[3 * c + 1])
                        ee[2, c] = _encoded(enc, enc_scale, px[3 * c + 2])
                if chan is not None:
                    for c in range(nc):
                        acc_c[0, c] += f32(tt[0, c])
                        acc_c[1, c] += f32(tt[1, c])
                        acc_c[2, c] += f32(tt[2, c])
                if ptm_sums is not None:
                    p0 = ptm_pinv[0, k]
                    p1 = ptm_pinv[1, k]
                    p2 = ptm_pinv[2, k]
                    p3 = ptm_pinv[3, k]
                    p4 = ptm_pinv[4, k]
                    p5 = ptm_pinv[5, k]
                    for c in range(nc):
                        e0 = ee[0, c]
                        e1 = ee[1, c]
                        e2 = ee[2, c]
                        y = e0 * hr + e1 * hg + e2 * hb
                        acc_p[0, c] += y * p0
                        acc_p[1, c] += y * p1
                        acc_p[2, c] += y * p2
                        acc_p[3, c] += y * p3
                        acc_p[4, c] += y * p4
                        acc_p[5, c] += y * p5
                        peak = acc_p[6, c]
                        acc_p[6, c] = y if y > peak else peak
                        acc_p[7, c] += e0 * y
                        acc_p[8, c] += e1 * y
                        acc_p[9, c] += e2 * y
                        acc_p[10, c] += y * y
                if sums_a is not None:
                    _add_channel_fit(acc_a, ee, mat_a, k, nc)
                if sums_b is not None:
                    _add_channel_fit(acc_b, ee, mat_b, k, nc)
            if chan is not None:
                for c in range(nc):
                    chan[r, c0 + c, 0] = acc_c[0, c]
                    chan[r, c0 + c, 1] = acc_c[1, c]
                    chan[r, c0 + c, 2] = acc_c[2, c]
            if ptm_sums is not None:
                for c in range(nc):
                    for j in range(6):
                        ptm_sums[r, c0 + c, j] = acc_p[j, c]
                    for j in range(5):
                        ptm_aux[r, c0 + c, j] = acc_p[6 + j, c]
            if sums_a is not None:
                _channel_sums(sums_a, acc_a, r, c0, nc, False)
            if sums_b is not None:
                _channel_sums(sums_b, acc_b, r, c0, nc, False)
    return counts


def srgb8_tables() -> tuple[np.ndarray, np.ndarray]:
    """The 8-bit stack's tables: uint16 code → 8-bit code (65536,), 8-bit code → linear (256,).

    An 8-bit code is ``round(255 · sRGB_encode(linear))``; 255 is reserved for a clipped
    sample, so an unclipped one that rounds to 255 stores 254. Linear of code 255 reads as 1.
    """
    lin = np.arange(65535, dtype=np.float64) / _LUM_SCALE
    to8 = np.empty(65536, np.uint8)
    to8[:65535] = np.minimum(np.rint(255.0 * linear_to_srgb(lin)), 254)
    to8[65535] = 255
    return to8, default_table(np.dtype(np.uint8))


@dataclass
class Reduced:
    """What :func:`reduce_photographs` made.

    Attributes
    ----------
    luminance : ndarray (N, H, W), uint16 or uint8, or None
        The stack's codes (see :class:`ptmcore.images.ImageStack`).
    table : ndarray, float32, or None
        Code → linear luminance.
    chroma : ndarray (H, W, 3), float32, or None
    saturated : ndarray (N,), int64, or None
        Clipped pixels per photograph.
    depths : ndarray (N,), int
        Bits per sample of each photograph.
    ptm_sums, ptm_aux : ndarray (H, W, 6) and (H, W, 5), float32, or None
        HP's LRGB sums (:func:`ptmcore.ptmencoded.finish_lrgb` makes the coefficients).
    channel_sums : ndarray (H, W, 3, 6), float32, or None
        The RGB-format PTM's coefficients.
    hsh : ndarray (H, W, 3, K), float32, or None
        The HSH coefficients (0..1 units).
    """

    luminance: np.ndarray | None
    table: np.ndarray | None
    chroma: np.ndarray | None
    saturated: np.ndarray | None
    depths: np.ndarray
    ptm_sums: np.ndarray | None
    ptm_aux: np.ndarray | None
    channel_sums: np.ndarray | None
    hsh: np.ndarray | None


class _Tables:
    """Per sample type: each channel's luminance contribution, for every photograph's gains, and
    the samples' values in the encoded fits' ``encoding`` (:func:`_encoding_table`)."""

    def __init__(self, linearize: bool, gains: np.ndarray | None, n: int, encoding: str = "stored") -> None:
        self.linearize = linearize
        self.encoding = encoding
        self._encoded: dict[np.dtype, np.ndarray | None] = {}
        # One set of tables without gains; one per photograph with them.
        self.weights = (LUMA_WEIGHTS[None, :] if gains is None
                        else (LUMA_WEIGHTS[None, :] * gains).astype(np.float32))
        self.lut_of = np.zeros(n, np.int64) if gains is None else np.arange(n, dtype=np.int64)
        self.wscale = (self.weights * np.float32(_LUM_SCALE)).astype(np.float32)
        self._luts: dict[np.dtype, np.ndarray] = {}

    def for_photographs(self, dtype: np.dtype, ks: np.ndarray) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
        """The kernel's tables of photographs ``ks``: a (3, 2^bits) uint16 table each (a
        1-entry dummy for floats), padded to :data:`_BATCH`, and their (_BATCH, 3) float scales."""
        luts = self._luts.get(dtype)
        if luts is None:
            # Two threads may both build it on first use of a sample type: harmless.
            luts = self._luts[dtype] = self._build(dtype)
        rows = self.lut_of[ks]
        rows = np.concatenate([rows, np.repeat(rows[:1], _BATCH - len(rows))])
        return tuple(luts[i] for i in rows), self.wscale[rows]

    def encoded(self, dtype: np.dtype) -> np.ndarray | None:
        """The kernel's ``enc`` for samples of ``dtype`` (made on first use; two threads may
        both make it: harmless)."""
        if dtype not in self._encoded:
            self._encoded[dtype] = _encoding_table(dtype, self.encoding, self.linearize)
        return self._encoded[dtype]

    def _build(self, dtype: np.dtype) -> np.ndarray:
        import cv2

        if dtype == np.uint8:
            # The 8-bit rule of the OpenCV reduction this replaces, so that codes are unchanged.
            v = np.arange(256, dtype=np.float32) / np.float32(255.0)
            lin = srgb_to_linear(v) if self.linearize else v
            # C order (np.stack keeps the transposes' layout): the kernel then indexes the
            # table with constant strides (3 % faster).
            return np.ascontiguousarray(
                np.stack([np.round(lin[:, None] * wt * _LUM_SCALE).astype(np.uint16).T for wt in self.weights]))
        if dtype == np.uint16:
            # 16-bit samples are linear: cv2.transform's rounding of v · w · 65534/65535, read
            # off a ramp of every value so that codes are the transform's own.
            ramp = np.repeat(np.arange(65536, dtype=np.uint16).reshape(1, -1, 1), 3, axis=2)
            out = [cv2.transform(ramp, np.diag(wt * np.float32(_LUM_SCALE / 65535.0)))[0].T for wt in self.weights]
            return np.ascontiguousarray(np.stack(out))
        # Float samples are scaled, not looked up (wscale): a placeholder per set of gains.
        return np.zeros((len(self.weights), 3, 1), np.uint16)


class _Buffers:
    """Memory for decoded JPEG photographs, reused from one to the next.

    A fresh array per photograph costs page faults as long as decoding it on some (virtual)
    machines; at most one buffer per photograph held at a time is ever made.
    """

    def __init__(self, nbytes: int) -> None:
        self._nbytes = nbytes
        self._free: list[np.ndarray] = []
        self._lock = threading.Lock()

    def take(self) -> np.ndarray | None:
        """A buffer (None when photographs are not 8-bit: they are not JPEGs)."""
        if self._nbytes == 0:
            return None
        with self._lock:
            if self._free:
                return self._free.pop()
        return np.empty(self._nbytes, np.uint8)

    def give(self, buf: np.ndarray) -> None:
        """Return a buffer whose photograph is done."""
        with self._lock:
            self._free.append(buf)


def _kernel_view(img: np.ndarray) -> np.ndarray:
    """A photograph as the kernel reads it: (H, W, 3) uint8, uint16 or float32.

    Colour is made C-contiguous (a PNG's BGR → RGB view is copied); grey becomes a view that
    repeats its one channel (stride 0), so the kernel reads channels 0, 1, 2 either way: with
    the channel index fixed it runs 15 % faster than with one taken from the shape.
    """
    if img.dtype.kind == "f" and img.dtype != np.float32:
        img = img.astype(np.float32)
    if img.ndim == 2 or img.shape[2] == 1:
        grey = np.ascontiguousarray(img.reshape(img.shape[:2]))
        return np.broadcast_to(grey[:, :, None], grey.shape + (3,))
    return np.ascontiguousarray(img)


def _kind(img: np.ndarray) -> tuple[np.dtype, bool, bool]:
    """What numba types a photograph by: sample type, contiguous layout, writeable; one
    kernel call takes photographs of one kind (a tuple indexed at run time must be uniform)."""
    return img.dtype, img.flags.c_contiguous, img.flags.writeable


def _top(dtype: np.dtype) -> np.generic:
    """Samples above this are clipped: 255, 65535, and float values of 1 or more. Of the
    samples' own type: comparing in float64 slowed the kernel."""
    if dtype == np.uint8:
        return np.uint8(254)
    if dtype == np.uint16:
        return np.uint16(65534)
    return np.nextafter(np.float32(1.0), np.float32(0.0))


def _encoded_scale(dtype: np.dtype) -> np.float32:
    """Sample → 0..255 units of the encoded fits (65535 ↦ 255; floats × 255)."""
    if dtype == np.uint8:
        return np.float32(1.0)
    if dtype == np.uint16:
        return np.float32(1 / 257)
    return np.float32(255)


def _encoding_table(dtype: np.dtype, encoding: str, srgb_bytes: bool) -> np.ndarray | None:
    """The kernel's ``enc``: sample → 0..255 value of the encoded fits in ``encoding``.

    None where that is the sample times :func:`_encoded_scale` (the samples' own encoding, or
    one they are already in); for float samples shown as sRGB a 1-entry placeholder (the kernel
    computes the curve). ``srgb_bytes``: 8-bit samples are sRGB (else linear).
    """
    if encoding == "stored":
        return None
    if dtype == np.uint8:
        if (encoding == "srgb") == srgb_bytes:
            return None
        v = np.arange(256, dtype=np.float64) / 255.0
    elif dtype == np.uint16:
        if encoding == "linear":
            return None
        v = np.arange(65536, dtype=np.float64) / 65535.0
    else:
        return None if encoding == "linear" else np.zeros(1, np.float32)
    curve = linear_to_srgb(v) if encoding == "srgb" else srgb_to_linear(v)
    return (255.0 * curve).astype(np.float32)


def _group_size(first: np.ndarray, threads: int, sums_bytes: int) -> int:
    """Photographs per group: within :data:`_GROUP_BYTES` and what the run's memory bound
    leaves beside the process's own memory (:data:`_OWN_BYTES`) and the sums (``sums_bytes``),
    but at least one per thread (so that they all decode), and at most :data:`_BATCH`."""
    bound = (RUN_BASE_MB << 20) + RUN_BYTES_PER_PIXEL * first.shape[0] * first.shape[1]
    room = bound - _OWN_BYTES - sums_bytes
    budget = min(_GROUP_BYTES, room)
    return int(max(1, min(_BATCH, max(threads, budget // max(1, first.nbytes)))))


def reduce_photographs(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    *,
    stack: bool = True,
    linearize: bool = True,
    channel_gains: np.ndarray | None = None,
    storage: str = "uint16",
    fit: EncodedFit | None = None,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    on_disk: str | os.PathLike | None = None,
    corrections: Corrections | None = None,
    probe: DriftProbe | None = None,
) -> Reduced:
    """Decode each photograph once and reduce it to the stack and the encoded fits' sums.

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        The photographs, all of one size.
    stack : bool
        Make the linear-luminance stack, the colour sums and the clipped counts.
    linearize : bool
        Take 8-bit photographs as sRGB (for the stack, and for the encoded fits when
        ``fit.encoding`` is not ``"stored"``).
    channel_gains : ndarray (N, 3), float32, optional
        Factors of each photograph's linear R, G, B, checked by the caller.
    storage : {"uint16", "auto"}
        The stack's codes: uint16, or with ``"auto"`` 8-bit sRGB codes when the first
        photograph is 8-bit, ``linearize`` is true and there are no gains
        (:func:`ptmcore.images.load_stack`).
    fit : EncodedFit, optional
        The fits in the photographs' own encoding to add up in the same pass.
    threads : int, optional
        Decoding and reducing threads; default: the number of CPUs.
    progress : callable, optional
        Called with 1 for each photograph, when its group is done.
    on_disk : path, optional
        A folder: the stack is then a memory-mapped file there
        (:func:`ptmcore.diskstack.disk_array`) instead of an array in memory, each band's
        pages released from the process once written.
    corrections : Corrections, optional
        What is done to each photograph after decoding (:mod:`ptmcore.corrections`: ambient
        light, alignment). A corrected photograph is reduced as float32 linear RGB.
    probe : DriftProbe, optional
        Given each photograph (as reduced, before any alignment) to measure the camera's drift
        afterwards (:func:`ptmcore.align.measure_drift`).

    Returns
    -------
    Reduced

    Raises
    ------
    InputError
        If no photograph is given, one cannot be read, or sizes differ.
    """
    photos = Photographs(images, raw=corrections.raw if corrections is not None else None)
    n = len(photos)
    if n < 1:
        raise InputError("no photographs given")
    correct = corrections is not None and corrections.active
    first = photos.load(0)
    h, w = first.shape[:2]
    first_depth = first.dtype.itemsize * 8
    if correct:
        first = corrections.apply(0, first, linearize)
    workers = thread_count(threads)
    counting = threading.Lock()  # threads add the clipped counts of their bands
    # 8-bit codes keep an 8-bit sRGB photograph's precision (a code per input level, finer in
    # the shadows); gains or linear 8-bit input would need finer steps in the highlights.
    eight = storage == "auto" and first.dtype == np.uint8 and linearize and channel_gains is None
    tables = _Tables(linearize, channel_gains, n, "stored" if fit is None else fit.encoding)

    f32 = np.float32
    zeroed: list[np.ndarray] = []

    def zeros(shape: tuple[int, ...]) -> np.ndarray:
        zeroed.append(np.empty(shape, f32))  # filled below
        return zeroed[-1]

    # What is not asked for is None: the kernel compiles without it (see _reduce_rows).
    lum16 = lum8 = to8 = table = chan = None
    clipped = np.zeros(n, np.int64)
    if stack:
        chan = zeros((h, w, 3))
        codes = np.empty if on_disk is None else lambda shape, dtype: disk_array(on_disk, shape, dtype)
        if eight:
            lum8 = codes((n, h, w), np.uint8)
            to8, table = srgb8_tables()
        else:
            lum16 = codes((n, h, w), np.uint16)
    hp = HP_LUMA_WEIGHTS.astype(f32)
    ptm_pinv = ptm_sums = ptm_aux = mat_a = sums_a = mat_b = sums_b = None
    if fit is not None:
        ptm_matrix, hsh_matrix = fit.matrices(n)
        if fit.ptm_format == "lrgb":
            ptm_pinv = ptm_matrix
            ptm_sums = zeros((h, w, 6))
            ptm_aux = zeros((h, w, 5))
        elif fit.ptm_format == "rgb":
            mat_a = ptm_matrix
            sums_a = zeros((h, w, 3, 6))
        if hsh_matrix is not None:
            mat_b = hsh_matrix
            sums_b = zeros((h, w, 3, hsh_matrix.shape[0]))
    # The sums are zeroed in bands by all threads before decoding starts. With np.zeros the
    # first task would touch (page in) every page of them while the second waited behind it:
    # 1.35 GB at 24 megapixels, seconds on a machine where fresh memory is slow to map.
    run_bands(h, max(1, _BAND_PIXELS // w), lambda r0, r1: [a[r0:r1].fill(0) for a in zeroed], threads=workers)
    per_group = _group_size(first, workers, sum(a.nbytes for a in zeroed))
    depths = np.zeros(n, np.int64)
    held = [first]  # photograph 0 until its group takes it (and frees it)
    buffers = _Buffers(first.nbytes if first.dtype == np.uint8 else 0)
    del first
    first_path = photos.path(0)

    def prepare(k: int) -> tuple[int, np.ndarray, np.ndarray | None]:
        buf = buffers.take() if k > 0 and photos.path(k) is not None else None
        img = held.pop() if k == 0 else photos.load(k, buf)
        if buf is not None and not np.may_share_memory(img, buf):
            buffers.give(buf)  # not a JPEG: decoded into an array of its own
            buf = None
        check_same_size(img, (h, w), k, photos.path(k), first_path)
        depths[k] = first_depth if k == 0 else img.dtype.itemsize * 8
        if correct and k > 0:
            img = corrections.apply(k, img, linearize)
            if buf is not None:  # the corrected photograph is a new array
                buffers.give(buf)
                buf = None
        view = _kernel_view(img)
        if probe is not None:
            probe.take(k, view, view.dtype == np.uint8 and linearize)
        return k, view, buf

    def release(prepared: list[tuple[int, np.ndarray, np.ndarray | None]]) -> None:
        for _, _, buf in prepared:
            if buf is not None:
                buffers.give(buf)

    def add_batch(prepared: list[np.ndarray], k0: int, r0: int, r1: int) -> None:
        # Consecutive photographs of one kind go to the kernel together.
        i = 0
        while i < len(prepared):
            j = i + 1
            while j < len(prepared) and _kind(prepared[j]) == _kind(prepared[i]):
                j += 1
            group = prepared[i:j]
            dtype = group[0].dtype
            padded = tuple(group + [group[0]] * (_BATCH - len(group)))
            ks = np.arange(k0 + i, k0 + j, dtype=np.int64)
            luts, wscale = tables.for_photographs(dtype, ks)
            counts = _reduce_rows(padded, len(group), ks, r0, r1, luts, wscale, _top(dtype), _encoded_scale(dtype),
                                  tables.encoded(dtype), lum16, lum8, to8, chan, hp, ptm_pinv, ptm_sums, ptm_aux, mat_a, sums_a,
                                  mat_b, sums_b)
            with counting:
                clipped[ks] += counts[: len(group)]
            i = j
        # A stack on disk: the band's new rows leave the process (they stay in the file).
        release_rows(lum16 if lum16 is not None else lum8, r0, r1, range(k0, k0 + len(prepared)))

    rows = max(1, _BAND_PIXELS // w)
    bands = [(r0, min(h, r0 + rows)) for r0 in range(0, h, rows)]
    # A group's prepared photographs carry their indices: the kernel needs them for the
    # matrices' columns and the stack's planes.
    run_in_groups(n, per_group, prepare,
                 lambda prepared, r0, r1: add_batch([p for _, p, _ in prepared], prepared[0][0], r0, r1),
                 bands, threads=workers, progress=progress, release=release)
    return Reduced(
        lum16 if lum16 is not None else lum8, UINT16_TABLE if lum16 is not None else table,
        _chroma_in_place(chan, workers) if stack else None, clipped if stack else None, depths,
        ptm_sums, ptm_aux, sums_a, sums_b,
    )
