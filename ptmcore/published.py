"""A relighting basis as it is published: per-pixel planes and what turns them into a pixel.

The linear bases this project publishes for people to relight (PTM, HSH, RBF, bilinear) render
a pixel under a light as a linear combination of its per-pixel planes, with weights that
depend only on the light; the learned one (NeuralRTI, :mod:`ptmcore.neural`) as a small
network's output for the pixel's planes and the light. :class:`PublishedBasis` holds that form,
in the three colour spaces of the web formats OpenLIME reads (its ``ShaderRTI`` and
``ShaderNeural``):

* ``"lrgb"`` (``type`` ``"ptm"`` or ``"hsh"``): a luminance model times a per-pixel colour::

      display_rgb = colour / 255 · Σ_k w_k(light) · planes[..., k]

  with ``w`` the basis functions at the light (:meth:`PublishedBasis.weights`), the planes in
  the order of the basis terms (PTM: ``1, x, y, x², x·y, y²``, OpenLIME's order; HSH:
  H0 … H(order²−1), :mod:`ptmcore.hsh`), in 0–1 units of ``encoding``.
* ``"mrgb"`` (``type`` ``"rbf"`` or ``"bln"``): a principal-component basis of RGB samples
  shared by all pixels, per-pixel coefficients::

      display_rgb = B₀(light) + Σ_k planes[..., k] · B_{k+1}(light)

  with ``B_p(light) = Σ_d v_d(light) · basis[p, d]`` (an RGB triple), ``v`` the interpolation
  weights of the light over the ``D`` basis directions: the capture's lights for ``"rbf"``
  (normalised Gaussians of width ``sigma``), the nodes of a ``resolution × resolution`` grid
  over the hemisphere for ``"bln"`` (bilinear). ``basis[0]`` is the mean of the samples, in
  0–1 units of ``encoding``.
* ``"rgb"`` (``type`` ``"neural"``): the planes are each pixel's code (k = 9 numbers), the
  decoder ``network`` three dense layers ``(W_i, b_i)``, ``W_i`` of shape (inputs, outputs)::

      h1 = elu([code, lu, lv] · W_1 + b_1)
      h2 = elu(h1 · W_2 + b_2)
      display_rgb = h2 · W_3 + b_3

  with ``(lu, lv)`` the x (right) and y (up) of the unit light vector and
  ``elu(z) = z if z > 0 else exp(z) − 1``: OpenLIME's ``ShaderNeural``. Display values
  (``encoding`` ``"srgb"``), as the network is trained on (:func:`neural_basis`).

``encoding`` says what the rendered values are: ``"srgb"``, display values as they are, or
``"linear"``, linear light that a viewer encodes to sRGB for display.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:
    from .neural import NeuralModel

__all__ = ["OPENLIME_PTM_ORDER", "PublishedBasis", "neural_basis", "ptm_weights"]

#: HP's a0…a5 (:func:`ptmcore.fit.light_matrix`) in OpenLIME's plane order 1, x, y, x², x·y, y².
OPENLIME_PTM_ORDER = [5, 3, 4, 0, 2, 1]


def ptm_weights(directions: np.ndarray) -> np.ndarray:
    """The PTM's six basis functions ``(N, 6)`` at unit light directions, in OpenLIME's plane
    order ``1, x, y, x², x·y, y²`` (HP's a0…a5 are ``x², y², x·y, x, y, 1``)."""
    from .fit import light_matrix

    d = np.asarray(directions, dtype=np.float64).reshape(-1, np.shape(directions)[-1])
    return light_matrix(d)[:, OPENLIME_PTM_ORDER]


@dataclass
class PublishedBasis:
    """A relighting basis in the form published for viewers (see the module docstring).

    Attributes
    ----------
    type : {"ptm", "hsh", "rbf", "bln", "neural"}
        The basis, as Relight's (and OpenLIME's) ``info.json`` names it.
    colorspace : {"lrgb", "mrgb", "rgb"}
        ``"lrgb"`` for PTM and HSH, ``"mrgb"`` for RBF and bilinear, ``"rgb"`` for neural.
    planes : ndarray, shape (H, W, K), float32
        Per-pixel coefficients; for ``"neural"``, the codes.
    encoding : {"srgb", "linear"}
        What the rendered values are.
    colour : ndarray, shape (H, W, 3), uint8, optional
        The per-pixel colour of ``"lrgb"``.
    lights : ndarray, shape (D, 3), optional
        ``"rbf"``: the unit directions the basis is given at (the capture's lights).
    sigma : float, optional
        ``"rbf"``: the Gaussians' width, in units of the distance between unit vectors.
    resolution : int, optional
        ``"bln"``: the grid's side.
    basis : ndarray, shape (K + 1, D, 3), float32, optional
        ``"mrgb"``: the mean (row 0) and the K components at each basis direction, RGB.
    order : int, optional
        ``"hsh"``: the order (K = order²).
    network : list of (weights, bias), optional
        ``"neural"``: the decoder's three layers, weights of shape (inputs, outputs) (module
        docstring).
    name : str
        The basis as the command line names it (``ptm``, ``hsh3``, ``rbf``, ``bilinear``,
        ``neural``…).
    """

    type: Literal["ptm", "hsh", "rbf", "bln", "neural"]
    colorspace: Literal["lrgb", "mrgb", "rgb"]
    planes: np.ndarray
    encoding: Literal["srgb", "linear"] = "srgb"
    colour: np.ndarray | None = None
    lights: np.ndarray | None = None
    sigma: float | None = None
    resolution: int | None = None
    basis: np.ndarray | None = None
    order: int | None = None
    network: list[tuple[np.ndarray, np.ndarray]] | None = None
    name: str = field(default="")

    @property
    def shape(self) -> tuple[int, int]:
        """Image height and width."""
        return self.planes.shape[:2]

    def weights(self, light: np.ndarray) -> np.ndarray:
        """What weighs the planes under one light (x, y, z), unit or not.

        Returns
        -------
        ndarray, float64
            ``"lrgb"``: the K basis functions, shape (K,). ``"mrgb"``: the RGB triples
            ``B_0 … B_K`` of the module docstring, shape (K + 1, 3).

        Raises
        ------
        ValueError
            For a ``"neural"`` basis, which no weights combine linearly.
        """
        from .hsh import hsh_basis
        from .interpolation import bilinear_weights, rbf_weights

        if self.type == "neural":
            raise ValueError("a neural basis is not linear in its planes: it has no weights")
        d = np.asarray(light, dtype=np.float64).reshape(1, 3)
        d = d / np.linalg.norm(d)
        if self.type == "ptm":
            return ptm_weights(d)[0]
        if self.type == "hsh":
            return hsh_basis(d, int(self.order))[0]
        v = rbf_weights(self.lights, d, self.sigma) if self.type == "rbf" else bilinear_weights(d, self.resolution)
        return np.einsum("d,pdc->pc", v[0], self.basis.astype(np.float64))

    def render(self, light: np.ndarray) -> np.ndarray:
        """The image ``(H, W, 3)`` float32 under one light, in the values of ``encoding``
        (0–1, not clipped; :meth:`display` for an image to look at)."""
        if self.type == "neural":
            from .neural import apply_decoder  # evaluated in chunks of pixels: bounded memory

            return apply_decoder(self.network, self.planes, light)
        w = self.weights(light).astype(np.float32)
        if self.colorspace == "lrgb":
            return self.colour.astype(np.float32) / np.float32(255.0) * (self.planes @ w)[..., None]
        return w[0] + self.planes @ w[1:]

    def display(self, light: np.ndarray) -> np.ndarray:
        """The image ``(H, W, 3)`` uint8 sRGB under one light, as a viewer shows it."""
        from .images import linear_to_srgb

        rgb = np.clip(self.render(light), 0.0, 1.0)
        if self.encoding == "linear":
            rgb = linear_to_srgb(rgb)
        return np.rint(rgb * np.float32(255.0)).astype(np.uint8)


def neural_basis(model: NeuralModel, codes: np.ndarray, name: str = "neural") -> PublishedBasis:
    """The published form of a NeuralRTI model (:mod:`ptmcore.neural`) and its pixels' codes.

    Parameters
    ----------
    model : NeuralModel
        Its decoder is published (the encoder is not: the codes stand for it).
    codes : ndarray, shape (H, W, k)
        The pixels' codes, :func:`ptmcore.neural.encode` of their samples reshaped to the image.
    name : str

    Returns
    -------
    PublishedBasis
        Type ``"neural"``, colour space ``"rgb"``, encoding ``"srgb"`` (the network's output is
        display values); its planes the codes as float32, its network a copy of the decoder.

    Raises
    ------
    ValueError
        If ``codes`` is not ``(H, W, k)`` with the model's code size.
    """
    codes = np.asarray(codes)
    if codes.ndim != 3 or codes.shape[2] != model.code_size:
        raise ValueError(f"codes must be (H, W, {model.code_size}), not {codes.shape}")
    network = [(np.array(w, np.float32), np.array(b, np.float32)) for w, b in model.decoder]
    return PublishedBasis("neural", "rgb", codes.astype(np.float32), "srgb", network=network, name=name)
