"""Hemispherical harmonics (HSH) as a relighting basis, as in RTIBuilder's and RTIViewer's ``.rti``.

Hemispherical harmonics (Gautron, Křivánek, Pattanaik, Bouatouch: "A Novel Hemispherical Basis
for Accurate and Efficient Rendering", EGSR 2004) are spherical harmonics whose Legendre part is
shifted from [−1, 1] onto the upper hemisphere, cos θ ∈ [0, 1], so they are orthonormal over
the hemisphere of light directions. An HSH of order ``n`` has ``n²`` terms: 4 for order 2, 9
for order 3 (the two orders RTIBuilder's HSH fitter writes) and 16 for order 4.

Per pixel the luminance under a light is ``L = Σ_k c_k H_k(θ, φ)``, a linear model like the PTM's
biquadratic, so the least-squares fit of every pixel is one K×N pseudoinverse applied to the
stack (:func:`fit_hsh`, done in bands like :func:`ptmcore.fit.fit_ptm`).

Convention (what makes coefficients interchangeable with RTIViewer's): for a light direction
(x, y, z) in the capture frame (x right, y up, z towards the camera),

* φ = atan2(y, x), the azimuth counter-clockwise from +x (RTIViewer then wraps it to [0, 2π),
  which changes none of the cos mφ, sin mφ below);
* θ = min(arccos(z / |l|), π/2 − 0.04), the angle from the camera axis, kept 0.04 rad above the
  horizon as RTIViewer does (s below has an infinite slope at the horizon, c = 0);

and with c = cos θ and s = √(c − c²) = √(cos θ (1 − cos θ)) the terms, in file order, are::

    H0 = 1/√(2π)
    H1 = √(6/π)  · cos φ · s                 H3 = √(6/π)  · sin φ · s
    H2 = √(3/2π) · (2c − 1)
    H4 = √(30/π) · cos 2φ · (c² − c)         H8 = √(30/π) · sin 2φ · (c² − c)
    H5 = √(30/π) · cos φ · (2c − 1) · s      H7 = √(30/π) · sin φ · (2c − 1) · s
    H6 = √(5/2π) · (6c² − 6c + 1)

and, for order 4 only::

    H9  = 2√(35/π) · cos 3φ · s³                      H15 = 2√(35/π) · sin 3φ · s³
    H10 = √(210/π) · cos 2φ · (2c − 1)(c² − c)        H14 = √(210/π) · sin 2φ · (2c − 1)(c² − c)
    H11 = 2√(21/π) · cos φ · (5c² − 5c + 1) · s       H13 = 2√(21/π) · sin φ · (5c² − 5c + 1) · s
    H12 = √(7/2π)  · (20c³ − 30c² + 12c − 1)

The ordering is the same for every order: term ``k = l² + l − m`` holds degree ``l`` and order
``m`` of Gautron et al.'s ``H_l^m = K_l^m · P_l^|m|(2 cos θ − 1) · {cos mφ, 1, sin |m|φ}``, ``m``
running from ``+l`` (cos lφ) down to ``−l`` (sin lφ), so order ``n`` is the first ``n²`` terms of
order ``n + 1``. With the Condon–Shortley phase in P_l^m, RTIViewer's terms for ``m ≠ 0`` are the
negatives of Gautron's; for ``m = 0`` they are equal.

Source: RTIViewer 1.1 (Visual Computing Lab, ISTI-CNR and Cultural Heritage Imaging), ``getHSH``
in ``util.h`` for the terms (its ``order > 3`` branch gives the 16 terms of order 4) and its HSH
rendering modes for θ and φ (the 0.04 rad clamp); the 9 terms of order 3 and the same angles are
in ``Rti::lightWeightsHsh`` of cnr-isti-vclab/relight (``src/rti.cpp``), which clamps θ at
π/2 − 0.01 instead, and in OpenLIME's ``ShaderRTI.js`` (class ``HSH``); neither has order 4.
The order-4 terms were checked against Gautron et al.'s definition (normalisation
K_l^m = √((2l+1)/(2π) · (l−|m|)!/(l+|m|)!), times √2 for m ≠ 0). Written from those
descriptions, not copied. The signs are RTIViewer's (H4 and H8 go as c² − c ≤ 0, the opposite
sign of the shifted Legendre function P₂² they come from): orthonormality over the hemisphere
does not depend on signs, compatibility with ``.rti`` files does.

Unlike RTIBuilder, which fits the 8-bit sRGB pixel values, :func:`fit_hsh` fits the linear
luminance of the :class:`~ptmcore.images.ImageStack`, like :func:`~ptmcore.fit.fit_ptm`.

Where order 4 goes: :func:`hsh_basis` and :func:`fit_hsh` take orders 2–4
(:data:`BASIS_ORDERS`); the ``.rti`` files of :mod:`ptmcore.rtifile` and the encoded fits of
:mod:`ptmcore.ptmencoded` stay at :data:`ORDERS` (2 and 3), because OpenLIME (9 HSH terms at
most) and relight cannot show order 4, and this project's ``.rti`` reader refuses 16 terms.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .fit import LinearRelighting, apply_fit_matrix
from .images import ImageStack
from .lp import as_directions

#: HSH orders of the ``.rti`` files this project writes and reads (RTIBuilder's choices, order²
#: terms: 4 or 9), and of the encoded fits; OpenLIME and relight show no more than order 3.
ORDERS = (2, 3)
#: HSH orders :func:`hsh_basis` and :func:`fit_hsh` evaluate: :data:`ORDERS` and order 4
#: (16 terms, RTIViewer's largest).
BASIS_ORDERS = (2, 3, 4)
#: RTIViewer keeps θ this far (radians) above the horizon when it evaluates the basis.
HORIZON_MARGIN = 0.04
#: Singular values of the light matrix below this fraction of the largest are taken as zero.
#: Lights on one ring leave combinations of terms undetermined (H0, H2, H6 are all constant
#: there), and an ``.lp`` file's six decimals turn those exact zeros into singular values of
#: 1e-7 to 1e-13: NumPy's default cut (1e-15) keeps them, and the float32 fit then multiplies
#: rounding by up to 1e13 (coefficients of 1e10 and luminance errors in the thousands on a
#: ring capture). Genuine layouts are far above the cut: a 48-light dome confined to 40–50°
#: elevation still has 6e-3 for order 3.
RCOND = 1e-4


def _check_order(order: int) -> int:
    if order not in BASIS_ORDERS:
        raise ValueError(f"HSH order must be one of {BASIS_ORDERS}, got {order!r}")
    return int(order)


def hsh_angles(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RTIViewer's (θ, φ) of light directions.

    Parameters
    ----------
    directions : ndarray, shape (N, 3) or (N, 2)
        Vectors towards the lights (x right, y up, z towards the camera); any length, or unit
        (lu, lv) projections whose z is then √(1 − lu² − lv²).

    Returns
    -------
    theta : ndarray, shape (N,), float64
        Angle from the camera axis, at most π/2 − :data:`HORIZON_MARGIN`.
    phi : ndarray, shape (N,), float64
        Azimuth atan2(y, x), counter-clockwise from +x, in [0, 2π).
    """
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] not in (2, 3):
        raise ValueError(f"directions must have shape (N, 3) or (N, 2), got {d.shape}")
    if d.shape[1] == 2:
        z = np.sqrt(np.clip(1.0 - d[:, 0] ** 2 - d[:, 1] ** 2, 0.0, None))
        d = np.column_stack([d, z])
    length = np.linalg.norm(d, axis=1)
    if not np.all(np.isfinite(length)) or np.any(length == 0):
        raise ValueError("light directions must be finite and non-zero")
    cos_theta = np.clip(d[:, 2] / length, -1.0, 1.0)
    theta = np.minimum(np.arccos(cos_theta), np.pi / 2 - HORIZON_MARGIN)
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    return theta, phi


