"""Mirror reflection on a glossy sphere: the light direction from a highlight's position.

With an orthographic camera (view v = (0, 0, 1)) the sphere normal at the highlight is
s = ((hx − cx)/r, (cy − hy)/r, √(1 − …)) and the light l = 2(s·v)s − v. With a pinhole camera
(:class:`reconstruct.calibration.camera.Intrinsics`) the view is the highlight's own ray and the
sphere's 3D position comes from its outline (:func:`sphere_centre_3d`).

Coordinates: image positions are (x_img, y_img) = (column, row) with pixel centres at integers;
spheres are (cx, cy, r) in those units. Directions use the project frame: x right, y up,
z towards the camera.
"""

from __future__ import annotations

import numpy as np

from reconstruct.calibration.camera import Intrinsics

Sphere = tuple[float, float, float]


def _pixel_to_ray_matrix(intrinsics: Intrinsics) -> np.ndarray:
    """3×3 M with M·(col, row, 1) = ((col − cx)/fx, −(row − cy)/fy, −1), a ray (not unit)."""
    k = intrinsics
    return np.array([[1.0 / k.fx, 0.0, -k.cx / k.fx],
                     [0.0, -1.0 / k.fy, k.cy / k.fy],
                     [0.0, 0.0, -1.0]])


def sphere_outline(centre: np.ndarray, intrinsics: Intrinsics) -> tuple[float, float, float, float, float]:
    """The ellipse that a pinhole camera sees of a unit sphere centred at ``centre``.

    The rays tangent to the sphere form a cone of axis â = C/|C| and half-angle α with
    sin α = 1/|C|; a ray d is on it when (d·â)² = cos²α |d|². With d = M·p for the pixel
    p = (col, row, 1) this is the conic pᵀ Mᵀ(â âᵀ − cos²α I) M p = 0.

    Parameters
    ----------
    centre : np.ndarray
        (3,) sphere centre in the camera frame, in units of the radius (|centre| > 1,
        in front of the camera).
    intrinsics : Intrinsics
        The camera.

    Returns
    -------
    (x0, y0, a, b, phi)
        Ellipse centre (column, row), semi-major and semi-minor axes in pixels, and the
        major axis's angle in radians from the +column axis towards +row.
    """
    centre = np.asarray(centre, dtype=np.float64)
    dist = float(np.linalg.norm(centre))
    axis = centre / dist
    cos2 = 1.0 - 1.0 / dist**2
    M = _pixel_to_ray_matrix(intrinsics)
    A = M.T @ (np.outer(axis, axis) - cos2 * np.eye(3)) @ M
    c = np.linalg.solve(A[:2, :2], -A[:2, 2])
    k = float(np.append(c, 1.0) @ A @ np.append(c, 1.0))
    lam, vec = np.linalg.eigh(A[:2, :2])
    semi = np.sqrt(-k / lam)
    major = int(np.argmax(semi))
    phi = float(np.arctan2(vec[1, major], vec[0, major]))
    return float(c[0]), float(c[1]), float(semi.max()), float(semi.min()), phi


def ellipse_mean_radius(a: float, b: float, n: int = 360) -> float:
    """Mean distance from an ellipse's centre to its outline over equally spaced angles.

    This is the radius a geometric circle fit gives for outline points sampled on rays at
    equal angles from the centre, as :func:`reconstruct.calibration.spheres.refine_circle` samples
    them.
    """
    phi = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return float(np.mean(a * b / np.hypot(b * np.cos(phi), a * np.sin(phi))))


