"""A pyvista plotter whose OpenGL context is known to work, on screen or off.

On a machine without a display VTK first tries X, prints a warning, then falls back to EGL
or OSMesa (Mesa's software rasteriser). The warning is expected there and alarms users, so
VTK's warnings are held back while the context is created; real errors still show. Where
no context can be had at all, :func:`plotter` raises ``RuntimeError`` at once instead of
crashing in the first render. ``VTK_DEFAULT_OPENGL_WINDOW`` is left alone (an empty value
crashes VTK; a wrong class segfaults where its library is missing).
"""

from __future__ import annotations

import importlib
import threading

import numpy as np

__all__ = ["VTK_LOCK", "import_plotting", "plotter", "render_image"]

#: Held while VTK reads or renders. VTK is not thread-safe: a batch makes the reports of two
#: objects in two threads of one worker, and a mesh read in one while the other rendered
#: aborted the process (seen once in a fresh test run).
VTK_LOCK = threading.RLock()
#: Held while matplotlib is imported (:func:`import_plotting`).
_IMPORTING = threading.Lock()


def import_plotting() -> None:
    """Import matplotlib's figures before threads draw with it, or render with pyvista (which
    imports it for its colour maps).

    matplotlib's modules import one another; imported for the first time from two threads at
    once (a page's charts in one, the mesh render's pyvista in the other), a thread can be
    handed the other's half-made module ("cannot import name 'Colormap' from partially
    initialized module 'matplotlib.colors'"): two of three 6-megapixel reports lost their
    height map, profile, light plot and mesh render so. Done once, under a lock, since a batch
    makes pages in several threads. Without matplotlib, the pictures that need it become notes.
    """
    with _IMPORTING:
        try:
            for name in ("matplotlib.colors", "matplotlib.figure", "matplotlib.backends.backend_agg"):
                importlib.import_module(name)
        except ImportError:
            pass


def plotter(size: tuple[int, int], *, off_screen: bool = True, **kwargs):
    """A ``pyvista.Plotter`` of ``size`` (width, height) pixels with a working OpenGL context.

    Parameters
    ----------
    size : (int, int)
        Window or image size in pixels.
    off_screen : bool
        Render to memory (screenshots) rather than to a window.
    **kwargs
        Passed on to ``pyvista.Plotter`` (``shape``, ``border``, ...).

    Returns
    -------
    pyvista.Plotter

    Raises
    ------
    RuntimeError
        When pyvista is missing or no OpenGL context can be created (no display, EGL or
        OSMesa); the message says which.
    """
    try:
        import pyvista as pv
        from vtkmodules.vtkCommonCore import vtkLogger
    except ImportError as exc:
        raise RuntimeError(f"rendering needs pyvista ({exc})") from exc

    previous = vtkLogger.GetCurrentVerbosityCutoff()
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
    try:
        result = pv.Plotter(off_screen=off_screen, window_size=(int(size[0]), int(size[1])), **kwargs)
        # Asking for OpenGL support creates the context.
        supported = result.ren_win.SupportsOpenGL()
    finally:
        vtkLogger.SetStderrVerbosity(vtkLogger.ConvertToVerbosity(previous))
    if not supported:
        result.close()
        raise RuntimeError("no OpenGL context (no display, EGL or OSMesa): cannot render; "
                           "install Mesa's libegl1 and libgl1-mesa-dri, or libosmesa6")
    return result


def render_image(draw, size: tuple[int, int], **kwargs) -> np.ndarray:
    """Render off-screen: ``draw(plotter)`` fills a fresh plotter; returns (H, W, 3) uint8.

    Raises
    ------
    RuntimeError
        No OpenGL context, a failure inside VTK (it reports them with assorted exception
        types), or an empty image.
    """
    result = None
    with VTK_LOCK:
        try:
            result = plotter(size, **kwargs)
            draw(result)
            image = result.screenshot(return_img=True)
        except RuntimeError:
            raise
        except Exception as exc:
            raise RuntimeError(f"off-screen rendering failed ({exc})") from exc
        finally:
            if result is not None:
                result.close()
    if image is None or image.size == 0 or np.ptp(image) == 0:
        raise RuntimeError("off-screen rendering is not available (the render is empty)")
    return np.ascontiguousarray(image[..., :3])