def hsh_basis(directions: np.ndarray, order: int = 3) -> np.ndarray:
    """The N×order² HSH light matrix, one row of basis values per light.

    Parameters
    ----------
    directions : ndarray, shape (N, 3) or (N, 2)
        Vectors towards the lights, as for :func:`hsh_angles`.
    order : int
        2 (4 terms), 3 (9 terms) or 4 (16 terms); each order's terms are the first of the
        next order's.

    Returns
    -------
    ndarray, shape (N, order²), float64
        Columns H0 … H(order²−1) in RTIViewer's order (see the module docstring).
    """
    order = _check_order(order)
    theta, phi = hsh_angles(directions)
    c = np.cos(theta)
    # c − c² ≥ 0 on the hemisphere; the clip only absorbs rounding at c = 0 or 1.
    s = np.sqrt(np.clip(c - c * c, 0.0, None))
    cos_p, sin_p = np.cos(phi), np.sin(phi)
    terms = [
        np.full_like(c, 1.0 / np.sqrt(2 * np.pi)),
        np.sqrt(6 / np.pi) * cos_p * s,
        np.sqrt(3 / (2 * np.pi)) * (2 * c - 1),
        np.sqrt(6 / np.pi) * sin_p * s,
    ]
    if order >= 3:
        k = np.sqrt(30 / np.pi)
        terms += [
            k * np.cos(2 * phi) * (c * c - c),
            k * cos_p * (2 * c - 1) * s,
            np.sqrt(5 / (2 * np.pi)) * (6 * c * c - 6 * c + 1),
            k * sin_p * (2 * c - 1) * s,
            k * np.sin(2 * phi) * (c * c - c),
        ]
    if order >= 4:
        s3 = s * s * s  # (c − c²)^1.5, RTIViewer's pow(c − c², 1.5), without its NaN at rounding
        k3, k2, k1 = 2 * np.sqrt(35 / np.pi), np.sqrt(210 / np.pi), 2 * np.sqrt(21 / np.pi)
        p32 = (2 * c - 1) * (c * c - c)
        p31 = (5 * c * c - 5 * c + 1) * s
        terms += [
            k3 * np.cos(3 * phi) * s3,
            k2 * np.cos(2 * phi) * p32,
            k1 * cos_p * p31,
            np.sqrt(7 / (2 * np.pi)) * (((20 * c - 30) * c + 12) * c - 1),
            k1 * sin_p * p31,
            k2 * np.sin(2 * phi) * p32,
            k3 * np.sin(3 * phi) * s3,
        ]
    return np.stack(terms, axis=1)


