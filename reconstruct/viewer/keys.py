"""The preview window's keys, listed once for the window's help and ``preview --help``.

Kept apart from :mod:`reconstruct.viewer.preview` so that the command line's parser lists
them without importing the window.
"""

from __future__ import annotations

__all__ = ["KEYS", "help_text"]

#: (key, what it does), in the order the help lists them.
KEYS = (
    ("1 2 3 4 5", "views: relit, albedo, normals, height, distance to a scan"),
    ("6 7 8", "views: specular enhancement, diffuse gain, relief shading"),
    ("arrows", "move the light left, right, up, down as seen"),
    ("drag on the disk", "move the light (lower left: the hemisphere from above)"),
    ("+ / -", "vertical exaggeration (mesh and relief shading)"),
    ("[ / ]", "diffuse gain, or specular highlight size, in those views"),
    ("right click", "pick a point; two give a distance or a height profile"),
    ("m", "measure distances or height profiles"),
    ("e", "export the last measurement (CSV; profile also PNG)"),
    ("s", "screenshot: a clean figure with scale bar and light marker"),
    ("r", "reset the view"),
    ("h", "show or hide this help"),
    ("q", "quit"),
)


def help_text() -> str:
    """The keys as lines ``key  what it does``."""
    return "\n".join(f"{key:<18}{text}" for key, text in KEYS)
