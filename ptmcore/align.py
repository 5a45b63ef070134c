"""The camera's drift between photographs: measured, and undone by resampling.

A bumped tripod or a sagging head moves the camera between photographs; a pixel then sees a
different point of the object in each, and every fit (PTM, normals) mixes neighbours: half the
photographs of a synthetic tablet moved by 4 × 3 px raised the mean normal error from 0.28° to
4.4°, and every other one moved by half a pixel to 0.73°.

Two photographs under different lights cannot be compared directly (the shading changes), but
two under *neighbouring* lights nearly can: their shading and shadows are alike. So the fine
detail (high-passed) of each photograph is cross-correlated with that of the photographs of its
ten nearest lights, giving each pair's relative offset to a twentieth of a pixel (an FFT, then
the correlation's Fourier series evaluated finely around its peak); the offsets that best agree
with all the pairs are solved for on that graph, robustly (a pair misled by a moving highlight
is dropped). A capture whose photographs split in two groups (before and after a bump) is found
whole, as long as the groups' lights are neighbours somewhere. Of what remains, the part that the
light's elevation explains (grazing light lengthens shadows away from the lamp: the lowest ring
of a dome reads half a pixel away from its lamps on a steady capture) is taken away
(:func:`_shading_bias`). The frame kept is the one the capture started in
(:func:`_common_frame`), and a group of photographs that moved together is resampled by its
median move (:func:`_shared_moves`). An earlier design registered each photograph against the
capture's PTM relit for its light; the PTM has no cast shadows, and on a capture split along the
light layout's order it went wrong by several pixels (BENCHMARKS.md, "Camera drift").

The work is on a few tiles of the frame, copied from each photograph while it is decoded
(:class:`DriftProbe`), so a steady capture pays no second decoding (a 48-photograph capture's
measurement takes 0.15–0.3 s with one tile, about 0.7 s with five); five tiles, from frames of
768 px on their shorter side, give a small rotation as well as the translation. A capture
whose photographs' details agree with their neighbours' too little is not measured
(:data:`_MIN_CAPTURE_CONFIDENCE`), nor a photograph whose tiles disagree (:func:`_rigid`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .images import LUMA_WEIGHTS, srgb_to_linear
from .resources import thread_count

__all__ = ["ALIGN_THRESHOLD_PX", "FRAME_RADIUS_PX", "STILL_PX", "Drift", "DriftProbe", "measure_drift",
           "warp_photograph"]

#: A photograph displaced by more than this anywhere in the frame (pixels) makes a run resample
#: the capture. Steady captures read up to 0.13 px on the 640 × 480 synthetic tablet, 0.83 px on
#: a 800 × 768 one under 24 lights (smooth at the pixel's scale: only shading to register),
#: 0.32 px on the real RTI icon and 0.58 px on DiLiGenT's glossy cat, whose highlights move with
#: the light (benchmarks/drift.py): resampling by offsets that are the measurement's own noise
#: would move photographs by as much as it corrects. Drift below it is reported, not undone; it
#: costs: every other photograph of the tablet moved by 0.5 px, 0.73° mean normal error against
#: 0.28°; by 1 px, 1.27°.
ALIGN_THRESHOLD_PX = 1.0
#: A photograph whose tiles disagree by more than this (pixels) with one rigid motion is not
#: measured: its details moved with the shading, not with the camera.
RIGID_TOLERANCE_PX = 0.5
#: Photographs this close to one another (pixels) share a frame.
FRAME_RADIUS_PX = 0.5
#: A photograph of the common frame displaced by less than this (pixels) is left as it is when
#: the others are resampled: resampling blurs, a little.
STILL_PX = 0.1
#: The probe's memory at most (bytes): its tiles shrink for captures of many photographs.
PROBE_BYTES = 64 << 20
#: The largest tile side (pixels): enough texture for a sub-pixel offset, small enough that
#: a capture's measurement takes about a second.
TILE = 192
#: The smallest useful tile side.
MIN_TILE = 32
_SRGB8 = srgb_to_linear(np.arange(256, dtype=np.float32) / np.float32(255.0)).astype(np.float32)
#: Below this confidence (the median correlation of a photograph's details with its neighbours')
#: a tile's offset is not trusted: a featureless or dark tile.
_MIN_CONFIDENCE = 0.2
#: Below this median confidence (each photograph's best tile) the capture is not measured at
#: all: its photographs' details agree with their neighbours' too little for their offsets to
#: be the camera's. A smooth synthetic tablet in 48 JPEGs of 3000 × 2000 px reads 0.3, and
#: offsets of up to 4 px on a steady capture; the captures the measurement is right on read
#: 0.5 (a 24-light dome at 480 × 384, noisy) to 0.95 (the real icon and cat).
_MIN_CAPTURE_CONFIDENCE = 0.45


class DriftProbe:
    """Tiles of every photograph, copied while the capture is decoded.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` of the photographs.
    n : int
        The number of photographs.

    Attributes
    ----------
    origins : ndarray, shape (T, 2)
        Each tile's top-left ``(row, column)``.
    size : int
        The tiles' side.
    tiles : ndarray, shape (n, T, size, size), float32
        Linear luminance.
    """

    def __init__(self, shape: tuple[int, int], n: int) -> None:
        h, w = int(shape[0]), int(shape[1])
        size = min(TILE, int(min(h, w) / 2.5))
        spread = min(h, w) >= 4 * size
        count = 5 if spread else 1
        if not spread:  # one tile: as large as the frame allows, for as much detail as it holds
            size = min(TILE, int(0.8 * min(h, w)))
        size = min(size, int(np.sqrt(PROBE_BYTES / (4 * count * max(1, n)))))
        self.size = max(MIN_TILE, size - size % 2)
        s = self.size
        centres = [(h // 2, w // 2)]
        if spread:
            centres += [(h // 4, w // 4), (h // 4, 3 * w // 4), (3 * h // 4, w // 4), (3 * h // 4, 3 * w // 4)]
        self.origins = np.array([(min(max(0, r - s // 2), h - s), min(max(0, c - s // 2), w - s))
                                 for r, c in centres], np.int64)
        self.shape = (h, w)
        self.tiles = np.zeros((n, len(self.origins), s, s), np.float32)

    def take(self, k: int, img: np.ndarray, srgb8: bool) -> None:
        """Copy photograph ``k``'s tiles: ``img`` ``(H, W, 3)`` as the reduction reads it (uint8,
        sRGB when ``srgb8``; uint16 linear; float linear; a grey one may be a stride-0 view)."""
        s = self.size
        for t, (r, c) in enumerate(self.origins):
            part = img[r : r + s, c : c + s]
            if part.dtype == np.uint8:
                rgb = _SRGB8[part] if srgb8 else part.astype(np.float32) / np.float32(255)
            elif part.dtype == np.uint16:
                rgb = part.astype(np.float32) / np.float32(65535)
            else:
                rgb = part.astype(np.float32, copy=False)
            self.tiles[k, t] = rgb @ LUMA_WEIGHTS


@dataclass
class Drift:
    """Each photograph's displacement against the capture's common frame.

    Attributes
    ----------
    offsets : ndarray, shape (N, 2)
        ``(dx, dy)`` in pixels, x to the right and y up: where the common frame's content lies
        in the photograph, at the frame's centre.
    rotation_deg : ndarray, shape (N,)
        Counter-clockwise rotation of the photograph's content, degrees.
    transforms : ndarray, shape (N, 2, 3)
        For each photograph, the affine map from a pixel ``(column, row)`` of the common frame
        to where it lies in the photograph (OpenCV's ``WARP_INVERSE_MAP`` convention).
    confidence : ndarray, shape (N,)
        0 to 1: how well the photograph's details matched its prediction (0: not measured,
        offset taken as 0).
    shape : tuple of int
        ``(H, W)`` of the frame.
    """

    offsets: np.ndarray
    rotation_deg: np.ndarray
    transforms: np.ndarray
    confidence: np.ndarray
    shape: tuple[int, int]

    def displacement(self) -> np.ndarray:
        """``(N,)`` the largest distance, pixels, any corner of the frame moves in each photograph."""
        h, w = self.shape
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], np.float64)
        moved = np.einsum("nij,cj->nci", self.transforms, corners)
        return np.linalg.norm(moved - corners[None, :, :2], axis=2).max(axis=1)

    def largest(self) -> tuple[int, float]:
        """The photograph displaced most, and by how many pixels (rotation included)."""
        d = self.displacement()
        k = int(np.argmax(d))
        return k, float(d[k])

    def needs_alignment(self, threshold: float | None = None) -> bool:
        """Whether some photograph is displaced by more than ``threshold`` pixels
        (:data:`ALIGN_THRESHOLD_PX` when None)."""
        return self.largest()[1] > (ALIGN_THRESHOLD_PX if threshold is None else threshold)

    def resampling(self, still: float = STILL_PX) -> np.ndarray:
        """:attr:`transforms`, with the identity for photographs displaced by less than
        ``still`` pixels (left as they are)."""
        out = self.transforms.copy()
        out[self.displacement() < still] = np.array([[1.0, 0, 0], [0, 1.0, 0]])
        return out


#: Each photograph is compared with the photographs of its nearest lights: their shading and
#: shadows are most alike, so the light's change biases the comparison least.
_NEIGHBOURS = 10
#: Elevations this close (degrees, one standard deviation) share their shading's bias: a dome's
#: ring is within a few degrees; rings are 10–15° apart.
_BIAS_BANDWIDTH_DEG = 5.0
#: Pairs cross-correlated at a time (bounds the FFTs' memory: 64 × 192² complex, 38 MB).
_PAIR_CHUNK = 64
#: The correlation peak is refined on a grid of 1/_UPSAMPLE pixel.
_UPSAMPLE = 20


def _details(tiles: np.ndarray) -> np.ndarray:
    """Tiles' fine detail, windowed: minus their blur (the shading's slow part), times a Hann
    window (so that their edges do not correlate with themselves)."""
    from scipy.ndimage import gaussian_filter

    high = tiles - gaussian_filter(tiles, (0, 4.0, 4.0), mode="nearest")
    s = tiles.shape[-1]
    window = np.hanning(s).astype(np.float32)
    return high * window[:, None] * window[None, :]


def _neighbour_pairs(lights: np.ndarray, k: int = _NEIGHBOURS) -> np.ndarray:
    """``(E, 2)`` pairs ``(i, j)``, ``i < j``: each photograph with those of its ``k`` nearest
    lights that are within three times the layout's typical spacing (the median angle to a light's
    nearest neighbour), and always its two nearest: under lights farther apart the shading
    differs too much for the details to be compared (a sparse layout's top lamps against the
    lowest ring read offsets of 2–3 px on a steady capture)."""
    n = len(lights)
    k = min(k, n - 1)
    cos = np.clip(lights @ lights.T, -1.0, 1.0)
    np.fill_diagonal(cos, -np.inf)
    nearest = np.argsort(-cos, axis=1, kind="stable")[:, :k]
    angle = np.arccos(np.take_along_axis(cos, nearest, axis=1))
    near = angle <= 3 * np.median(angle[:, 0])
    near[:, :2] = True
    i = np.repeat(np.arange(n), k)[near.ravel()]
    j = nearest.ravel()[near.ravel()]
    return np.unique(np.stack([np.minimum(i, j), np.maximum(i, j)], 1), axis=0)


def _pair_offsets(details: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each pair ``(i, j)``: where tile ``i``'s content lies in tile ``j`` (rows, columns,
    sub-pixel), and the normalised correlation at that offset.

    Cross-correlation by FFT, :data:`_PAIR_CHUNK` pairs at a time (a 48-photograph capture has
    about 300 pairs), its peak refined to 1/:data:`_UPSAMPLE` px by evaluating the
    correlation's Fourier series along the row through the peak, then along the column through
    the refined position, then the row again (Guizar-Sicairos et al. 2008 evaluate a whole
    square around the peak, as scikit-image's ``phase_cross_correlation`` does: as accurate
    here, at 13 times the cost). A parabola through the peak instead locks offsets towards
    whole pixels: steady captures then read up to 1.2 px.
    """
    from scipy import fft

    e = len(pairs)
    s = details.shape[-1]
    spectra = fft.fft2(details.astype(np.float32, copy=False), workers=-1)  # complex64: half the traffic
    norms = np.linalg.norm(details.reshape(len(details), -1), axis=1)
    freq = np.fft.fftfreq(s)
    m = int(np.ceil(1.5 * _UPSAMPLE)) | 1
    steps = (np.arange(m) - m // 2) / _UPSAMPLE
    fine = np.exp(2j * np.pi * steps[:, None] * freq).astype(np.complex64)  # (m, s): the steps' phase ramps
    offsets = np.zeros((e, 2))
    conf = np.zeros(e)
    for c0 in range(0, e, _PAIR_CHUNK):
        chunk = pairs[c0:c0 + _PAIR_CHUNK]
        k = len(chunk)
        cross = spectra[chunk[:, 1]] * np.conj(spectra[chunk[:, 0]])
        corr = fft.ifft2(cross, workers=-1).real
        r, c = np.unravel_index(corr.reshape(k, -1).argmax(axis=1), (s, s))
        row = np.where(r > s // 2, r - s, r).astype(np.float64)
        col = np.where(c > s // 2, c - s, c).astype(np.float64)

        def profile(at: np.ndarray, around: np.ndarray, rows: bool) -> tuple[np.ndarray, np.ndarray]:
            # The correlation at ``around + steps`` along the rows (at column ``at``) or the
            # columns (at row ``at``): the other axis's sum first, once, then a small product.
            ramp = np.exp(2j * np.pi * at[:, None] * freq).astype(np.complex64)
            w = np.einsum("euv,ev->eu", cross, ramp) if rows else np.einsum("euv,eu->ev", cross, ramp)
            value = np.matmul(w * np.exp(2j * np.pi * around[:, None] * freq).astype(np.complex64), fine.T).real
            best = value.argmax(axis=1)
            return around + steps[best], value[np.arange(k), best]

        row, _ = profile(col, row, True)
        col, _ = profile(row, col, False)
        row, value = profile(col, row, True)
        offsets[c0:c0 + k] = np.stack([row, col], 1)
        denom = norms[chunk[:, 0]] * norms[chunk[:, 1]] * s * s
        conf[c0:c0 + k] = np.divide(value, denom, out=np.zeros(k), where=denom > 0)
    return offsets, np.clip(conf, 0, 1)


def _solve_graph(n: int, pairs: np.ndarray, relative: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Offsets ``(n, 2)`` whose differences ``d[j] - d[i]`` best match ``relative`` (robustly:
    Tukey's biweight drops pairs a repeated texture or a moving shadow misled), mean zero."""
    e = len(pairs)
    a = np.zeros((e + 1, n))
    a[np.arange(e), pairs[:, 1]] = 1.0
    a[np.arange(e), pairs[:, 0]] = -1.0
    a[e] = 1.0
    rhs = np.vstack([relative, np.zeros((1, 2))])
    w = weight.copy()
    d = np.zeros((n, 2))
    for _ in range(6):
        sw = np.sqrt(np.append(w, 1.0))[:, None]
        d = np.linalg.lstsq(a * sw, rhs * sw, rcond=None)[0]
        residual = np.linalg.norm(a[:e] @ d - relative, axis=1)
        scale = 4.685 * max(1.4826 * float(np.median(residual)), 0.1)
        w = weight * np.where(residual < scale, (1 - (residual / scale) ** 2) ** 2, 0.0)
    return d


def _measure_tiles(tiles: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offsets ``(N, 2)`` (rows, columns) of each photograph's tile against their mean, and
    their confidence: the median correlation of the photograph's details with its neighbours'
    (``pairs``, :func:`_neighbour_pairs`)."""
    n = len(tiles)
    details = _details(tiles)
    relative, conf = _pair_offsets(details, pairs)
    d = _solve_graph(n, pairs, relative, conf ** 2)
    per = np.zeros(n)
    for k in range(n):
        per[k] = np.median(conf[(pairs[:, 0] == k) | (pairs[:, 1] == k)])
    return d, per


def _rigid(offsets: np.ndarray, pos: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, float] | None:
    """A photograph's translation (rows, columns) and small rotation θ (radians, about the frame's
    centre) from its tiles' offsets ``(T, 2)`` at ``pos`` (rows, columns from the centre), or
    None when the tiles do not agree on one rigid motion.

    A camera's move displaces every tile alike (but for the rotation); a grazing light's
    shadows move each tile's details their own way (a steady 1600 × 1200 synthetic tablet, smooth
    at the pixel's scale, read up to 10 px in one tile and 0.5 px in another). So a translation
    may leave out the tile that disagrees most when five are trusted; a rotation is fitted to
    all of them; and the photograph is not measured when the tiles are still more than
    :data:`RIGID_TOLERANCE_PX` from the fit.
    """
    def fit(keep: np.ndarray, rotate: bool) -> tuple[np.ndarray, float, float]:
        # A tile at (r, c) moves by (θ·c, −θ·r) beside the translation.
        rows = np.zeros((2 * keep.sum(), 3))
        rows[0::2, 0], rows[0::2, 2] = 1, pos[keep, 1]
        rows[1::2, 1], rows[1::2, 2] = 1, -pos[keep, 0]
        rows = rows if rotate else rows[:, :2]
        target = offsets[keep].reshape(-1)
        sol = np.linalg.lstsq(rows, target, rcond=None)[0]
        worst = float(np.abs(rows @ sol - target).max())
        return sol[:2], float(sol[2]) if rotate else 0.0, worst

    candidates = [use]
    if use.sum() >= 5:
        for t in np.flatnonzero(use):
            keep = use.copy()
            keep[t] = False
            candidates.append(keep)
    # A rotation only where a translation does not explain the tiles: the tiles' own scatter
    # (a few tenths of a pixel, 200 px apart) would otherwise read as a rotation that moves
    # the frame's corners by more than the threshold. And only from every trusted tile: with
    # one left out, three corners and a rotation explain a glossy object's moving highlights
    # as well as a camera's turn (a steady 1024 × 768 glossy tablet read ±0.1°, 1.6 px at its
    # corners, and was resampled: 0.37° → 0.64° mean normal error).
    translation, _, worst = min((fit(keep, False) for keep in candidates), key=lambda f: f[2])
    if worst <= RIGID_TOLERANCE_PX:
        return translation, 0.0
    translation, angle, worst = fit(use, True)
    if worst <= RIGID_TOLERANCE_PX:
        return translation, angle
    return None


def _shading_bias(shift: np.ndarray, lights: np.ndarray, measured: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``(N, 2)`` the part of the offsets (rows, columns) that the light's elevation explains.

    Under a grazing light, shadows lengthen away from the lamp and the details move with them:
    on a steady capture the lowest ring of a dome reads half a pixel to a pixel away from its
    lamps (synthetic tablets: 0.58 px at 15° under 48 lights, 1.3 px under 24; DiLiGenT's cat
    0.27 px at 40–55°), and a sparse dome's top ring as much. The camera's drift does not
    depend on where the lamp is: at each elevation the offsets are modelled as ``β·u + γ·u⊥``
    (``u`` the direction towards the lamp in the image) plus the camera's move. Each estimate
    of β and γ is blind to some moves: the ring's mean (:func:`_bias_from_means`) over the
    largest group of photographs that stayed together, to every move of the others; over all
    the photographs, to a move of a whole ring or of every other photograph of it; the
    differences of neighbouring photographs (:func:`_bias_from_differences`), to a move of a
    contiguous part of a ring (a bump half-way through it). Of these, and of no correction,
    the one kept leaves the photographs in the tightest groups: a drift is a few groups, a
    shading bias a spread.
    """
    k = np.flatnonzero(measured)
    if len(k) < 3:
        return np.zeros_like(shift)
    # The means over the largest group of photographs that moved together (found again once
    # the bias is out: it spreads them by about a pixel), over all of them, and the differences.
    group = np.zeros_like(shift)
    for _ in range(2):
        ref = _common_frame(shift - group, measured, 2 * FRAME_RADIUS_PX)
        group = _bias_from_means(shift - np.median(shift[ref] - group[ref], axis=0), lights, ref)
    candidates = [group, _bias_from_means(shift - np.median(shift[k], axis=0), lights, measured),
                  _bias_from_differences(shift, lights, measured, pairs), np.zeros_like(shift)]

    def tightness(bias: np.ndarray) -> float:
        # The sum of the groups' squared shares: 1 for one group, ½ for two equal ones, small
        # for a spread.
        return sum((len(g) / len(k)) ** 2 for g in _groups((shift - bias)[k], FRAME_RADIUS_PX))

    scores = [tightness(b) for b in candidates]
    return candidates[int(np.argmax(scores))]  # of equals, the first


def _lamp_axes(lights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each lamp's direction in the image ``u`` and its perpendicular ``u⊥`` (``(N, 2)``, rows
    and columns; zero for an overhead lamp, which has no azimuth), whether it has one, and its
    elevation in degrees."""
    lxy = np.stack([-lights[:, 1], lights[:, 0]], 1)  # towards the lamp, (rows, columns)
    norm = np.linalg.norm(lxy, axis=1)
    oblique = norm > 0.05
    along = np.zeros((len(lights), 2))
    along[oblique] = lxy[oblique] / norm[oblique, None]
    across = np.stack([-along[:, 1], along[:, 0]], 1)
    return along, across, oblique, np.degrees(np.arcsin(np.clip(lights[:, 2], -1.0, 1.0)))


def _bias_from_means(shift: np.ndarray, lights: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``(N, 2)`` each elevation's mean offset along and across its lamps' azimuths, over the
    photographs ``ref`` (a Gaussian kernel of :data:`_BIAS_BANDWIDTH_DEG` in elevation), shrunk by
    its own uncertainty. A move shared by a whole ring, or by every other photograph of it,
    leaves the mean alone (the azimuths' directions add up to nothing); a move of one
    contiguous part of a ring does not."""
    n = len(shift)
    along_dir, across_dir, oblique, elevation = _lamp_axes(lights)
    along = (shift * along_dir).sum(axis=1)
    across = (shift * across_dir).sum(axis=1)
    use = ref & oblique
    if not use.any():
        return np.zeros((n, 2))
    kernel = np.exp(-0.5 * ((elevation[:, None] - elevation[None, use]) / _BIAS_BANDWIDTH_DEG) ** 2)
    total = kernel.sum(axis=1)
    # Enough of the common frame near an elevation to say what its shading does there.
    known = total > 2.0
    safe = np.where(known, total, 1.0)
    count = total ** 2 / np.maximum((kernel ** 2).sum(axis=1), 1e-300)  # the kernel's effective count

    def shared(values: np.ndarray) -> np.ndarray:
        # The mean, shrunk by its own uncertainty: where the photographs scatter (a camera that
        # shook) a mean of their scatter is not a bias to take away. Only a mean of two
        # standard errors or more is kept whole (four times the squared error below).
        mean = kernel @ values / safe
        spread = kernel @ values ** 2 / safe - mean ** 2
        noise = np.maximum(spread, 0.0) / np.maximum(count - 1.0, 1.0)
        keep = np.clip(1.0 - np.divide(4.0 * noise, mean ** 2, out=np.ones(n), where=mean != 0), 0.0, 1.0)
        return np.where(known, mean * keep, 0.0)

    return shared(along[use])[:, None] * along_dir + shared(across[use])[:, None] * across_dir


def _bias_from_differences(shift: np.ndarray, lights: np.ndarray, measured: np.ndarray,
                           pairs: np.ndarray) -> np.ndarray:
    """``(N, 2)`` the shading's bias (:func:`_shading_bias`), β and γ fitted at each elevation to
    the *differences* of neighbouring photographs there (pairs of the graph within
    :data:`_BIAS_BANDWIDTH_DEG`): a move the two share (a ring, or part of one, moved by a bump)
    cancels in their difference, and the few pairs across a bump are dropped as outliers. Each
    coefficient is shrunk by its own uncertainty (James–Stein), so that a shaking camera's
    scatter is not taken for a bias."""
    n = len(shift)
    along, across, oblique, elevation = _lamp_axes(lights)
    oblique &= measured
    a, b = pairs[:, 0], pairs[:, 1]
    usable = oblique[a] & oblique[b] & (np.abs(elevation[a] - elevation[b]) <= _BIAS_BANDWIDTH_DEG)
    a, b = a[usable], b[usable]
    bias = np.zeros((n, 2))
    fitted: dict[tuple[int, ...], np.ndarray] = {}
    for k in np.flatnonzero(oblique):
        near = (np.abs(elevation[a] - elevation[k]) <= _BIAS_BANDWIDTH_DEG) & (
            np.abs(elevation[b] - elevation[k]) <= _BIAS_BANDWIDTH_DEG)
        key = tuple(np.flatnonzero(near))
        if key not in fitted:
            fitted[key] = _bias_coefficients(shift[b[near]] - shift[a[near]], along[b[near]] - along[a[near]],
                                             across[b[near]] - across[a[near]])
        beta, gamma = fitted[key]
        bias[k] = beta * along[k] + gamma * across[k]
    return bias


def _bias_coefficients(difference: np.ndarray, d_along: np.ndarray, d_across: np.ndarray) -> np.ndarray:
    """β, γ with ``difference ≈ β·d_along + γ·d_across`` (each ``(m, 2)``), robustly (Tukey's
    biweight), each shrunk by its standard error; zeros with fewer than three pairs (a dome's
    top ring may hold three lamps)."""
    m = len(difference)
    if m < 3:
        return np.zeros(2)
    x = np.zeros((2 * m, 2))
    x[:, 0] = d_along.reshape(-1)
    x[:, 1] = d_across.reshape(-1)
    y = difference.reshape(-1)
    w = np.ones(2 * m)
    coef = np.zeros(2)
    for _ in range(5):
        sw = np.sqrt(w)
        coef = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)[0]
        residual = (y - x @ coef).reshape(m, 2)
        size = np.linalg.norm(residual, axis=1)
        scale = 4.685 * max(1.4826 * float(np.median(size)), 0.05)
        w = np.repeat(np.where(size < scale, (1 - (size / scale) ** 2) ** 2, 0.0), 2)
    kept = w > 0
    if kept.sum() < 4:
        return np.zeros(2)
    r = y[kept] - x[kept] @ coef
    sigma2 = float(r @ r) / max(int(kept.sum()) - 2, 1)
    try:
        cov = sigma2 * np.linalg.inv((x[kept] * w[kept, None]).T @ x[kept])
    except np.linalg.LinAlgError:
        return np.zeros(2)
    noise = np.maximum(np.diag(cov), 0.0)
    keep = np.clip(1.0 - np.divide(noise, coef ** 2, out=np.ones(2), where=coef != 0), 0.0, 1.0)
    return coef * keep


def _shared_moves(shift: np.ndarray, theta: np.ndarray, measured: np.ndarray,
                  reach: float) -> tuple[np.ndarray, np.ndarray]:
    """The translations and rotations the photographs are resampled by: each group of at least
    three photographs within :data:`FRAME_RADIUS_PX` of one another (tiles' moves) takes its
    median, as a bumped camera moved them all alike; this divides the measurement's own noise
    (±0.03° of rotation, 0.3 px at a frame's corner) by the root of the group's size. Others
    (a shaking camera's photographs) keep their own."""
    move, turn = shift.copy(), theta.copy()
    k = np.flatnonzero(measured)
    for group in _groups(np.column_stack([shift, theta * reach])[k], FRAME_RADIUS_PX, smallest=3):
        members = k[group]
        move[members] = np.median(shift[members], axis=0)
        turn[members] = np.median(theta[members])
    return move, turn


def _groups(points: np.ndarray, radius: float, smallest: int = 1) -> list[np.ndarray]:
    """Greedy groups of ``points`` ``(M, D)``: the most points within ``radius`` of one of them,
    then the most of those left, and so on while a group holds ``smallest`` or more; each as
    indices into ``points``."""
    close = np.linalg.norm(points[:, None] - points[None], axis=2) <= radius
    left = np.ones(len(points), bool)
    found = []
    while left.any():
        count = (close & left[None, :]).sum(axis=1) * left
        best = int(np.argmax(count))
        if count[best] < smallest:
            break
        found.append(np.flatnonzero(close[best] & left))
        left &= ~close[best]
    return found


def _common_frame(pose: np.ndarray, measured: np.ndarray, radius: float = FRAME_RADIUS_PX) -> np.ndarray:
    """The photographs of the frame the capture is brought to: those within ``radius`` of the
    first photograph measured when they are a third of the photographs or more (the frame the
    capture started in, before a bump); else the largest such group when it holds at least half
    of them; else (a camera that shook) all of them, whose median is then the frame that moves
    the photographs least."""
    k = np.flatnonzero(measured)
    close = np.linalg.norm(pose[k, None] - pose[None, k], axis=2) <= radius
    count = close.sum(axis=1)
    best = 0 if 3 * count[0] >= len(k) else int(np.argmax(count))
    ref = np.zeros(len(pose), bool)
    ref[k[close[best]] if 2 * count[best] >= len(k) or best == 0 else k] = True
    return ref


def measure_drift(probe: DriftProbe, lights: np.ndarray, *, threads: int | None = None) -> Drift:
    """Each photograph's offset (and small rotation) against the capture's common frame.

    Parameters
    ----------
    probe : DriftProbe
        Filled by the decoding pass.
    lights : ndarray, shape (N, 3)
        Unit directions towards the lights, one per photograph.
    threads : int, optional
        Tiles measured at once (:func:`ptmcore.resources.thread_count`).

    Returns
    -------
    Drift
    """
    lights = np.asarray(lights, np.float64)
    n, count = probe.tiles.shape[:2]
    per_tile = np.zeros((n, count, 2))
    conf = np.zeros((n, count))
    # The centre tile first: where it holds too little detail (a smooth object seen at many
    # megapixels: its details are the JPEG's noise, confidence 0.04), the capture is not
    # measured and the others are not worth their time (about 0.6 s for 48 photographs).
    pairs = _neighbour_pairs(lights)
    per_tile[:, 0], conf[:, 0] = _measure_tiles(probe.tiles[:, 0], pairs)
    if count > 1 and np.median(conf[:, 0]) >= _MIN_CAPTURE_CONFIDENCE / 2:
        # The others at once, in threads (the FFTs and products release the GIL).
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(max(1, min(count - 1, thread_count(threads)))) as pool:
            found = pool.map(lambda t: _measure_tiles(probe.tiles[:, t], pairs), range(1, count))
            for t, (d, c) in enumerate(found, 1):
                per_tile[:, t], conf[:, t] = d, c
    trusted = conf >= _MIN_CONFIDENCE
    if np.median(conf.max(axis=1)) < _MIN_CAPTURE_CONFIDENCE:
        trusted[:] = False  # the shading, not the object's details, is what the tiles hold
    h, w = probe.shape
    centre = np.array([(h - 1) / 2, (w - 1) / 2])
    pos = probe.origins + probe.size / 2 - 0.5 - centre  # tile centres (rows, columns) from the frame's centre
    shift = np.zeros((n, 2))
    theta = np.zeros(n)
    for k in range(n):
        use = trusted[k]
        if not use.any():
            continue
        if use.sum() >= 3:
            fit = _rigid(per_tile[k], pos, use)
            if fit is None:  # the tiles disagree: shading, not the camera, moved the details
                trusted[k] = False
                continue
            shift[k], theta[k] = fit
        else:
            shift[k] = np.median(per_tile[k, use], axis=0)
    measured = trusted.any(axis=1)
    # Rotations in pixels of a tile's move, where they are measured (at a corner their noise
    # would be twice as large): two photographs share a frame when they agree on both.
    reach = float(np.hypot(pos[:, 0], pos[:, 1]).mean())
    if measured.any():
        shift = shift - _shading_bias(shift, lights, measured, pairs)
        ref = _common_frame(np.column_stack([shift, theta * reach]), measured)
        shift[measured] -= np.median(shift[ref], axis=0)
        shift[~measured] = 0.0
        theta[measured] -= np.median(theta[ref])
    move, turn = _shared_moves(shift, theta, measured, reach)
    cos, sin = np.cos(turn), np.sin(turn)
    transforms = np.zeros((n, 2, 3))
    # (column, row) of the common frame → the photograph: rotate about the centre, then shift.
    transforms[:, 0, 0], transforms[:, 0, 1] = cos, -sin
    transforms[:, 1, 0], transforms[:, 1, 1] = sin, cos
    cxy = centre[::-1]
    transforms[:, :, 2] = cxy + move[:, ::-1] - np.einsum("nij,j->ni", transforms[:, :, :2], cxy)
    offsets = np.stack([shift[:, 1], -shift[:, 0]], axis=1)
    confidence = np.where(trusted, conf, 0).sum(axis=1) / np.maximum(1, trusted.sum(axis=1))
    return Drift(offsets, -np.degrees(theta), transforms, confidence, (h, w))


def warp_photograph(img: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """A photograph resampled onto the common frame (Lanczos, 8 × 8 samples: on the drift
    benchmark's tablet its normals were 0.335° where bicubic's were 0.348°, clean 0.284°; the
    border repeated).

    Parameters
    ----------
    img : ndarray, shape (H, W) or (H, W, 3), float32
    transform : ndarray, shape (2, 3)
        :attr:`Drift.transforms` of the photograph.

    Returns
    -------
    ndarray, float32, the shape of ``img``
    """
    import cv2

    h, w = img.shape[:2]
    return cv2.warpAffine(np.ascontiguousarray(img, np.float32), np.asarray(transform, np.float64), (w, h),
                          flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
