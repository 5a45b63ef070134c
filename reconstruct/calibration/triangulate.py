"""Near-light positions by triangulating the mirror rays of two or more glossy spheres.

A flash close to the object is seen in a different direction from each sphere. The highlight
on sphere i (centre C_i, radius r_i) lies at the sphere point X_i = C_i + r_i s_i whose normal
s_i bisects the view v = (0, 0, 1) (orthographic camera) and the direction to the light, so
the light lies on the reflected ray X_i + t l_i, t > 0, with l_i = 2 (s_i·v) s_i − v. The
light's position is the point closest to all rays in the least-squares sense:

    Σ_i w_i (I − l_i l_iᵀ)(P − X_i) = 0,

weighted by the highlights' confidences. When the rays are nearly parallel the light is
effectively distant: its position is not determined and is reported as such (NaN) rather than
invented.

Frame and units: pixels, x = column, y = −row (up), z above the base plane on which the
object lies; a sphere resting on that plane has its centre at height r. Image coordinates of
the calibration are (x_img, y_img) = (column, row), so C_i = (cx, −cy, h_i).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from ptmcore.errors import InputError
from ptmcore.images import ImageStack
from ptmcore.lp import write_lp
from ptmcore.nearlight import centre_directions, typical_distance, write_light_positions

from reconstruct.calibration.calibrate import Calibration, calibrate_stack
from reconstruct.calibration.camera import Intrinsics
from reconstruct.calibration.reflection import Sphere, mirror, sphere_normal_at

#: Status of a photograph whose light was triangulated.
OK = "ok"
#: Fewer than two spheres showed a usable highlight.
TOO_FEW = "too few spheres"
#: The rays are (nearly) parallel: the light is effectively distant.
PARALLEL = "parallel rays"
#: The closest point lies behind a sphere's reflecting surface: inconsistent highlights.
BEHIND = "behind a sphere"


@dataclass
class Triangulation:
    """Light positions triangulated from sphere highlights.

    Attributes
    ----------
    positions : ndarray, shape (N, 3), float64
        Light positions in pixels (x = column, y = −row, z above the base plane); NaN rows
        where the status is not :data:`OK`.
    residual : ndarray, shape (N,), float64
        RMS distance (pixels) from the position to the rays used; NaN where not triangulated.
    angle_deg : ndarray, shape (N,), float64
        Largest angle between two of the photograph's rays (NaN with fewer than two rays);
        small angles mean a distant light and an uncertain position.
    rays : ndarray, shape (N,), int
        Number of spheres whose highlight was used.
    status : list of str
        Per photograph: :data:`OK`, :data:`TOO_FEW`, :data:`PARALLEL` or :data:`BEHIND`.
    names : list of str
        Photograph names, as in the calibration.
    """

    positions: np.ndarray
    residual: np.ndarray
    angle_deg: np.ndarray
    rays: np.ndarray
    status: list[str]
    names: list[str] = field(default_factory=list)

    @property
    def usable(self) -> np.ndarray:
        """(N,) bool: photographs with a triangulated position."""
        return np.isfinite(self.positions).all(axis=1)


def sphere_rays(calibration: Calibration, heights: list[float] | np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Reflection points and mirror rays of every sphere's highlight.

    Parameters
    ----------
    calibration : Calibration
        Spheres and highlights (:func:`reconstruct.calibration.calibrate.calibrate_stack`).
    heights : sequence of float, optional
        Height of each sphere's centre above the base plane, in pixels; default its radius
        (the sphere rests on the plane).

    Returns
    -------
    points : ndarray, shape (S, N, 3)
        X_i, NaN where the sphere has no highlight.
    rays : ndarray, shape (S, N, 3)
        Unit l_i towards the light, NaN where the sphere has no highlight.
    """
    spheres = np.asarray(calibration.spheres, dtype=np.float64).reshape(-1, 3)
    cx, cy, r = spheres.T
    hc = r if heights is None else np.asarray(heights, dtype=np.float64)
    if hc.shape != r.shape or not np.isfinite(hc).all():
        raise InputError(f"need one finite centre height per sphere ({len(r)}), got {heights!r}")
    hl = np.asarray(calibration.highlights, dtype=np.float64)  # (S, N, 2)
    s = sphere_normal_at(hl[..., 0], hl[..., 1], (cx[:, None], cy[:, None], r[:, None]))
    centre = np.stack([cx, -cy, hc], axis=-1)[:, None, :]
    return centre + r[:, None, None] * s, mirror(s)


