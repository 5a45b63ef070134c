"""The charts of ``report.html``: the height profile (matplotlib; the lights' polar plot is
:func:`reconstruct.calibration.lightcheck.polar_plot_png`).

Each chart is drawn at the size the page shows it (:data:`CHART_WIDTH` pixels), with text
large enough to read there, axes ticks at round values (1, 2 or 5 × 10^k: :func:`round_ticks`)
and lengths in millimetres when a pixel size is known. The figures are matplotlib ``Figure``
objects of their own (no pyplot, no global state), so two pages can be made in two threads.
"""

from __future__ import annotations

import io

import numpy as np

from reconstruct.report.summary import unit_words

__all__ = ["CHART_WIDTH", "FONT_SIZE", "figure", "png", "profile_figure", "profile_row", "round_ticks"]

#: Width of the charts in pixels, as the page shows them (one column of the page).
CHART_WIDTH = 900

#: Text size of the charts in points at 100 dpi: about 14 screen pixels.
FONT_SIZE = 10.5


def round_ticks(nbins: int = 6):
    """A matplotlib locator placing ticks at multiples of 1, 2 or 5 × 10^k (never 2.5)."""
    from matplotlib.ticker import MaxNLocator

    return MaxNLocator(nbins=nbins, steps=[1, 2, 5, 10])


def png(fig) -> bytes:
    """A matplotlib figure as PNG bytes, tagged as sRGB (:mod:`ptmcore.colourtags`)."""
    from ptmcore.colourtags import srgb_save_options

    buf = io.BytesIO()
    fig.savefig(buf, format="png", pil_kwargs=srgb_save_options("PNG"))
    return buf.getvalue()


def figure(width_px: int, height_px: int):
    """A matplotlib ``Figure`` of `width_px` × `height_px` pixels at 100 dpi, laid out by
    matplotlib's constrained layout, on an Agg canvas of its own (no pyplot)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_px / 100, height_px / 100), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def profile_row(height: np.ndarray) -> int:
    """The row of a height map through the middle of the object (its finite heights' rows)."""
    rows = np.flatnonzero(np.isfinite(height).any(axis=1))
    return int((rows[0] + rows[-1]) // 2) if rows.size else height.shape[0] // 2


def profile_figure(height: np.ndarray, row: int, stride: int, unit: str, pixel_size: float | None, *,
                   width_px: int = CHART_WIDTH) -> bytes:
    """The heights along one row of a height map's subsample, as PNG bytes.

    Parameters
    ----------
    height : ndarray, shape (h, w)
        Every ``stride``-th height of the full map (NaN outside the object: gaps in the line).
    row : int
        The row of the subsample (the full map's row ``row * stride``).
    stride : int
        The subsample's step in full-size pixels.
    unit : str
        The heights' unit.
    pixel_size : float or None
        Millimetres per full-size pixel; the distance along the row is in mm when given, else
        in pixels.
    """
    fig = figure(width_px, 300)
    ax = fig.add_subplot()
    per = (pixel_size or 1.0) * stride
    x = np.arange(height.shape[1]) * per
    values = height[row]
    ax.plot(x, values, color="#1b4f8a", linewidth=1.6)
    finite = values[np.isfinite(values)]
    if finite.size:
        ax.fill_between(x, np.nanmin(finite), values, color="#1b4f8a", alpha=0.12, linewidth=0)
    ax.set_xlim(0, x[-1] if x.size > 1 else 1)
    ax.xaxis.set_major_locator(round_ticks(10))
    ax.yaxis.set_major_locator(round_ticks(5))
    unit = unit_words(unit)
    ax.set_xlabel(f"distance from the left edge ({'mm' if pixel_size else 'pixels'})", fontsize=FONT_SIZE)
    ax.set_ylabel(f"height ({unit})", fontsize=FONT_SIZE)
    ax.tick_params(labelsize=FONT_SIZE)
    ax.grid(color="#dddddd", linewidth=0.8)
    ax.spines[["top", "right"]].set_visible(False)
    return png(fig)