def hsh_fit_matrix(directions: np.ndarray, order: int = 3) -> np.ndarray:
    """The order²×N pseudoinverse that maps N luminances to the HSH coefficients.

    Singular values below :data:`RCOND` times the largest are dropped, so undetermined
    combinations of terms get zero rather than rounding blown up (the minimum-norm fit).
    """
    return np.linalg.pinv(hsh_basis(directions, order), rcond=RCOND)


@dataclass
class HSH(LinearRelighting):
    """A luminance HSH relighting model with per-pixel colour, the analogue of an LRGB PTM:
    coefficients c0 … c(order²−1), shape (H, W, order²)."""

    @property
    def order(self) -> int:
        """The HSH order, √(number of terms)."""
        return int(round(np.sqrt(self.coefficients.shape[-1])))

    def basis(self, light: np.ndarray) -> np.ndarray:
        return hsh_basis(light.reshape(1, -1), self.order)[0]


def fit_hsh(
    stack: ImageStack,
    directions: np.ndarray,
    order: int = 3,
    *,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> HSH:
    """Fit a luminance HSH to a stack by least squares.

    Parameters
    ----------
    stack : ImageStack
        The photographs' luminance.
    directions : ndarray, shape (N, 3)
        Unit light directions, one per photograph.
    order : int
        2 (4 coefficients), 3 (9 coefficients) or 4 (16 coefficients).
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.

    Returns
    -------
    HSH

    Notes
    -----
    With fewer lights than terms, or lights that do not separate the terms (all on one ring
    leaves H0, H2 and H6 indistinguishable; two rings leave one combination of them), the
    pseudoinverse gives the minimum-norm fit (see :data:`RCOND`).
    """
    order = _check_order(order)
    matrix = hsh_fit_matrix(as_directions(directions, len(stack)), order)
    return HSH(apply_fit_matrix(stack, matrix, threads=threads, progress=progress), stack.chroma)
