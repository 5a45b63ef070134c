"""The preview window as a person uses it: its keys and mouse through an interactor on EGL,
and its event loop on a virtual X display (Xvfb) when one can be started. Key presses change what is drawn, the disk moves the
light and never the camera, `q` ends the event loop and closes the window, and figures carry
a scale bar and no controls."""

import os
import shutil
import subprocess

import numpy as np
import pytest

from data_synthetic import write_capture
from reconstruct.pipeline import RunOptions, run_capture
from reconstruct.viewer.preview import _BACKGROUND, build_plotter
from reconstruct.viewer.scene import load_scene

SIZE = (400, 300)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("window")
    info = write_capture(root / "cap", scene="tablet", shape=(60, 80), n_lights=12, seed=1)
    return load_scene(run_capture(root / "cap", root / "out", RunOptions(pixel_size=info.pixel_size)).output)


@pytest.fixture(scope="module")
def xvfb():
    """A virtual X display for the module's tests; None when Xvfb is not installed."""
    binary = shutil.which("Xvfb")
    if binary is None:
        yield None
        return
    read, write = os.pipe()
    server = subprocess.Popen([binary, "-displayfd", str(write), "-screen", "0", "1024x768x24", "-nolisten", "tcp"],
                              pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    with os.fdopen(read) as f:
        number = f.readline().strip()
    try:
        yield f":{number}" if number else None
    finally:
        server.terminate()
        server.wait(timeout=10)


@pytest.fixture
def window(scene, monkeypatch, tmp_path):
    # An interactor on EGL: in this process VTK keeps the window system of the session's
    # first (off-screen) render; the X window is tested in a process of its own below.
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.delenv("DISPLAY", raising=False)
    try:
        w = build_plotter(scene, off_screen=False, size=SIZE, output=tmp_path)
    except RuntimeError as exc:
        pytest.skip(f"no OpenGL context: {exc}")
    w.plotter.show(auto_close=False, interactive_update=True)  # returns without an event loop
    yield w
    if not w.closed:
        w.close()


def press(w, key):
    interactor = w.plotter.iren.interactor
    interactor.SetKeyCode(key if len(key) == 1 else "\0")
    interactor.SetKeySym(key)
    interactor.KeyPressEvent()
    interactor.CharEvent()
    interactor.KeyReleaseEvent()


def _differ(a, b) -> float:
    return float(np.abs(a.astype(int) - b).mean())


def _camera(w):
    return tuple(w.plotter.camera_position), w.plotter.camera.parallel_scale


def test_keys_change_what_is_drawn_and_never_the_camera(window):
    w = window
    first = w.screenshot()
    camera = _camera(w)
    for key in ("Left", "Left", "Down"):
        press(w, key)
    moved = w.screenshot()
    assert _differ(moved, first) > 1
    assert _camera(w) == camera  # pyvista's Up/Down zoom is unbound
    press(w, "6")
    assert w.mode == "specular" and _differ(w.screenshot(), moved) > 1
    press(w, "8")
    relief = w.screenshot()
    press(w, "plus")
    press(w, "plus")
    assert w.style.exaggeration == 3 and _differ(w.screenshot(), relief) > 0.5
    press(w, "7")
    before = w.screenshot()
    press(w, "bracketright")
    assert w.style.gain == 2.5 and _differ(w.screenshot(), before) > 0.2
    press(w, "5")  # no scan here: it says so in the window
    assert w.mode == "diffuse-gain" and "no distance view" in w.message
    assert "no distance view" in w._status.GetText(w._status.UpperRight)


def test_dragging_the_disk_moves_the_light_not_the_camera(window):
    w = window
    interactor = w.plotter.iren.interactor
    origin = np.array(w.plotter.renderer.GetOrigin()[:2])

    def drag(start, end):
        for event, (x, y) in (("LeftButtonPressEvent", start), ("MouseMoveEvent", end),
                              ("LeftButtonReleaseEvent", end)):
            interactor.SetEventInformation(int(x), int(y))
            interactor.InvokeEvent(event)

    camera = _camera(w)
    c, r = w.disk.centre + origin, w.disk.radius
    drag(c, c + (r * 0.5, 0))  # to the right, half way to the horizon: elevation 60°
    assert w.azimuth == pytest.approx(0, abs=2) and w.elevation == pytest.approx(60, abs=2)
    assert _camera(w) == camera
    # The same drag beside the disk turns the camera: the disk took its events.
    far = np.array(SIZE) / 2
    drag(far, far + (60, 0))
    assert _camera(w) != camera


_Q_SCRIPT = """
import json, sys
from reconstruct.viewer.preview import build_plotter
from reconstruct.viewer.scene import load_scene

w = build_plotter(load_scene(sys.argv[1]), size=(400, 300), output=sys.argv[2])
timed_out = []

def tick(step):
    interactor = w.plotter.iren.interactor
    if step == 1:
        interactor.SetKeyCode("q")
        interactor.SetKeySym("q")
        interactor.KeyPressEvent()
        interactor.CharEvent()
        interactor.KeyReleaseEvent()
    elif step >= 40:  # 8 s: q did not end the loop
        timed_out.append(step)
        interactor.SetDone(True)

w.plotter.add_timer_event(max_steps=41, duration=200, callback=tick)
window_class = w.plotter.ren_win.GetClassName()
w.plotter.show()  # the event loop; returns when it ends
print(json.dumps({"class": window_class, "timed_out": bool(timed_out), "closed": w.closed,
                  "window_gone": w.plotter.render_window is None}))
"""


def test_q_ends_the_event_loop_and_closes_the_window(scene, xvfb, tmp_path):
    # In a process of its own: VTK keeps the first window system it found (EGL, for the
    # off-screen renders of this session) for every later window of the process.
    import json
    import sys

    if not xvfb:
        pytest.skip("needs Xvfb (tools/system-libs.sh installs it) for a real window and event loop")
    env = {**os.environ, "DISPLAY": xvfb}
    env.pop("WAYLAND_DISPLAY", None)
    done = subprocess.run([sys.executable, "-c", _Q_SCRIPT, str(scene.folder), str(tmp_path)],
                          env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result == {"class": "vtkXOpenGLRenderWindow", "timed_out": False, "closed": True,
                      "window_gone": True}


def test_figures_have_a_scale_bar_and_no_controls(window):
    w = window
    w.toggle_help()
    shown = w.screenshot()
    figure = w.figure()
    background = np.round(np.array(_BACKGROUND) * 255)
    top = slice(0, SIZE[1] // 5)
    # The help (top left) and status (top right) are in the window, not in the figure.
    assert (np.abs(shown[top].astype(int) - background).max(axis=-1) > 40).sum() > 100
    assert (np.abs(figure[top].astype(int) - background).max(axis=-1) > 40).sum() == 0
    # The scale bar: a white line of a round length in the lower right corner.
    length = w.scale_bar.length
    assert length in {m * 10.0 ** k for m in (1, 2, 5) for k in range(-3, 4)}
    per_pixel = 2 * w.plotter.camera.parallel_scale / SIZE[1]
    corner = figure[-40:, SIZE[0] // 2:]
    white = (corner.min(axis=-1) > 230).sum(axis=1)
    assert abs(white.max() - length / per_pixel) <= 3
    assert w.scale_bar.label.GetInput().startswith(f"{length:g} mm")
    # The light marker is drawn in the lit views, not in the albedo.
    assert w.disk.label.GetVisibility() and "azimuth" in w.disk.label.GetInput()
    w.set_mode("albedo")
    assert not w.disk.label.GetVisibility()
