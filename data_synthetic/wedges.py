"""Cuneiform-like wedge impressions: small triangular-pyramid depressions with a thin tail."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from .surface import centred_grid

#: Steepest facet of a wedge before smoothing; keeps normals well defined.
MAX_FACET_SLOPE_DEG = 55.0


@dataclass(frozen=True)
class Wedge:
    """One stylus impression, in mm, in the centred frame (x right, y up).

    Attributes
    ----------
    x, y : float
        Centre of the head's back edge.
    angle : float
        Direction from the head towards the tail, radians counter-clockwise from +x.
    head_length, head_half_width : float
        The triangular head: back edge of width ``2*head_half_width``, tip ``head_length``
        ahead of it.
    tail_length, tail_half_width : float
        The thin tail continuing past the head's tip.
    depth : float
        Depth of the deepest point, in the head.
    """

    x: float
    y: float
    angle: float
    head_length: float
    head_half_width: float
    tail_length: float
    tail_half_width: float
    depth: float

    @property
    def reach(self) -> float:
        """Radius around (x, y) that contains the whole impression."""
        return self.head_length + self.tail_length + self.head_half_width

    def bounds(self) -> tuple[float, float, float, float]:
        """Tight box (x_min, x_max, y_min, y_max) around the impression, in mm."""
        length = self.head_length + self.tail_length
        u = np.array([0.0, 0.0, length])
        v = np.array([-self.head_half_width, self.head_half_width, 0.0])
        c, s = np.cos(self.angle), np.sin(self.angle)
        xs, ys = self.x + u * c - v * s, self.y + u * s + v * c
        return float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())


def random_inscription(
    rng: np.random.Generator,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    scale: float,
) -> list[Wedge]:
    """Wedges grouped into signs along horizontal lines of text, like a cuneiform inscription.

    Parameters
    ----------
    rng : np.random.Generator
        Source of randomness.
    x_range, y_range : tuple of float
        The area (mm, centred frame) every wedge must fit in entirely.
    scale : float
        Size factor; 1 gives heads of 1.6–3.2 mm, depths of 0.3–1 mm and lines 6 mm apart.

    Returns
    -------
    list of Wedge
    """
    line_gap = 6.0 * scale
    n_lines = max(1, int((y_range[1] - y_range[0]) // line_gap) + 1)
    line_ys = y_range[1] - line_gap * np.arange(n_lines)
    heads: list[tuple[float, float]] = []
    for line_y in line_ys:
        cursor = x_range[0]
        while cursor < x_range[1]:
            width = rng.uniform(2.5, 6.0) * scale
            count = int(rng.integers(1, 5))
            xs = rng.uniform(cursor, min(cursor + width, x_range[1]), count)
            ys = line_y + rng.uniform(-0.3, 0.3, count) * line_gap
            heads.extend(zip(xs, ys))
            cursor += width + rng.uniform(1.0, 2.5) * scale
    wedges = _random_shapes(rng, np.array(heads).reshape(-1, 2), scale)
    # Wedges running over the edge of the writing area would cut into the tablet's rim.
    return [
        wedge for wedge in wedges
        if (x_range[0] <= (box := wedge.bounds())[0] and box[1] <= x_range[1]
            and y_range[0] <= box[2] and box[3] <= y_range[1])
    ]


def _random_shapes(rng: np.random.Generator, heads: np.ndarray, scale: float) -> list[Wedge]:
    """Wedges at the given head positions with random cuneiform-like shapes and directions."""
    count = len(heads)
    # Scribes mostly pressed horizontal and vertical wedges, fewer diagonal ones.
    base_angles = np.deg2rad(np.array([0.0, -90.0, -45.0, 45.0]))
    kinds = rng.choice(len(base_angles), size=count, p=[0.55, 0.25, 0.1, 0.1])
    angles = base_angles[kinds] + np.deg2rad(rng.normal(0.0, 6.0, count))
    head = rng.uniform(1.6, 3.2, count) * scale
    half_width = head * rng.uniform(0.45, 0.6, count)
    tail = head * rng.uniform(0.6, 1.6, count)
    tail_half_width = rng.uniform(0.3, 0.45, count) * scale
    depth = rng.uniform(0.3, 1.0, count) * scale
    return [
        Wedge(*map(float, values))
        for values in zip(heads[:, 0], heads[:, 1], angles, head, half_width, tail,
                          tail_half_width, depth)
    ]


def _pyramid(u: np.ndarray, v: np.ndarray, corners: np.ndarray, apex: np.ndarray,
             depth: float, max_slope_deg: float = MAX_FACET_SLOPE_DEG) -> np.ndarray:
    """Depth of a pyramid over a triangle, deepest at ``apex``, zero outside the triangle.

    Parameters
    ----------
    u, v : np.ndarray
        Local coordinates (mm) of the sample points, broadcastable.
    corners : np.ndarray
        (3, 2) triangle corners, counter-clockwise, in local coordinates.
    apex : np.ndarray
        (2,) deepest point, strictly inside the triangle.
    depth : float
        Depth at the apex, before the slope limit.
    max_slope_deg : float
        Steepest facet: a deeper apex is raised to it.

    Returns
    -------
    np.ndarray
        Depth (≥ 0) at each sample.
    """
    edges = np.roll(corners, -1, axis=0) - corners
    inward = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    apex_dist = np.einsum("ij,ij->i", inward, apex[None, :] - corners)
    depth = min(depth, np.tan(np.deg2rad(max_slope_deg)) * apex_dist.min())
    # A pyramid with a given apex is the minimum of its facet planes; each plane is 0 on its
    # edge and 1 at the apex, so the minimum is the depth fraction (negative outside).
    frac = None
    for corner, normal, dist in zip(corners, inward, apex_dist):
        plane = ((u - corner[0]) * normal[0] + (v - corner[1]) * normal[1]) / dist
        frac = plane if frac is None else np.minimum(frac, plane)
    return depth * np.clip(frac, 0.0, None)


def wedge_depth(wedge: Wedge, x: np.ndarray, y: np.ndarray,
                max_slope_deg: float = MAX_FACET_SLOPE_DEG) -> np.ndarray:
    """Depth (mm, ≥ 0) of one wedge impression at points (x, y) of the centred frame.

    Parameters
    ----------
    wedge : Wedge
        The impression.
    x, y : np.ndarray
        Coordinates in mm, broadcastable to each other.
    max_slope_deg : float
        Steepest facet (a stylus pressed deep and at a steep angle leaves walls of 70° and
        more; the tablet keeps the default).

    Returns
    -------
    np.ndarray
        Depth of the impression, 0 outside it.
    """
    c, s = np.cos(wedge.angle), np.sin(wedge.angle)
    dx, dy = x - wedge.x, y - wedge.y
    u = dx * c + dy * s
    v = -dx * s + dy * c
    hl, hw = wedge.head_length, wedge.head_half_width
    apex = np.array([0.3 * hl, 0.0])
    head = _pyramid(u, v, np.array([[0.0, -hw], [hl, 0.0], [0.0, hw]]), apex, wedge.depth,
                    max_slope_deg)
    # The tail is a long thin pyramid sharing the head's deepest point, so it reads as a
    # groove running out of the head's tip.
    tw, end = wedge.tail_half_width, hl + wedge.tail_length
    tail = _pyramid(u, v, np.array([[0.1 * hl, -tw], [end, 0.0], [0.1 * hl, tw]]), apex,
                    0.7 * wedge.depth, max_slope_deg)
    return np.maximum(head, tail)


def rasterize_wedges(wedges: list[Wedge], x: np.ndarray, y: np.ndarray,
                     pixel_size: float,
                     max_slope_deg: float = MAX_FACET_SLOPE_DEG) -> np.ndarray:
    """Combined depth of overlapping wedges on the pixel grid.

    Parameters
    ----------
    wedges : list of Wedge
        The impressions.
    x, y : np.ndarray
        Pixel-centre coordinates from :func:`data_synthetic.surface.centred_grid`,
        shapes (1, W) and (H, 1).
    pixel_size : float
        Millimetres per pixel.
    max_slope_deg : float
        Steepest facet of every wedge (:func:`wedge_depth`).

    Returns
    -------
    np.ndarray
        (H, W) float64 depth; overlapping impressions keep the deeper one.
    """
    h, w = y.shape[0], x.shape[1]
    depth = np.zeros((h, w))
    x0, y0 = x[0, 0], y[0, 0]
    for wedge in wedges:
        # Each wedge only touches a small box of pixels; evaluate it there alone.
        reach = wedge.reach / pixel_size + 1
        col, row = (wedge.x - x0) / pixel_size, (y0 - wedge.y) / pixel_size
        r0, r1 = max(0, int(row - reach)), min(h, int(row + reach) + 2)
        c0, c1 = max(0, int(col - reach)), min(w, int(col + reach) + 2)
        if r0 >= r1 or c0 >= c1:
            continue
        box = wedge_depth(wedge, x[:, c0:c1], y[r0:r1, :], max_slope_deg)
        np.maximum(depth[r0:r1, c0:c1], box, out=depth[r0:r1, c0:c1])
    return depth


def wedge_plate(
    shape: tuple[int, int] = (256, 320),
    pixel_size: float = 0.05,
    *,
    max_slope_deg: float = 75.0,
    depth_scale: float = 3.0,
    seed: int = 0,
) -> np.ndarray:
    """Height (mm, ≤ 0) of a flat plate covered in steep-walled wedge impressions.

    The inscription of :func:`random_inscription` at scale 1 over the whole frame, its depths
    multiplied by `depth_scale` and its facets allowed up to `max_slope_deg`, smoothed over
    0.75 pixel like the tablet's: a test of integration on walls much steeper than the
    tablet's (which keeps :data:`MAX_FACET_SLOPE_DEG`).

    Parameters
    ----------
    shape : tuple of int
        (H, W) in pixels.
    pixel_size : float
        Millimetres per pixel.
    max_slope_deg : float
        Steepest facet before smoothing.
    depth_scale : float
        Factor on the inscription's depths (0.3–1 mm at scale 1).
    seed : int
        Drives the inscription.

    Returns
    -------
    np.ndarray
        (H, W) float64 height in mm, 0 on the plate.
    """
    rng = np.random.default_rng(seed)
    x, y = centred_grid(shape, pixel_size)
    half_w, half_h = shape[1] * pixel_size / 2 - 1.0, shape[0] * pixel_size / 2 - 1.0
    wedges = [
        replace(wedge, depth=depth_scale * wedge.depth)
        for wedge in random_inscription(rng, (-half_w, half_w), (-half_h, half_h), 1.0)
    ]
    depth = rasterize_wedges(wedges, x, y, pixel_size, max_slope_deg)
    return -ndimage.gaussian_filter(depth, 0.75)
