"""``reconstruct preview``: a pyvista window on a reconstruction, relit live.

The arrays come from :mod:`reconstruct.viewer.scene`; this module puts them in a VTK scene
and wires the controls. :func:`build_plotter` returns a :class:`PreviewWindow` whose methods
are the window's callbacks (``on_light``, ``move_light``, ``set_mode``, ``on_pick``,
``set_exaggeration``, ``export_measurement``, ``save_screenshot``, ``toggle_help``,
``toggle_profile``, ``quit``), so they run the same off-screen, in scripts and tests, as
behind the mouse and keys (:mod:`reconstruct.viewer.keys` lists them).

The light is moved by the arrow keys, in the direction they point as seen, and by dragging
on the hemisphere disk (:class:`reconstruct.viewer.overlays.LightDisk`); pyvista's and VTK's
own keys are unbound, so nothing but the mouse in the view moves the camera. Relighting
writes the new colours into the texture's VTK image in place and marks it modified: only the
texture is uploaded again, the mesh and its actor stay as they are.

Figures (``s``, ``--screenshot``) are the view alone with a scale bar (mm, or pixels without
a pixel size) and, in the lit views, the light's direction on the disk: no text, help or
profile strip. They, and exported measurements, go into ``preview/`` in the result's folder.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from ptmcore.errors import InputError
from ptmcore.relight import light_direction
from reconstruct.report import rendering
from reconstruct.report.figures import finite_range
from reconstruct.viewer.keys import help_text
from reconstruct.viewer.measurements import Measurement
from reconstruct.viewer.overlays import ImageStrip, LightDisk, ScaleBar, inside_horizon
from reconstruct.viewer.scene import (
    COLOUR_MODES,
    LIT_MODES,
    MODES,
    PreviewScene,
    Style,
    distance,
    mode_colors,
    profile,
)

__all__ = ["PreviewWindow", "build_plotter", "has_display", "render_screenshot"]

DEFAULT_AZIMUTH = 135.0  # light from the top left, as relief is usually photographed
DEFAULT_ELEVATION = 40.0
PROFILE_SAMPLES = 400
#: How far one arrow key moves the light's projection on the image plane (the disk's radius is 1).
LIGHT_STEP = 0.1
#: The vertical exaggerations that + and - step through.
EXAGGERATIONS = (1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 50.0)
#: Limits of diffuse gain (RTIViewer's slider) and of the specular exponent, and the factor
#: [ and ] change them by.
GAIN_RANGE = (1.0, 10.0)
EXPONENT_RANGE = (1.0, 150.0)
PARAMETER_STEP = 1.25
#: Size of an exported profile figure, pixels.
PROFILE_PNG = (1200, 500)
#: The widest or tallest window or figure, pixels: OpenGL's viewport limit on common GPUs.
MAX_SIDE = 16384
#: The most pixels a window or figure has: rendering one takes about 70 bytes per pixel (Mesa's
#: software rasteriser: 4.7 GB at 8192×8192, 9.5 GB at 16384×16384); 100000×100000 aborted the
#: process inside VTK.
MAX_PIXELS = 8192 * 8192

_BACKGROUND = (0.16, 0.16, 0.18)
# Colour bars stand on the right edge; the light disk is in the lower left corner, the scale
# bar in the lower right, the help at the top left and the status at the top right.
_BAR = {"vertical": True, "position_x": 0.84, "position_y": 0.3, "width": 0.06, "height": 0.5,
        "title_font_size": 14, "label_font_size": 12}
_TEXT = "white"


def has_display() -> bool:
    """Whether a window can be opened: always on Windows and macOS, with an X11 or Wayland
    display elsewhere."""
    if sys.platform in ("win32", "darwin"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _bar_unit(unit: str) -> str:
    return {"mm": "mm", "pixel": "px"}.get(unit, "units")


class PreviewWindow:
    """A pyvista plotter showing a :class:`PreviewScene`, and the callbacks of its controls.

    Build it with :func:`build_plotter`. Attributes worth reading after a callback:
    ``mode``, ``azimuth``, ``elevation``, ``style`` (gain, specular exponent, exaggeration),
    ``colors`` (the colour array the GPU shows, a view of VTK's memory), ``measurement``
    (with ``last_distance`` and ``last_profile`` read from it), ``message`` (the last thing
    said to the user) and ``closed``.
    """

    def __init__(self, scene: PreviewScene, *, off_screen: bool, size: tuple[int, int],
                 mode: str | None, azimuth: float, elevation: float, output: Path | None) -> None:
        import pyvista as pv

        self.scene = scene
        self.style = Style()
        self.output = output
        self.azimuth, self.elevation = float(azimuth) % 360.0, float(elevation)
        light = self._light()  # checks the angles before anything is built
        self.picks: list[np.ndarray] = []
        self.profile_mode = False
        self.help_shown = False
        self.closed = False
        self.message = ""
        #: The last measurement made (what ``e`` exports), whatever was picked since.
        self.measurement: Measurement | None = None
        self.mode = mode or scene.modes[0]

        plotter = rendering.plotter(size, off_screen=off_screen)
        self.plotter = plotter
        plotter.set_background(_BACKGROUND)
        plotter.enable_parallel_projection()

        mesh = pv.PolyData.from_regular_faces(scene.vertices, scene.faces)
        self._actors: dict[str, object] = {}
        self._bars: dict[str, str] = {}
        self._add_colour_actor(pv, mesh, light)
        self._add_scalar_actors(mesh)
        self._add_scene_light(pv)

        self._status = plotter.add_text("", position="upper_right", font_size=9, color=_TEXT)
        self._help = plotter.add_text("h: help", position="upper_left", font_size=9, color=_TEXT)
        renderer = plotter.renderer
        interactor = plotter.iren.interactor if plotter.iren is not None else None
        radius = float(np.clip(0.1 * min(size), 36, 90))
        self.disk = LightDisk(renderer, interactor, radius, self._on_disk)
        self.scale_bar = ScaleBar(renderer, _bar_unit(scene.unit))
        self.strip = ImageStrip(plotter.ren_win, renderer)
        if interactor is not None:
            self._bind_keys()

        self._apply_exaggeration()
        self._aim_light(light)
        self._show_view(self.mode)
        self._update_status()
        self.reset_view()

    @property
    def last_distance(self) -> float | None:
        """The distance last measured (None before one, or when the last was a profile)."""
        m = self.measurement
        return distance(m.p0, m.p1) if m is not None and m.kind == "distance" else None

    @property
    def last_profile(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(along, heights)`` of the profile last measured (None before one, or when the
        last was a distance)."""
        m = self.measurement
        return (m.along, m.heights) if m is not None and m.kind == "profile" else None

    # --- building -----------------------------------------------------------------------

    def _add_colour_actor(self, pv, mesh, light: np.ndarray) -> None:
        scene = self.scene
        colour_modes = [m for m in scene.modes if m in COLOUR_MODES]
        if not colour_modes:
            self.colors = None
            return
        # The first view's colours, computed once here: a scalar first view (height) leaves
        # them hidden until a colour view is chosen, which recolours.
        first = mode_colors(scene, self.mode if self.mode in COLOUR_MODES else colour_modes[0], light, self.style)
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

    def _add_scene_light(self, pv) -> None:
        # The height view is shaded by VTK: one light fixed to the object, the same as the
        # relit texture's, instead of pyvista's light kit that follows the camera.
        self.plotter.remove_all_lights()
        self._scene_light = pv.Light(light_type="scene light")
        self._scene_light.positional = False
        self._scene_light.intensity = 1.0
        self.plotter.add_light(self._scene_light)

    def _bind_keys(self) -> None:
        plotter = self.plotter
        # VTK's own one-letter keys (w wireframe, 3 stereo, e exit...) and pyvista's (Up and
        # Down zoom, q only flags a close, + and - thicken lines...) would fight ours.
        plotter.iren.interactor.RemoveObservers("CharEvent")
        plotter.iren.clear_key_event_callbacks()
        bindings = {
            "q": self.quit, "s": lambda: self.save_screenshot(), "e": lambda: self.export_measurement(),
            "r": self.reset_view, "h": self.toggle_help, "m": self.toggle_profile,
            "Left": lambda: self.move_light(-LIGHT_STEP, 0), "Right": lambda: self.move_light(LIGHT_STEP, 0),
            "Up": lambda: self.move_light(0, LIGHT_STEP), "Down": lambda: self.move_light(0, -LIGHT_STEP),
            "bracketleft": lambda: self.change_parameter(-1), "bracketright": lambda: self.change_parameter(1),
        }
        for key in ("plus", "equal", "KP_Add"):
            bindings[key] = lambda: self.step_exaggeration(1)
        for key in ("minus", "underscore", "KP_Subtract"):
            bindings[key] = lambda: self.step_exaggeration(-1)
        for k, name in enumerate(MODES, start=1):
            bindings[str(k)] = lambda name=name: self.request_mode(name)
        for key, callback in bindings.items():
            plotter.add_key_event(key, callback)
        plotter.enable_point_picking(callback=self.on_pick, show_message=False, show_point=False,
                                     left_clicking=False, picker="cell")

    # --- the light ----------------------------------------------------------------------

    def _light(self) -> np.ndarray:
        return light_direction(azimuth_deg=self.azimuth, elevation_deg=self.elevation)

    def _show_colours(self, colours: np.ndarray) -> None:
        self.colors[:] = colours.reshape(-1, 3)
        self.colors.VTKObject.Modified()
        self._image.Modified()

    def _aim_light(self, light: np.ndarray) -> None:
        """Point the disk's marker and VTK's scene light (the height view's) at `light`."""
        self.disk.set_light(light, self.azimuth, self.elevation)
        centre = np.asarray(self.plotter.center)
        self._scene_light.focal_point = tuple(centre)
        self._scene_light.position = tuple(centre + light * max(self.plotter.length, 1e-6))

    def on_light(self, azimuth: float, elevation: float) -> None:
        """Move the light (degrees) and relight the lit views.

        It does not render: the key and drag callbacks render after it, and
        :meth:`screenshot` renders.
        """
        self.azimuth, self.elevation = float(azimuth) % 360.0, float(elevation)
        light = self._light()
        self._aim_light(light)
        if self.mode in LIT_MODES and self.mode in COLOUR_MODES:
            self._show_colours(mode_colors(self.scene, self.mode, light, self.style))
        self._update_status()

    def _set_projection(self, lu: float, lv: float) -> None:
        r = math.hypot(lu, lv)
        azimuth = math.degrees(math.atan2(lv, lu)) if r > 1e-9 else self.azimuth
        self.on_light(azimuth, math.degrees(math.acos(min(1.0, r))))

    def move_light(self, d_lu: float, d_lv: float) -> None:
        """Move the light's projection on the image plane: (−, 0) to the left as seen,
        (0, +) upwards; it stays inside the horizon (1° up at least). Renders."""
        lu, lv = self._light()[:2]
        self._set_projection(*inside_horizon(lu + d_lu, lv + d_lv))
        self.plotter.render()

    def _on_disk(self, lu: float, lv: float) -> None:
        self._set_projection(lu, lv)
        self.plotter.render()

    # --- views --------------------------------------------------------------------------

    def request_mode(self, name: str) -> None:
        """A view key: switch to `name`, or say in the window why it is not there."""
        if name in self.scene.modes:
            self.set_mode(name)
            return
        why = {"distance": "no comparison with a scan here (reconstruct run --scan, or preview --comparison DIR)",
               "specular": "specular enhancement needs a PTM", "diffuse-gain": "diffuse gain needs a PTM",
               "relief": "relief shading needs a normal map on the texture"}.get(name, "")
        self._say(f"no {name} view: {why}" if why else f"no {name} view for this source")
        self.plotter.render()

    def set_mode(self, name: str) -> None:
        """Show one view mode (see :data:`reconstruct.viewer.scene.MODES`)."""
        if name not in self.scene.modes:
            raise ValueError(f"{self.scene.name} has no {name} view; it has {', '.join(self.scene.modes)}")
        self.mode = name
        self.message = ""
        self._show_view(name)
        if name in COLOUR_MODES:
            self._show_colours(mode_colors(self.scene, name, self._light(), self.style))
        self._update_status()
        self.plotter.render()

    def _show_view(self, name: str) -> None:
        """Show the actor, colour bar and light disk of view `name`, and hide the others'."""
        shown = self._actors[name]
        for actor in self._actors.values():
            actor.SetVisibility(actor is shown)
        for mode, title in self._bars.items():
            self.plotter.scalar_bars[title].SetVisibility(mode == name)
        self.disk.set_visible(name in LIT_MODES)

    def set_exaggeration(self, factor: float) -> None:
        """Scale the heights shown (mesh and relief shading) by `factor`; measurements stay
        in true heights. Renders."""
        if not (math.isfinite(factor) and factor > 0):
            raise ValueError(f"the vertical exaggeration must be a positive number, not {factor}")
        self.style = replace(self.style, exaggeration=float(factor))
        self._apply_exaggeration()
        if self.mode == "relief":
            self._show_colours(mode_colors(self.scene, "relief", self._light(), self.style))
        self._update_status()
        self.plotter.render()

    def step_exaggeration(self, step: int) -> None:
        """The next larger (`step` > 0) or smaller vertical exaggeration of :data:`EXAGGERATIONS`."""
        now = self.style.exaggeration
        if step > 0:
            factor = next((e for e in EXAGGERATIONS if e > now), EXAGGERATIONS[-1])
        else:
            factor = next((e for e in reversed(EXAGGERATIONS) if e < now), EXAGGERATIONS[0])
        self.set_exaggeration(factor)

    def _apply_exaggeration(self) -> None:
        e = self.style.exaggeration
        for actor in self._scaled_actors():
            actor.SetScale(1.0, 1.0, e)
        self.scale_bar.note = f"  (heights ×{e:g})" if e != 1 else ""
        self.plotter.renderer.ResetCameraClippingRange()

    def _scaled_actors(self) -> list:
        actors = {id(a): a for a in self._actors.values()}
        for name in ("picks", "measure"):
            if name in self.plotter.actors:
                actors[id(self.plotter.actors[name])] = self.plotter.actors[name]
        return list(actors.values())

    def change_parameter(self, step: int) -> None:
        """``[`` and ``]``: the diffuse gain in its view, the highlight's size (the specular
        exponent, inversely) in the specular view. Renders."""
        factor = PARAMETER_STEP ** step
        if self.mode == "diffuse-gain":
            gain = float(np.clip(round(self.style.gain * factor, 2), *GAIN_RANGE))
            self.style = replace(self.style, gain=gain)
        elif self.mode == "specular":
            exponent = float(np.clip(round(self.style.exponent / factor, 1), *EXPONENT_RANGE))
            self.style = replace(self.style, exponent=exponent)
        else:
            self._say("[ and ] change the diffuse gain or the specular highlight, in those views (7, 6)")
            self.plotter.render()
            return
        self._show_colours(mode_colors(self.scene, self.mode, self._light(), self.style))
        self._update_status()
        self.plotter.render()

    # --- measuring ----------------------------------------------------------------------

    def on_pick(self, point, *_: object) -> None:
        """Add a picked surface point (as drawn: its height divided by the exaggeration);
        every second one measures a distance, or in profile mode draws the height profile
        between the two in a strip below the view. Renders."""
        p = np.asarray(point, dtype=np.float64).reshape(3) / (1.0, 1.0, self.style.exaggeration)
        self.picks = (self.picks + [p])[-2:] if len(self.picks) < 2 else [p]
        self.plotter.add_points(np.array(self.picks), color="yellow", point_size=10,
                                render_points_as_spheres=True, name="picks", reset_camera=False)
        if len(self.picks) < 2:
            self.plotter.remove_actor("measure", render=False)
        else:
            self._measure(*self.picks)
        self._apply_exaggeration()
        self._update_status()
        self.plotter.render()

    def _measure(self, p0: np.ndarray, p1: np.ndarray) -> None:
        """Measure between two picks: keep the record (:attr:`measurement`), draw its path,
        and in profile mode its chart in the strip."""
        along, heights = profile(self.scene, p0, p1, PROFILE_SAMPLES)
        # The samples of profile(), evenly spaced from p0 to p1.
        chord = p0 + np.linspace(0.0, 1.0, len(along))[:, None] * (p1 - p0)
        self.measurement = Measurement("profile" if self.profile_mode else "distance", p0, p1, along,
                                       chord[:, :2], heights)
        # Drawn as the path on the surface, slightly lifted towards the camera: the straight
        # chord would pass under the bumps between the two points and vanish.
        path = chord.copy()
        lift = 0.005 * self.plotter.length / self.style.exaggeration
        path[:, 2] = np.where(np.isfinite(heights), heights, chord[:, 2]) + lift
        self.plotter.add_lines(np.repeat(path, 2, axis=0)[1:-1], color="yellow", width=3, name="measure")
        if self.profile_mode:
            from reconstruct.viewer.measurements import profile_figure, rgb_pixels

            self.strip.show(rgb_pixels(profile_figure(along, heights, self.scene.unit, self.strip.size())))

    def toggle_profile(self) -> None:
        """Switch the two-point measurement between a distance and a height profile."""
        self.profile_mode = not self.profile_mode
        self.picks = []
        self.plotter.remove_actor(["picks", "measure"], render=False)
        if not self.profile_mode:
            self.strip.set_visible(False)
        self._update_status()
        self.plotter.render()

    def export_measurement(self, folder: str | os.PathLike | None = None) -> list[Path]:
        """Write the last measurement made (:attr:`measurement`, whatever was picked since)
        into `folder` (default: ``preview/`` in the result's folder): a profile as CSV and
        PNG, a distance as CSV. Returns the files written."""
        from reconstruct.viewer.measurements import export_measurement

        if self.measurement is None:
            self._say("nothing measured yet: right-click two points (m: distance or profile)")
            self.plotter.render()
            return []
        folder = Path(folder) if folder is not None else self._folder()
        written = export_measurement(self.measurement, folder, self.scene.name, self.scene.unit, PROFILE_PNG)
        self._say("exported " + ", ".join(str(p) for p in written))
        self.plotter.render()
        return written

    # --- the window ---------------------------------------------------------------------

    def toggle_help(self) -> None:
        """Show or hide the list of keys."""
        self.help_shown = not self.help_shown
        self._help.SetText(self._help.UpperLeft, help_text() if self.help_shown else "h: help")
        self.plotter.render()

    def reset_view(self) -> None:
        """Look at the whole object from the camera's side, as the photographs do."""
        self.plotter.view_xy()
        self.plotter.reset_camera()
        self.plotter.render()

    def _say(self, message: str) -> None:
        """Show a message in the status (and on the terminal, where the window was opened)."""
        self.message = message
        print(message, flush=True)
        self._update_status()

    def _update_status(self) -> None:
        unit = self.scene.unit
        lines = [f"{self.scene.name}: {self.mode}"]
        if self.style.exaggeration != 1:
            lines.append(f"vertical exaggeration ×{self.style.exaggeration:g} (+/-)")
        if self.mode == "diffuse-gain":
            lines.append(f"diffuse gain {self.style.gain:g} ([ ])")
        elif self.mode == "specular":
            lines.append(f"specular exponent {self.style.exponent:g} ([ ])")
        lines.append("measure: " + ("height profile" if self.profile_mode else "distance") + " (m to switch)")
        if len(self.picks) == 2 and not self.profile_mode and self.last_distance is not None:
            lines.append(f"distance {self.last_distance:.4g} {unit}")
        elif len(self.picks) == 1:
            lines.append("pick a second point")
        if self.message:
            lines.append(self.message)
        # Setting the text does not render (add_text would, at every light step).
        self._status.SetText(self._status.UpperRight, "\n".join(lines))

    def screenshot(self) -> np.ndarray:
        """The current image as the window shows it, ``(H, W, 3)`` uint8."""
        self.plotter.render()
        return np.ascontiguousarray(self.plotter.screenshot(return_img=True)[..., :3])

    def figure(self) -> np.ndarray:
        """The current view as a clean figure, ``(H, W, 3)`` uint8: the object with its
        colour bar, the scale bar and (in the lit views) the light's direction; no help,
        status or profile strip."""
        texts = (self._status, self._help)
        strip = self.strip.shown
        for actor in texts:
            actor.SetVisibility(False)
        self.strip.set_visible(False)
        try:
            return self.screenshot()
        finally:
            for actor in texts:
                actor.SetVisibility(True)
            self.strip.set_visible(strip)
            self.plotter.render()

    def _folder(self) -> Path:
        """Where figures and measurements go: ``preview/`` in the result's folder."""
        return (self.output or Path.cwd()) / "preview"

    def save_screenshot(self, path: str | os.PathLike | None = None) -> Path:
        """Write the current view as a clean figure (:meth:`figure`), PNG, atomically; by
        default ``preview/<source>_<view>.png`` in the result's folder, numbered when it
        exists. Says where. Returns the path."""
        from reconstruct.viewer.measurements import free_paths
        from reconstruct.viewer.relighting import write_image

        path = Path(path) if path is not None else free_paths(self._folder(), f"{self.scene.name}_{self.mode}",
                                                              (".png",))[0]
        write_image(path, self.figure())
        self._say(f"saved {path}")
        self.plotter.render()
        return path

    def quit(self) -> None:
        """End the window's event loop (``q``); ``plotter.show`` then closes the window."""
        self.closed = True
        self.disk.remove()
        if self.plotter.iren is not None:
            # The event loop ends after this event; TerminateApp would also post an X event,
            # which crashes where there is no X display (EGL).
            self.plotter.iren.interactor.SetDone(True)

    def close(self) -> None:
        self.disk.remove()
        self.plotter.close()


def build_plotter(
    scene: PreviewScene,
    *,
    off_screen: bool = False,
    size: tuple[int, int] = (1280, 900),
    mode: str | None = None,
    azimuth: float = DEFAULT_AZIMUTH,
    elevation: float = DEFAULT_ELEVATION,
    output: str | os.PathLike | None = None,
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
    output : path, optional
        The result's folder: figures and measurements go into its ``preview/`` (default:
        the scene's folder, else the working folder).

    Raises
    ------
    ValueError
        For a mode the scene does not have, a light below the horizon, or a size beyond
        :data:`MAX_SIDE` or :data:`MAX_PIXELS`.
    RuntimeError
        If rendering is not available.
    """
    if mode is not None and mode not in scene.modes:
        raise ValueError(f"{scene.name} has no {mode} view; it has {', '.join(scene.modes)}")
    width, height = size
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE and width * height <= MAX_PIXELS):
        raise ValueError(f"a window or figure of {width}×{height} pixels is too large: at most {MAX_SIDE} "
                         f"per side and {MAX_PIXELS / 2**20:g} megapixels")
    folder = Path(output) if output is not None else scene.folder
    return PreviewWindow(scene, off_screen=off_screen, size=size, mode=mode, azimuth=azimuth,
                         elevation=elevation, output=folder)


def render_screenshot(
    scene: PreviewScene,
    path: str | os.PathLike,
    *,
    mode: str | None = None,
    azimuth: float = DEFAULT_AZIMUTH,
    elevation: float = DEFAULT_ELEVATION,
    size: tuple[int, int] = (1280, 900),
) -> Path:
    """Render the preview off-screen to a PNG figure (:meth:`PreviewWindow.figure`) and
    close it (for scripts and tests).

    Raises
    ------
    InputError
        For a mode the scene lacks, a size too large (:func:`build_plotter`), or when this
        machine cannot render off-screen.
    """
    try:
        window = build_plotter(scene, off_screen=True, size=size, mode=mode, azimuth=azimuth,
                               elevation=elevation)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    except RuntimeError as exc:
        raise InputError(f"{exc}; install Mesa's EGL or OSMesa (make install does)") from None
    try:
        from reconstruct.viewer.relighting import write_image

        path = Path(path)
        write_image(path, window.figure())
        return path
    finally:
        window.close()
