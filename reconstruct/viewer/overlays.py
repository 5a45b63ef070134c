"""The preview window's 2-D overlays, drawn by VTK in display pixels over the 3-D view.

* :class:`LightDisk`: the hemisphere of light directions seen from above (the rim is the
  horizon, the centre the camera's direction, rings at 30° and 60° elevation) with a marker
  where the light is. Dragging on it moves the light; its mouse events are taken before the
  camera's, so the view never moves with it. In figures it is the light-direction marker.
* :class:`ScaleBar`: a bar of a round length (1, 2 or 5 × 10^k) in the scene's unit, kept
  true to the camera's zoom at every render (parallel projection).
* :class:`ImageStrip`: a picture (the height profile) in its own viewport along the bottom of
  the window, the 3-D view shrunk above it so the picture never covers the object.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from reconstruct.report.figures import nice_length

__all__ = ["ImageStrip", "LightDisk", "ScaleBar", "inside_horizon"]

_WHITE = (1.0, 1.0, 1.0)
_MARKER = (1.0, 0.85, 0.1)
_MARGIN = 16  # pixels between an overlay and the window's edge


#: The lowest elevation a light is moved to, degrees: a light at the horizon lights nothing.
MIN_ELEVATION = 1.0


def inside_horizon(lu: float, lv: float) -> tuple[float, float]:
    """A light's projection (lu, lv) pulled inside the rim, to :data:`MIN_ELEVATION` at the
    lowest."""
    r = math.hypot(lu, lv)
    top = math.cos(math.radians(MIN_ELEVATION))
    if r > top:
        lu, lv = lu * top / r, lv * top / r
    return float(lu), float(lv)


def _polylines(lines: list[np.ndarray]):
    """A vtkPolyData of 2-D polylines (each ``(n, 2)`` display coordinates)."""
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    points, cells = vtkPoints(), vtkCellArray()
    for line in lines:
        start = points.GetNumberOfPoints()
        for x, y in line:
            points.InsertNextPoint(float(x), float(y), 0.0)
        cells.InsertNextCell(len(line), list(range(start, start + len(line))))
    data = vtkPolyData()
    data.SetPoints(points)
    data.SetLines(cells)
    return data


def _disk(radius: float, sides: int = 40):
    """A filled 2-D disk centred on the origin, as vtkPolyData."""
    from vtkmodules.vtkFiltersSources import vtkRegularPolygonSource

    source = vtkRegularPolygonSource()
    source.SetNumberOfSides(sides)
    source.SetRadius(radius)
    source.SetCenter(0.0, 0.0, 0.0)
    source.Update()
    return source.GetOutput()


def _actor2d(data, color, *, width: float = 1.0, opacity: float = 1.0):
    from vtkmodules.vtkRenderingCore import vtkActor2D, vtkPolyDataMapper2D

    mapper = vtkPolyDataMapper2D()
    mapper.SetInputData(data)
    actor = vtkActor2D()
    actor.SetMapper(mapper)
    prop = actor.GetProperty()
    prop.SetColor(*color)
    prop.SetLineWidth(width)
    prop.SetOpacity(opacity)
    return actor


#: The scale bar's label size (points) and the profile strip's share of the window's height.
_SCALE_FONT = 14
STRIP_FRACTION = 0.3


def _text(font_size: int, *, justify_right: bool = False):
    from vtkmodules.vtkRenderingCore import vtkTextActor

    actor = vtkTextActor()
    prop = actor.GetTextProperty()
    prop.SetFontSize(font_size)
    prop.SetColor(*_WHITE)
    prop.SetShadow(True)
    if justify_right:
        prop.SetJustificationToRight()
    return actor


class LightDisk:
    """The light's direction on a disk in the lower left corner; drag on it to move the light.

    Parameters
    ----------
    renderer : vtkRenderer
        Where it is drawn.
    interactor : vtkRenderWindowInteractor or None
        Whose mouse events it takes (None off-screen: drawn only).
    radius : float
        Radius of the disk in pixels.
    on_light : callable
        Called with ``(lu, lv)``, the light's projection on the image plane, while dragging.
    """

    def __init__(self, renderer, interactor, radius: float, on_light: Callable[[float, float], None]) -> None:
        self.renderer = renderer
        self.radius = float(radius)
        self.centre = np.array([_MARGIN + radius, _MARGIN + radius + 14.0])
        self.on_light = on_light
        self.dragging = False
        self._enabled = True
        r, c = self.radius, self.centre
        t = np.linspace(0.0, 2 * np.pi, 65)
        circle = np.column_stack([np.cos(t), np.sin(t)])
        backdrop = _actor2d(_disk(r * 1.08, 64), (0.0, 0.0, 0.0), opacity=0.45)
        backdrop.SetPosition(*c)
        rings = [c + r * circle] + [c + r * math.cos(math.radians(e)) * circle for e in (30, 60)]
        cross = [np.array([c - (r, 0), c + (r, 0)]), np.array([c - (0, r), c + (0, r)])]
        self._rim = _actor2d(_polylines(rings[:1]), _WHITE, width=2.0)
        self._grid = _actor2d(_polylines(rings[1:] + cross), _WHITE, width=1.0, opacity=0.45)
        self._marker = _actor2d(_disk(max(4.0, r / 9)), _MARKER)
        self._ray = _actor2d(_polylines([np.zeros((2, 2))]), _MARKER, width=2.0)
        self.label = _text(max(10, int(r / 5)))
        self.label.SetPosition(_MARGIN, 4)
        self.actors = [backdrop, self._rim, self._grid, self._ray, self._marker, self.label]
        for actor in self.actors:
            renderer.AddViewProp(actor)
        self._tags: list[int] = []
        if interactor is not None:
            self._interactor = interactor
            for event, handler in (("LeftButtonPressEvent", self._press), ("MouseMoveEvent", self._move),
                                   ("LeftButtonReleaseEvent", self._release)):
                # Priority above the interactor style's (0): the camera never sees these events.
                self._tags.append(interactor.AddObserver(event, handler, 10.0))

    def set_light(self, light: np.ndarray, azimuth: float, elevation: float) -> None:
        """Move the marker to a unit light vector; label it with its angles."""
        tip = self.centre + self.radius * np.asarray(light[:2], dtype=np.float64)
        self._marker.SetPosition(*tip)
        self._ray.GetMapper().SetInputData(_polylines([np.array([self.centre, tip])]))
        self.label.SetInput(f"light: azimuth {azimuth:.0f}°, elevation {elevation:.0f}°")

    def set_visible(self, visible: bool) -> None:
        """Show or hide it; hidden, it takes no mouse events."""
        self._enabled = bool(visible)
        for actor in self.actors:
            actor.SetVisibility(self._enabled)

    def light_at(self, x: float, y: float) -> tuple[float, float]:
        """(lu, lv) under display pixel (x, y), pulled inside the rim (:func:`inside_horizon`)."""
        return inside_horizon(*(np.array([x, y], dtype=np.float64) - self.centre) / self.radius)

    def _inside(self, x: float, y: float) -> bool:
        origin = self.renderer.GetOrigin()  # the renderer's lower left corner in the window
        d = np.array([x - origin[0], y - origin[1]]) - self.centre
        return self._enabled and float(np.hypot(*d)) <= 1.1 * self.radius

    def _take(self, obj, x: float, y: float, tag_index: int) -> None:
        origin = self.renderer.GetOrigin()
        self.on_light(*self.light_at(x - origin[0], y - origin[1]))
        obj.GetCommand(self._tags[tag_index]).SetAbortFlag(1)

    def _press(self, obj, _event) -> None:
        x, y = obj.GetEventPosition()
        if self._inside(x, y):
            self.dragging = True
            self._take(obj, x, y, 0)

    def _move(self, obj, _event) -> None:
        if self.dragging:
            self._take(obj, *obj.GetEventPosition(), 1)

    def _release(self, obj, _event) -> None:
        if self.dragging:
            self.dragging = False
            obj.GetCommand(self._tags[2]).SetAbortFlag(1)

    def remove(self) -> None:
        """Stop taking mouse events (before the interactor goes)."""
        for tag in self._tags:
            self._interactor.RemoveObserver(tag)
        self._tags = []


class ScaleBar:
    """A scale bar in the lower right corner of a renderer with a parallel-projection camera.

    Parameters
    ----------
    renderer : vtkRenderer
    unit : str
        Label unit: ``"mm"``, ``"px"`` or another word.
    """

    def __init__(self, renderer, unit: str) -> None:
        self.renderer = renderer
        self.unit = unit
        self.note = ""
        self.length: float | None = None
        self._bar = _actor2d(_polylines([np.zeros((2, 2))]), _WHITE, width=3.0)
        self.label = _text(_SCALE_FONT, justify_right=True)
        self.actors = [self._bar, self.label]
        for actor in self.actors:
            renderer.AddViewProp(actor)
        # Before each frame: the zoom may have changed.
        renderer.AddObserver("StartEvent", lambda *_: self.update())

    def update(self) -> None:
        """Fit the bar to the current zoom: about a fifth of the view's width."""
        width, height = self.renderer.GetSize()
        camera = self.renderer.GetActiveCamera()
        if height <= 0 or width <= 0:
            return
        per_pixel = 2.0 * camera.GetParallelScale() / height
        self.length = nice_length(0.2 * width * per_pixel)
        pixels = self.length / per_pixel
        right, base = width - _MARGIN - 4, _MARGIN + 4
        tick = 6.0
        lines = [np.array([[right - pixels, base], [right, base]]),
                 np.array([[right - pixels, base - tick], [right - pixels, base + tick]]),
                 np.array([[right, base - tick], [right, base + tick]])]
        self._bar.GetMapper().SetInputData(_polylines(lines))
        self.label.SetInput(f"{self.length:g} {self.unit}{self.note}")
        self.label.SetPosition(right, base + tick + 4)


