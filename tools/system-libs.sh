#!/usr/bin/env bash
# Install the Debian libraries that the Python wheels of open3d and VTK load at import time
# but do not ship (open3d's wheel needs libusb-1.0-0, for example), and Mesa's EGL/OSMesa
# when off-screen rendering does not work (see the end). It imports each module,
# reads the name of a missing shared library from the error, installs the package that holds
# it, and tries again. Needs root for apt-get; otherwise it says what to install.
set -u
python=${1:-.venv/bin/python}
declare -A pkg=(
  [libusb-1.0.so.0]=libusb-1.0-0 [libgomp.so.1]=libgomp1 [libGL.so.1]=libgl1
  [libEGL.so.1]=libegl1 [libOSMesa.so.8]=libosmesa6 [libX11.so.6]=libx11-6
  [libXrender.so.1]=libxrender1 [libXext.so.6]=libxext6 [libXcursor.so.1]=libxcursor1
  [libXfixes.so.3]=libxfixes3 [libXi.so.6]=libxi6 [libxcb.so.1]=libxcb1
  [libudev.so.1]=libudev1 [libglib-2.0.so.0]=libglib2.0-0 [libsm.so.6]=libsm6
)
updated=0
for module in open3d vtk; do
  for _ in 1 2 3 4 5 6; do
    err=$("$python" -c "import $module" 2>&1) && break
    lib=$(printf '%s\n' "$err" | grep -o 'lib[A-Za-z0-9_.+-]*\.so[.0-9]*' | head -n 1)
    deb=${pkg[$lib]:-}
    if [ -z "$lib" ] || [ -z "$deb" ]; then
      printf 'cannot import %s:\n%s\n' "$module" "$err" >&2; exit 1
    fi
    if [ "$(id -u)" != 0 ]; then
      echo "$module needs the Debian package $deb ($lib): run 'sudo apt-get install $deb'" >&2; exit 1
    fi
    if [ "$updated" = 0 ]; then apt-get update -qq >/dev/null && updated=1; fi
    echo "installing $deb (needed by $module for $lib)"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$deb" >/dev/null || exit 1
  done
done

# Off-screen rendering (reconstruct preview --screenshot, compare's overlay.png) needs an
# OpenGL context without a display: VTK falls back to EGL, then OSMesa, both with Mesa's
# software rasteriser. Render a sphere in a separate process (a missing driver may crash it)
# and install Mesa's libraries when that fails. VTK_DEFAULT_OPENGL_WINDOW is left alone: set
# to an empty string it crashes VTK.
render_check='
import pyvista as pv
plotter = pv.Plotter(off_screen=True, window_size=(64, 48))
ok = bool(plotter.ren_win.SupportsOpenGL())
if ok:
    plotter.add_mesh(pv.Sphere())
    ok = float(plotter.screenshot(return_img=True).std()) > 0
plotter.close()
raise SystemExit(0 if ok else 1)
'
mesa="libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6"
if ! "$python" -c "$render_check" >/dev/null 2>&1; then
  if [ "$(id -u)" != 0 ]; then
    # Only the preview and compare's overlay.png need it: say so, but do not stop the install.
    echo "off-screen rendering does not work here: run 'sudo apt-get install $mesa'" >&2
    exit 0
  fi
  if [ "$updated" = 0 ]; then apt-get update -qq >/dev/null && updated=1; fi
  echo "installing $mesa (off-screen rendering with Mesa's software rasteriser)"
  # shellcheck disable=SC2086  # one word per package
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $mesa >/dev/null || exit 1
  if ! "$python" -c "$render_check" >/dev/null 2>&1; then
    echo "off-screen rendering still fails after installing $mesa:" >&2
    "$python" -c "$render_check" >&2
  fi
fi

# The preview window's tests run its event loop on a virtual X display (Xvfb); without it
# they skip that test.
if ! command -v Xvfb >/dev/null 2>&1; then
  if [ "$(id -u)" != 0 ]; then
    echo "the preview window's event-loop test needs Xvfb: run 'sudo apt-get install xvfb'" >&2
    exit 0
  fi
  if [ "$updated" = 0 ]; then apt-get update -qq >/dev/null && updated=1; fi
  echo "installing xvfb (a virtual display for the preview window's tests)"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq xvfb >/dev/null || exit 1
fi
