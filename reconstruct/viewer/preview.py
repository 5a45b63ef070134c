"""``reconstruct preview``: a pyvista window on a reconstruction, relit live.

The arrays come from :mod:`reconstruct.viewer.scene`; this module puts them in a VTK scene
and wires the controls. :func:`build_plotter` returns a :class:`PreviewWindow` whose methods
are the window's callbacks (``on_light``, ``set_mode``, ``on_pick``, ``reset_view``,
``save_screenshot``, ``toggle_help``, ``toggle_profile``), so they run the same off-screen,
in scripts and tests, as behind the sliders, mouse and keys.

Relighting writes the new colours into the texture's VTK image in place and marks it modified:
only the texture is uploaded again, the mesh and its actor stay as they are.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from ptmcore.errors import InputError
from ptmcore.relight import light_direction
from reconstruct.report import rendering
from reconstruct.viewer.scene import (
    MODES,
    PreviewScene,
    distance,
    mode_colors,
    profile,
)
from reconstruct.report.figures import finite_range

__all__ = ["PreviewWindow", "build_plotter", "has_display", "render_screenshot"]

DEFAULT_AZIMUTH = 135.0  # light from the top left, as relief is usually photographed
DEFAULT_ELEVATION = 40.0
PROFILE_SAMPLES = 400

HELP = """\
1 to 5: relit, albedo, normals, height, distance
arrows: move the light (azimuth, elevation)
right click: pick a point; two give a distance
m: measure a distance or a height profile
s: screenshot (PNG named after the source)
r: reset the view
h: this help
q: quit"""

_BACKGROUND = (0.16, 0.16, 0.18)
# Scale bars lie along the bottom, where the light sliders are in the relit mode (which has
# no scale bar); the profile plot sits above them on the right, the status at the top right.
_BAR = {"vertical": False, "position_x": 0.25, "position_y": 0.02, "width": 0.5, "height": 0.09}
_TEXT = "white"


def has_display() -> bool:
    """Whether a window can be opened: always on Windows and macOS, with an X11 or Wayland
    display elsewhere."""
    if sys.platform in ("win32", "darwin"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class PreviewWindow:
    """A pyvista plotter showing a :class:`PreviewScene`, and the callbacks of its controls.

    Build it with :func:`build_plotter`. Attributes worth reading after a callback:
    ``mode``, ``azimuth``, ``elevation``, ``colors`` (the colour array the GPU shows, a view
    of VTK's memory), ``last_distance`` and ``last_profile``.
    """

    def __init__(self, scene: PreviewScene, *, off_screen: bool, size: tuple[int, int],
                 mode: str | None, azimuth: float, elevation: float) -> None:
        import pyvista as pv

        self.scene = scene
        self.azimuth, self.elevation = float(azimuth), float(elevation)
        self._light()  # checks the angles before anything is built
        self.picks: list[np.ndarray] = []
        self.profile_mode = False
        self.help_shown = False
        self.last_distance: float | None = None
        self.last_profile: tuple[np.ndarray, np.ndarray] | None = None
        self._chart = None
        self._screenshots = 0
        self.mode = mode or scene.modes[0]

        plotter = rendering.plotter(size, off_screen=off_screen)
        self.plotter = plotter
        plotter.set_background(_BACKGROUND)
        plotter.enable_parallel_projection()

        mesh = pv.PolyData.from_regular_faces(scene.vertices, scene.faces)
        self._actors: dict[str, object] = {}
        self._bars: dict[str, str] = {}
        self._add_colour_actor(pv, mesh)
        self._add_scalar_actors(mesh)

        self._status = plotter.add_text("", position="upper_right", font_size=9, color=_TEXT)
        self._help = plotter.add_text("h: help", position="upper_left", font_size=9, color=_TEXT)
        self._light_sliders = []
        if "relit" in scene.modes:
            self._add_light_sliders()
        if plotter.iren is not None:
            self._bind_keys()

        self.set_mode(self.mode)
        self.reset_view()

    # --- building -----------------------------------------------------------------------

    def _add_colour_actor(self, pv, mesh) -> None:
        scene = self.scene
        colour_modes = [m for m in scene.modes if m in ("relit", "albedo", "normals")]
        if not colour_modes:
            self.colors = None
            return
        first = mode_colors(scene, colour_modes[0], self._light())
        surface = mesh.copy(deep=False)
        if scene.uv is not None:
            h, w = first.shape[:2]
            # VTK images start at the bottom row; storing the texture's rows top-first and
            # flipping v instead saves a copy of the image on every relight.
            surface.active_texture_coordinates = np.column_stack([scene.uv[:, 0], 1.0 - scene.uv[:, 1]])
            image = pv.ImageData(dimensions=(w, h, 1))
            image.point_data["colors"] = first.reshape(-1, 3)
            self._image = image
            self.colors = image.point_data["colors"]
            texture = pv.Texture(image)
            texture.interpolate = True
            actor = self.plotter.add_mesh(surface, texture=texture, lighting=False, name="colour")
        else:
            surface.point_data["colors"] = np.ascontiguousarray(first)
            self._image = surface
            self.colors = surface.point_data["colors"]
            actor = self.plotter.add_mesh(surface, scalars="colors", rgb=True, lighting=False, name="colour")
        self._actors.update({m: actor for m in colour_modes})

    def _add_scalar_actors(self, mesh) -> None:
        scene = self.scene
        unit = scene.unit
        if "height" in scene.modes:
            surface = mesh.copy(deep=False)
            surface.point_data["height"] = scene.vertices[:, 2]
            clim = finite_range(scene.vertices[:, 2])
            title = f"height ({unit})"
            self._actors["height"] = self.plotter.add_mesh(
                surface, scalars="height", cmap="viridis", clim=clim,
                smooth_shading=True, ambient=0.3, diffuse=0.7, name="height",
                scalar_bar_args={"title": title, "color": _TEXT, "fmt": "%.3g", **_BAR},
            )
            self._bars["height"] = title
        if "distance" in scene.modes:
            from reconstruct.compare.figures import NAN_COLOR, distance_lookup_table

            limit = float(scene.distance_limit)
            surface = mesh.copy(deep=False)
            surface.point_data["distance"] = scene.vertex_distance
            title = "distance to scan (mm)"
            self._actors["distance"] = self.plotter.add_mesh(
                surface, scalars="distance", cmap=distance_lookup_table(limit), clim=(-limit, limit),
                nan_color=tuple(c / 255 for c in NAN_COLOR), lighting=False, name="distance",
                scalar_bar_args={"title": title, "color": _TEXT, "fmt": "%.3g", **_BAR},
            )
            self._bars["distance"] = title

    def _add_light_sliders(self) -> None:
        common = {"style": "modern", "interaction_event": "always", "color": _TEXT, "fmt": "%.0f°"}
        self._light_sliders = [
            self.plotter.add_slider_widget(
                lambda v: self.on_light(v, self.elevation), (0.0, 360.0), value=self.azimuth,
                title="light azimuth", pointa=(0.03, 0.14), pointb=(0.3, 0.14), **common),
            self.plotter.add_slider_widget(
                lambda v: self.on_light(self.azimuth, v), (1.0, 90.0), value=self.elevation,
                title="light elevation", pointa=(0.33, 0.14), pointb=(0.6, 0.14), **common),
        ]

    def _bind_keys(self) -> None:
        plotter = self.plotter
        # VTK's own one-letter keys (w wireframe, 3 stereo, e exit...) would fight ours.
        plotter.iren.interactor.RemoveObservers("CharEvent")
        plotter.add_key_event("s", lambda: self.save_screenshot())
        plotter.add_key_event("r", self.reset_view)
        plotter.add_key_event("h", self.toggle_help)
        plotter.add_key_event("m", self.toggle_profile)
        for k, name in enumerate(MODES, start=1):
            plotter.add_key_event(str(k), lambda name=name: name in self.scene.modes and self.set_mode(name))
        for key, (da, de) in {"Left": (-15, 0), "Right": (15, 0), "Up": (0, 5), "Down": (0, -5)}.items():
            plotter.add_key_event(key, lambda da=da, de=de: self._nudge_light(da, de))
        plotter.enable_point_picking(callback=self.on_pick, show_message=False, show_point=False,
                                     left_clicking=False, picker="cell")

    # --- callbacks ----------------------------------------------------------------------

    def _light(self) -> np.ndarray:
        return light_direction(azimuth_deg=self.azimuth, elevation_deg=self.elevation)

    def _show_colours(self, colours: np.ndarray) -> None:
        self.colors[:] = colours.reshape(-1, 3)
        self.colors.VTKObject.Modified()
        self._image.Modified()

    def _nudge_light(self, d_azimuth: float, d_elevation: float) -> None:
        self.on_light((self.azimuth + d_azimuth) % 360, min(90.0, max(1.0, self.elevation + d_elevation)))
        self.plotter.render()

    def on_light(self, azimuth: float, elevation: float) -> None:
        """Move the light (degrees) and, in the relit mode, relight the texture.

        It does not render: the slider's interaction renders after its callback, and
        :meth:`screenshot` renders.
        """
        self.azimuth, self.elevation = float(azimuth) % 360.0, float(elevation)
        for slider, value in zip(self._light_sliders, (self.azimuth, self.elevation)):
            slider.GetRepresentation().SetValue(value)
        if self.mode == "relit":
            self._show_colours(mode_colors(self.scene, "relit", self._light()))
        self._update_status()

    def set_mode(self, name: str) -> None:
        """Show one view mode (see :data:`reconstruct.viewer.scene.MODES`)."""
        if name not in self.scene.modes:
            raise ValueError(f"{self.scene.name} has no {name} view; it has {', '.join(self.scene.modes)}")
        self.mode = name
        shown = self._actors[name]
        for actor in self._actors.values():
            actor.SetVisibility(actor is shown)
        for mode, title in self._bars.items():
            self.plotter.scalar_bars[title].SetVisibility(mode == name)
        for slider in self._light_sliders:
            slider.SetEnabled(name == "relit")
        if name in ("relit", "albedo", "normals"):
            self._show_colours(mode_colors(self.scene, name, self._light()))
        self._update_status()
        self.plotter.render()

    def on_pick(self, point, *_: object) -> None:
        """Add a picked surface point; every second one measures a distance, or in profile
        mode draws the height profile between the two."""
        p = np.asarray(point, dtype=np.float64).reshape(3)
        self.picks = (self.picks + [p])[-2:] if len(self.picks) < 2 else [p]
        self.plotter.add_points(np.array(self.picks), color="yellow", point_size=10,
                                render_points_as_spheres=True, name="picks", reset_camera=False)
        if len(self.picks) < 2:
            self.plotter.remove_actor("measure", render=False)
            self._update_status()
            return
        p0, p1 = self.picks
        # Drawn as the path on the surface, slightly lifted towards the camera: the straight
        # chord would pass under the bumps between the two points and vanish.
        along, heights = profile(self.scene, p0, p1, PROFILE_SAMPLES)
        t = along / along[-1] if along[-1] > 0 else np.linspace(0, 1, len(along))
        chord = p0 + t[:, None] * (p1 - p0)
        path = chord.copy()
        path[:, 2] = np.where(np.isfinite(heights), heights, chord[:, 2]) + 0.005 * self.plotter.length
        self.plotter.add_lines(np.repeat(path, 2, axis=0)[1:-1], color="yellow", width=3, name="measure")
        if self.profile_mode:
            self.last_profile = along, heights
            self._draw_profile(*self.last_profile)
        else:
            self.last_distance = distance(p0, p1)
        self._update_status()

    def toggle_profile(self) -> None:
        """Switch the two-point measurement between a distance and a height profile."""
        self.profile_mode = not self.profile_mode
        self.picks = []
        self.plotter.remove_actor(["picks", "measure"], render=False)
        if not self.profile_mode and self._chart is not None:
            self._chart.visible = False
        self._update_status()

    def _draw_profile(self, along: np.ndarray, heights: np.ndarray) -> None:
        import pyvista as pv

        unit = self.scene.unit
        if self._chart is None:
            self._chart = pv.Chart2D(size=(0.36, 0.34), loc=(0.62, 0.16), x_label=f"along the line ({unit})",
                                     y_label=f"height ({unit})")
            self._chart.background_color = (1.0, 1.0, 1.0, 0.85)
            self.plotter.add_chart(self._chart)
        self._chart.clear()
        self._chart.visible = True
        known = np.isfinite(heights)
        if known.sum() >= 2:
            self._chart.line(along[known], heights[known], color="b", width=2.0)
            depth = float(np.ptp(heights[known]))
            self._chart.title = f"height profile (range {depth:.3g} {unit})"
        else:
            self._chart.title = "height profile: the line misses the object"

    def toggle_help(self) -> None:
        """Show or hide the list of keys."""
        self.help_shown = not self.help_shown
        self._help.SetText(self._help.UpperLeft, HELP if self.help_shown else "h: help")
        self.plotter.render()

    def reset_view(self) -> None:
        """Look at the whole object from the camera's side, as the photographs do."""
        self.plotter.view_xy()
        self.plotter.reset_camera()
        self.plotter.render()

    def _update_status(self) -> None:
        unit = self.scene.unit
        lines = [f"{self.scene.name}: {self.mode}"]
        if self.mode == "relit":
            lines.append(f"light azimuth {self.azimuth:.0f}°, elevation {self.elevation:.0f}°")
        lines.append("measure: " + ("height profile" if self.profile_mode else "distance") + " (m to switch)")
        if len(self.picks) == 2 and not self.profile_mode and self.last_distance is not None:
            lines.append(f"distance {self.last_distance:.4g} {unit}")
        elif len(self.picks) == 1:
            lines.append("pick a second point")
        # Setting the text does not render (add_text would, at every slider step).
        self._status.SetText(self._status.UpperRight, "\n".join(lines))

    def screenshot(self) -> np.ndarray:
        """The current image, ``(H, W, 3)`` uint8."""
        self.plotter.render()
        return np.ascontiguousarray(self.plotter.screenshot(return_img=True)[..., :3])

    def save_screenshot(self, path: str | os.PathLike | None = None) -> Path:
        """Write the current image as PNG (atomically); by default ``<source>_preview.png``
        in the working folder, numbered when it exists. Returns the path."""
        from reconstruct.viewer.relighting import write_image

        if path is None:
            while True:
                suffix = f"_{self._screenshots}" if self._screenshots else ""
                path = Path.cwd() / f"{self.scene.name}_preview{suffix}.png"
                self._screenshots += 1
                if not path.exists():
                    break
        path = Path(path)
        write_image(path, self.screenshot())
        self.plotter.add_text(f"saved {path.name}", position="lower_right", font_size=9, color=_TEXT,
                              name="saved")
        return path

    def close(self) -> None:
        self.plotter.close()


def build_plotter(
    scene: PreviewScene,
    *,
    off_screen: bool = False,
    size: tuple[int, int] = (1280, 900),
    mode: str | None = None,
    azimuth: float = DEFAULT_AZIMUTH,
    elevation: float = DEFAULT_ELEVATION,
) -> PreviewWindow:
    """Build the preview window (not shown yet: call ``window.plotter.show()``).

    Parameters
    ----------
    scene : PreviewScene
    off_screen : bool
        Render without a window (EGL or OSMesa where there is no display).
    size : tuple of int
        ``(width, height)`` in pixels.
    mode : str, optional
        First view mode (default: the first the scene has: relit when it can be relit).
    azimuth, elevation : float
        Light direction in degrees.

    Raises
    ------
    ValueError
        For a mode the scene does not have or a light below the horizon.
    RuntimeError
        If rendering is not available.
    """
    if mode is not None and mode not in scene.modes:
        raise ValueError(f"{scene.name} has no {mode} view; it has {', '.join(scene.modes)}")
    return PreviewWindow(scene, off_screen=off_screen, size=size, mode=mode, azimuth=azimuth, elevation=elevation)


def render_screenshot(
    scene: PreviewScene,
    path: str | os.PathLike,
    *,
    mode: str | None = None,
    azimuth: float = DEFAULT_AZIMUTH,
    elevation: float = DEFAULT_ELEVATION,
    size: tuple[int, int] = (1280, 900),
) -> Path:
    """Render the preview off-screen to a PNG and close it (for scripts and tests).

    Raises
    ------
    InputError
        For a mode the scene lacks, or when this machine cannot render off-screen.
    """
    try:
        window = build_plotter(scene, off_screen=True, size=size, mode=mode, azimuth=azimuth, elevation=elevation)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    except RuntimeError as exc:
        raise InputError(f"{exc}; install Mesa's EGL or OSMesa (make install does)") from None
    try:
        return window.save_screenshot(path)
    finally:
        window.close()