class ImageStrip:
    """A picture in a viewport along the bottom of the window, the main view above it.

    Parameters
    ----------
    render_window : vtkRenderWindow
    main : vtkRenderer
        The 3-D view, whose viewport shrinks while the strip is shown (to
        :data:`STRIP_FRACTION` of the window's height).
    """

    def __init__(self, render_window, main) -> None:
        from vtkmodules.vtkRenderingCore import vtkActor2D, vtkImageMapper, vtkRenderer

        self.main = main
        self.fraction = STRIP_FRACTION
        self.renderer = vtkRenderer()
        self.renderer.SetViewport(0.0, 0.0, 1.0, self.fraction)
        self.renderer.SetBackground(1.0, 1.0, 1.0)
        self.renderer.InteractiveOff()
        self._mapper = vtkImageMapper()
        self._mapper.SetColorWindow(255.0)
        self._mapper.SetColorLevel(127.5)
        self._actor = vtkActor2D()
        self._actor.SetMapper(self._mapper)
        self.renderer.AddViewProp(self._actor)
        render_window.AddRenderer(self.renderer)
        self.shown = False
        self.set_visible(False)

    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels of the strip."""
        width, height = self.main.GetRenderWindow().GetSize()
        return int(width), max(1, int(round(height * self.fraction)))

    def show(self, image: np.ndarray) -> None:
        """Show an ``(h, w, 3)`` uint8 image (drawn from the strip's lower left corner)."""
        from vtkmodules.util.numpy_support import numpy_to_vtk
        from vtkmodules.vtkCommonDataModel import vtkImageData

        h, w = image.shape[:2]
        data = vtkImageData()
        data.SetDimensions(w, h, 1)
        # VTK images start at the bottom row.
        flat = np.ascontiguousarray(image[::-1].reshape(-1, 3))
        array = numpy_to_vtk(flat, deep=True)
        data.GetPointData().SetScalars(array)
        self._mapper.SetInputData(data)
        self.set_visible(True)

    def set_visible(self, visible: bool) -> None:
        self.shown = bool(visible)
        self.renderer.SetDraw(self.shown)
        self.main.SetViewport(0.0, self.fraction if self.shown else 0.0, 1.0, 1.0)