def sphere_centre_3d(sphere: Sphere, intrinsics: Intrinsics) -> np.ndarray:
    """Centre of a unit-radius sphere whose fitted outline circle is ``sphere``, pinhole camera.

    The outline of a sphere is the image of the cone of rays tangent to it. In the plane
    that holds the optical axis and the sphere's centre, the cone's two extreme rays pass
    through the outline points on the image line from the principal point through the
    outline's centre; the cone's axis (the direction of the sphere's centre) bisects them
    and their half-angle α gives the distance D = 1/sin α for a radius of 1 (everything is
    scale-free).

    Approximation and its correction: the outline is detected as a circle, but in
    perspective it is an ellipse elongated away from the principal point (by about
    1/cos θ for a sphere θ off the optical axis: 6 % at 20°). The circle fit returns the
    ellipse's centre and, between the two semi-axes, its mean radius, so the two points
    above sit inside the true extremes: D comes out a few percent too large, which tilts
    the normals of highlights away from the disc's centre, by a degree or more for spheres
    off-axis under a normal or wide lens. The rays through those points therefore only give
    the starting point; the centre is then adjusted (a 3-unknown least-squares solve) until
    the exact projected ellipse (:func:`sphere_outline`) has the measured circle's centre
    and mean radius. What remains is the difference between a circle fit of a sampled,
    anti-aliased ellipse and that ideal, a small fraction of a pixel.

    Parameters
    ----------
    sphere : (cx, cy, r)
        The fitted outline circle in pixels (cx = column, cy = row).
    intrinsics : Intrinsics
        The camera.

    Returns
    -------
    np.ndarray
        (3,) float64 centre in the camera frame (x right, y up, z towards the camera; the
        camera looks along −z), in units of the sphere's radius.
    """
    from scipy.optimize import least_squares

    cx, cy, r = (float(v) for v in sphere)
    d = np.array([cx - intrinsics.cx, cy - intrinsics.cy])
    norm = float(np.hypot(*d))
    # On the optical axis every diameter is such a line; any one will do.
    d = d / norm if norm > 1e-9 else np.array([1.0, 0.0])
    ends = np.array([cx, cy])[None, :] + np.array([[-r], [r]]) * d[None, :]
    r0, r1 = intrinsics.rays(ends[:, 0], ends[:, 1])
    axis = r0 + r1
    axis /= np.linalg.norm(axis)
    half = 0.5 * np.arccos(np.clip(r0 @ r1, -1.0, 1.0))
    start = axis / np.sin(half)

    def residual(c: np.ndarray) -> np.ndarray:
        x0, y0, a, b, _ = sphere_outline(c, intrinsics)
        return np.array([x0 - cx, y0 - cy, ellipse_mean_radius(a, b) - r])

    # Unknowns scaled by the starting distance so that each is of order 1.
    scale = float(np.linalg.norm(start))
    fit = least_squares(lambda p: residual(p * scale), start / scale, x_scale="jac",
                        xtol=1e-12, ftol=1e-12, gtol=1e-12)
    centre = fit.x * scale
    return centre if np.linalg.norm(centre) > 1.0 and centre[2] < 0 else start


def sphere_normal_at(hx, hy, sphere) -> np.ndarray:
    """Sphere normals seen at image points by an orthographic camera (view v = (0, 0, 1)).

    s = ((hx − cx)/r, (cy − hy)/r, √(1 − …)): rows go down, y goes up. A point just outside
    the outline (a highlight measured on the anti-aliased limb) is taken onto the limb.

    Parameters
    ----------
    hx, hy : float or ndarray
        Image positions (column, row) in pixels; NaN gives NaN normals.
    sphere : (cx, cy, r)
        The outline in pixels; its values may be arrays broadcasting with ``hx``.

    Returns
    -------
    ndarray, shape (..., 3), float64
        Unit normals in the project frame.
    """
    cx, cy, r = (np.asarray(v, dtype=np.float64) for v in sphere)
    sx = (np.asarray(hx, dtype=np.float64) - cx) / r
    sy = (cy - np.asarray(hy, dtype=np.float64)) / r
    rho2 = sx * sx + sy * sy
    outside = rho2 > 1.0
    scale = np.where(outside, 1.0 / np.sqrt(np.where(outside, rho2, 1.0)), 1.0)
    rho2 = np.where(outside, 1.0, rho2)
    return np.stack(np.broadcast_arrays(sx * scale, sy * scale, np.sqrt(1.0 - rho2)), axis=-1)


