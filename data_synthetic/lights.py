"""Directional light layouts: unit vectors towards the lights (x right, y up, z to camera)."""

from __future__ import annotations

import numpy as np


def _directions(azimuth_rad: np.ndarray, elevation_rad: np.ndarray) -> np.ndarray:
    """Unit vectors from azimuth (counter-clockwise from +x) and elevation above the plane."""
    cos_el = np.cos(elevation_rad)
    return np.stack(
        [cos_el * np.cos(azimuth_rad), cos_el * np.sin(azimuth_rad), np.sin(elevation_rad)],
        axis=-1,
    )


def _ring_counts(n: int, elevations_rad: np.ndarray) -> np.ndarray:
    """Split ``n`` lights over rings in proportion to each ring's circumference."""
    weights = np.cos(elevations_rad)
    share = n * weights / weights.sum()
    counts = np.floor(share).astype(int)
    # Largest remainders get the leftover lights; the stable sort makes ties deterministic.
    order = np.argsort(-(share - counts), kind="stable")
    counts[order[: n - counts.sum()]] += 1
    while counts.min() < 1:
        counts[np.argmax(counts)] -= 1
        counts[np.argmin(counts)] += 1
    return counts


def dome_lights(
    n: int = 48,
    min_elevation_deg: float = 15.0,
    max_elevation_deg: float = 75.0,
    seed: int | None = None,
) -> np.ndarray:
    """Lights on several rings of a dome, like a real RTI dome.

    Ring elevations are evenly spaced from ``min_elevation_deg`` to ``max_elevation_deg``:
    about √(n/3) rings, at least two from 6 lights on so the biquadratic PTM basis has full
    rank (fewer lights share one ring at the mean elevation). Each ring gets lights in
    proportion to its circumference, evenly spread in azimuth, alternate rings staggered by
    half a spacing.

    Parameters
    ----------
    n : int
        Number of lights, at least 3.
    min_elevation_deg, max_elevation_deg : float
        Elevation of the lowest and highest ring above the object plane, in (0, 90].
    seed : int, optional
        None gives the ideal layout; an integer jitters each light (±15 % of the azimuth
        spacing, ±2° of elevation) deterministically, like a hand-built dome.

    Returns
    -------
    np.ndarray
        (n, 3) float64 unit vectors towards the lights, ring by ring from the lowest.
    """
    if n < 3:
        raise ValueError(f"need at least 3 lights, got {n}")
    if not 0 < min_elevation_deg <= max_elevation_deg <= 90:
        raise ValueError(
            "elevations must satisfy 0 < min ≤ max ≤ 90 degrees, got "
            f"{min_elevation_deg}, {max_elevation_deg}"
        )
    n_rings = 1 if n < 6 else max(2, min(n // 3, round(np.sqrt(n / 3))))
    if n_rings == 1:
        ring_el = np.array([0.5 * (min_elevation_deg + max_elevation_deg)])
    else:
        ring_el = np.linspace(min_elevation_deg, max_elevation_deg, n_rings)
    counts = _ring_counts(n, np.deg2rad(ring_el))
    ring = np.repeat(np.arange(n_rings), counts)
    index = np.concatenate([np.arange(c) for c in counts])
    spacing = 2 * np.pi / counts[ring]
    azimuth = (index + 0.5 * (ring % 2)) * spacing
    elevation = np.deg2rad(ring_el[ring])
    if seed is not None:
        rng = np.random.default_rng(seed)
        azimuth = azimuth + rng.uniform(-0.15, 0.15, n) * spacing
        elevation = np.clip(elevation + np.deg2rad(rng.uniform(-2.0, 2.0, n)),
                            np.deg2rad(1.0), np.pi / 2)
    return _directions(azimuth, elevation)


def ring_lights(n: int, elevation_deg: float, azimuth_offset_deg: float = 0.0) -> np.ndarray:
    """Lights on a single ring at one elevation.

    All directions share the same elevation, so lu² + lv² is constant and the biquadratic PTM
    basis (lu², lv², lu·lv, lu, lv, 1) is rank-deficient: a deliberately degenerate layout.
    (A Lambertian fit still has full rank with three or more distinct azimuths.)

    Parameters
    ----------
    n : int
        Number of lights, at least 1.
    elevation_deg : float
        Elevation above the object plane, in (0, 90].
    azimuth_offset_deg : float
        Azimuth of the first light, counter-clockwise from +x.

    Returns
    -------
    np.ndarray
        (n, 3) float64 unit vectors towards the lights, by increasing azimuth.
    """
    if n < 1:
        raise ValueError(f"need at least 1 light, got {n}")
    if not 0 < elevation_deg <= 90:
        raise ValueError(f"elevation must be in (0, 90] degrees, got {elevation_deg}")
    azimuth = np.deg2rad(azimuth_offset_deg + 360.0 * np.arange(n) / n)
    return _directions(azimuth, np.full(n, np.deg2rad(elevation_deg)))