def triangulate(
    calibration: Calibration,
    *,
    heights: list[float] | np.ndarray | None = None,
    min_angle_deg: float = 1.0,
) -> Triangulation:
    """Each photograph's light position from the highlights on two or more spheres.

    Parameters
    ----------
    calibration : Calibration
        Spheres and highlights; every sphere with a highlight (confidence > 0) contributes
        one ray, weighted by its confidence.
    heights : sequence of float, optional
        Sphere centre heights above the base plane in pixels; default the radii.
    min_angle_deg : float
        Photographs whose rays are all closer than this to parallel are reported as
        :data:`PARALLEL` (distant light) with no position. At 1°, spheres 400 pixels apart
        triangulate lights up to about 23 000 pixels away.

    Returns
    -------
    Triangulation
    """
    if min_angle_deg <= 0:
        raise ValueError("min_angle_deg must be positive")
    points, rays = sphere_rays(calibration, heights)
    conf = np.asarray(calibration.sphere_confidence, dtype=np.float64)
    used = np.isfinite(points).all(-1) & np.isfinite(rays).all(-1) & (conf > 0)  # (S, N)
    wts = np.where(used, conf, 0.0)
    x = np.where(used[..., None], points, 0.0)
    l = np.where(used[..., None], rays, 0.0)
    n = points.shape[1]
    count = used.sum(axis=0)

    # Largest pairwise angle between the rays of each photograph.
    cos = np.einsum("inc,jnc->ijn", l, l)
    both = used[:, None, :] & used[None, :, :]
    min_cos = np.where(both, cos, 1.0).min(axis=(0, 1))
    angle = np.where(count >= 2, np.degrees(np.arccos(np.clip(min_cos, -1.0, 1.0))), np.nan)

    # Σ w (I − l lᵀ) P = Σ w (I − l lᵀ) X for every photograph at once.
    proj = np.eye(3) - l[..., :, None] * l[..., None, :]  # (S, N, 3, 3)
    a = np.einsum("sn,snij->nij", wts, proj)
    b = np.einsum("sn,snij,snj->ni", wts, proj, x)
    solvable = (count >= 2) & (angle >= min_angle_deg)
    a[~solvable] = np.eye(3)
    pos = np.linalg.solve(a, b[..., None])[..., 0]
    t = np.einsum("snc,snc->sn", l, pos[None] - x)
    behind = solvable & ((t <= 0) & used).any(axis=0)
    perp = (pos[None] - x) - t[..., None] * l
    residual = np.sqrt((np.einsum("snc,snc->sn", perp, perp) * used).sum(0) / np.maximum(count, 1))

    ok = solvable & ~behind
    status = [OK if ok[k] else TOO_FEW if count[k] < 2 else PARALLEL if not solvable[k] else BEHIND
              for k in range(n)]
    pos[~ok] = np.nan
    residual = np.where(ok, residual, np.nan)
    return Triangulation(positions=pos, residual=residual, angle_deg=angle, rays=count,
                         status=status, names=list(calibration.names))


def lights_are_near(
    triangulation: Triangulation,
    shape: tuple[int, int],
    *,
    max_diagonals: float = 10.0,
    min_fraction: float = 0.5,
    max_relative_residual: float = 0.02,
) -> bool:
    """Whether a capture's lights are near enough for per-pixel light directions to matter.

    Near means: at least ``min_fraction`` of the photographs were triangulated, with a
    median ray miss distance below ``max_relative_residual`` × the median light distance,
    and the lights' median distance from the image centre is below ``max_diagonals`` image
    diagonals. At 10 diagonals the light's direction still turns by about 6° across the
    image (3° from the centre to a corner), several times the error of sphere calibration.

    Parameters
    ----------
    triangulation : Triangulation
    shape : (H, W)
        Image size in pixels.

    Returns
    -------
    bool
    """
    ok = triangulation.usable
    if ok.sum() < max(2, min_fraction * len(ok)):
        return False
    h, w = shape
    dist = typical_distance(triangulation.positions[ok], shape)
    residual = float(np.median(triangulation.residual[ok]))
    return dist < max_diagonals * float(np.hypot(h, w)) and residual < max_relative_residual * dist