def ray_sphere_distance(rays: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays t·d from the camera centre first meet the sphere |p − C| = 1.

    t = d·C − √((d·C)² − |C|² + 1) for unit rays d. A ray that misses gets the distance of
    its point closest to the centre, on the limb as seen along that ray.

    Parameters
    ----------
    rays : ndarray, shape (..., 3)
        Unit rays (:meth:`reconstruct.calibration.camera.Intrinsics.rays`).
    centre : ndarray, shape (3,)
        Sphere centre in units of its radius.

    Returns
    -------
    t : ndarray, shape (...)
        Distance along each ray.
    hit : ndarray, shape (...), bool
        Whether the ray meets the sphere.
    """
    dc = rays @ centre
    disc = dc * dc - (centre @ centre - 1.0)
    return dc - np.sqrt(np.clip(disc, 0.0, None)), disc > 0


def sphere_normal_through(rays: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Unit normals (…, 3) where ``rays`` (…, 3), from the pinhole, meet the sphere of radius 1
    centred at ``centre`` (:func:`sphere_centre_3d`); rays that miss it take their closest
    point (:func:`ray_sphere_distance`)."""
    t, _ = ray_sphere_distance(rays, centre)
    normal = t[..., None] * rays - centre
    return normal / np.linalg.norm(normal, axis=-1, keepdims=True)


def mirror(normal: np.ndarray, view: np.ndarray | None = None) -> np.ndarray:
    """Unit direction l = 2(n·v)n − v that a mirror of normal n reflects the view v into.

    ``view`` (..., 3) points towards the camera; None is the orthographic v = (0, 0, 1).
    """
    if view is None:
        light = 2.0 * normal[..., 2:3] * normal - np.array([0.0, 0.0, 1.0])
    else:
        light = 2.0 * np.sum(normal * view, axis=-1, keepdims=True) * normal - view
    return light / np.linalg.norm(light, axis=-1, keepdims=True)


def light_from_highlight(hx, hy, sphere: Sphere,
                         intrinsics: Intrinsics | None = None) -> np.ndarray:
    """Light direction from highlights on a mirror sphere.

    Orthographic view (the default): the sphere normal at the highlight is
    s = ((hx − cx)/r, (cy − hy)/r, √(1 − …)) (:func:`sphere_normal_at`; rows go down, y goes
    up); the light is the mirror image of the view v = (0, 0, 1) about it: l = 2(s·v)s − v.

    Pinhole camera (``intrinsics`` given): the sphere's centre direction and distance come
    from its outline (:func:`sphere_centre_3d`, radius 1); the ray through the highlight
    pixel meets the sphere at a point with normal n; the view v is the reversed ray
    (towards the camera), and l = 2(n·v)n − v.

    Either way a highlight measured just outside the outline is taken on the limb.

    Parameters
    ----------
    hx, hy : float or ndarray
        Highlight positions (column, row) in pixels, all on the same sphere.
    sphere : (cx, cy, r)
        The sphere's outline in pixels.
    intrinsics : Intrinsics, optional
        Pinhole camera in pixels (:class:`reconstruct.calibration.camera.Intrinsics`); None for an
        orthographic view.

    Returns
    -------
    np.ndarray
        (..., 3) float64 unit vectors towards the light, in the project frame ((3,) for
        scalar positions).
    """
    if intrinsics is None:
        return mirror(sphere_normal_at(hx, hy, sphere))
    centre = sphere_centre_3d(sphere, intrinsics)
    rays = intrinsics.rays(hx, hy)
    return mirror(sphere_normal_through(rays, centre), -rays)


__all__ = [
    "ellipse_mean_radius",
    "light_from_highlight",
    "mirror",
    "ray_sphere_distance",
    "sphere_centre_3d",
    "sphere_normal_at",
    "sphere_normal_through",
    "sphere_outline",
]