def near_lights(calibration: Calibration, shape: tuple[int, int] | None = None
                ) -> Triangulation | None:
    """The triangulated lights of a calibration when they are near, else None.

    None also when fewer than two spheres were used, or when the calibration used a
    perspective camera (the rays here assume the orthographic view).

    Parameters
    ----------
    calibration : Calibration
    shape : (H, W), optional
        Image size in pixels; default the calibration's.
    """
    shape = calibration.shape if shape is None else shape
    if shape is None:
        raise ValueError("the image size is needed: the calibration does not hold it")
    if len(calibration.spheres) < 2 or calibration.intrinsics is not None:
        return None
    tri = triangulate(calibration)
    return tri if lights_are_near(tri, shape) else None


@dataclass
class SphereLights:
    """The lights of a capture read from its spheres, and which photographs have one.

    Attributes
    ----------
    calibration : Calibration
        The highlights and distant directions (:func:`reconstruct.calibration.calibrate.calibrate_stack`).
    triangulation : Triangulation or None
        The near lights' positions when two or more spheres show them near, else None.
    usable : ndarray, shape (N,), bool
        Photographs with a light: a triangulated position for near lights, else a direction.
    directions : ndarray, shape (M, 3)
        The usable photographs' directions: for near lights, from the image centre
        (:func:`ptmcore.nearlight.centre_directions`).
    positions : ndarray, shape (M, 3) or None
        The usable photographs' light positions (pixels), or None for distant lights.
    left_out : list of str
        One line per photograph without a light: ``"name: reason"``.
    """

    calibration: Calibration
    triangulation: Triangulation | None
    usable: np.ndarray
    directions: np.ndarray
    positions: np.ndarray | None
    left_out: list[str]

    @property
    def names(self) -> list[str]:
        """Names of the usable photographs."""
        return [n for n, u in zip(self.calibration.names, self.usable) if u]


def sphere_lights(
    stack: ImageStack,
    *,
    spheres: list[Sphere] | None = None,
    intrinsics: Intrinsics | None = None,
    near: bool = True,
) -> SphereLights:
    """Calibrate a capture from its spheres and, when they show near lights, triangulate.

    Parameters
    ----------
    stack : ImageStack
        The decoded capture (:func:`ptmcore.images.load_stack`).
    spheres : list of (cx, cy, r), optional
        Known spheres; detected when omitted.
    intrinsics : Intrinsics, optional
        Pinhole camera for the reflection (near lights are then not triangulated).
    near : bool
        Whether to look for near lights (:func:`near_lights`) at all.

    Returns
    -------
    SphereLights

    Raises
    ------
    InputError
        As :func:`reconstruct.calibration.calibrate.calibrate_stack`.
    """
    cal = calibrate_stack(stack, spheres=spheres, intrinsics=intrinsics)
    tri = near_lights(cal) if near else None
    if tri is None:
        usable = cal.usable
        return SphereLights(cal, None, usable, cal.directions[usable], None,
                            [f"{name}: no usable highlight" for name in cal.flagged])
    usable = tri.usable
    positions = tri.positions[usable]
    return SphereLights(cal, tri, usable, centre_directions(positions, stack.shape), positions,
                        [f"{name}: no light position ({status})"
                         for name, status in zip(tri.names, tri.status) if status != OK])


def write_near_light_files(lp_path: str | os.PathLike, positions_path: str | os.PathLike,
                           triangulation: Triangulation, shape: tuple[int, int]) -> np.ndarray:
    """Write the ``.lp`` and the light-position file of the triangulated photographs.

    The ``.lp`` holds, for tools that take one direction per photograph, the direction from
    the image centre; the positions give ``reconstruct run`` every pixel's own direction.
    Photographs without a position are left out of both.

    Returns
    -------
    ndarray, shape (M, 3)
        The directions written to the ``.lp``.
    """
    ok = triangulation.usable
    if not ok.any():
        raise InputError("no photograph has a triangulated light position", lp_path)
    names = [n for n, u in zip(triangulation.names, ok) if u]
    directions = centre_directions(triangulation.positions[ok], shape)
    write_lp(lp_path, names, directions)
    write_light_positions(positions_path, names, triangulation.positions[ok])
    return directions


__all__ = [
    "BEHIND",
    "OK",
    "PARALLEL",
    "TOO_FEW",
    "SphereLights",
    "Triangulation",
    "lights_are_near",
    "near_lights",
    "sphere_lights",
    "sphere_rays",
    "triangulate",
    "write_near_light_files",
]
