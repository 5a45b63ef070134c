"""The ``reconstruct`` command's arguments: one builder per command.

Choices and defaults of the run and comparison options come from
:class:`reconstruct.pipeline.options.RunOptions` and ``CompareOptions`` (:func:`choices`,
:func:`default`), so the command line offers exactly what the Python API accepts.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from ptmcore import __version__
from ptmcore.relight import DEFAULT_EXPONENT, DEFAULT_GAIN, DEFAULT_KD, DEFAULT_KS
from ptmcore.normalmethods import FITS, NORMAL_METHODS
from reconstruct.pipeline.options import BOUNDS, STACK_FILE_MB, CompareOptions, RunOptions, choices, default
from reconstruct.viewer.preview import MAX_PIXELS as PREVIEW_PIXELS, MAX_SIDE as PREVIEW_SIDE
from reconstruct.viewer.relighting import BASES as RELIGHT_BASES, MAX_SWEEP, MODES as RELIGHT_MODES
from reconstruct.viewer.scene import MODES as VIEW_MODES
from reconstruct.viewer.keys import help_text as preview_keys

#: data_synthetic.capture.ENCODINGS' names (tests/test_cli.py checks): importing the renderer
#: for them cost every command a quarter of a second.
DEMO_ENCODINGS = ("tiff16", "jpeg8")
#: data_synthetic.capture.MAX_LIGHTS, for the same reason (tests/test_hostile_values.py checks).
DEMO_MAX_LIGHTS = 1000

DESCRIPTION = """\
Turn reflectance photographs (RTI captures) into surface normals, a height map and a
textured 3D mesh.

A capture is a folder of photographs taken with a fixed camera under different light
directions, plus an .lp file listing, for each photograph, the unit vector towards its light
(x right, y up, z towards the camera).

Start with `reconstruct demo` to see the whole pipeline on a synthetic clay tablet, then
`reconstruct run MY_CAPTURE -o results --pixel-size 0.05`.
"""

RELIGHT_EPILOG = """\
examples:
  reconstruct relight tablet_out --azimuth 135 --elevation 15 -o raking.png
  reconstruct relight old_scan.ptm --light 0.5,0.5,0.7 --mode specular -o shiny.png
  reconstruct relight tablet_out --sweep 36 --elevation 25 -o turntable.gif
"""

RUN_EPILOG = """\
CAPTURE may also be an existing .ptm file: its normals (from the PTM's maximum), height map
and meshes are made from it, no photographs needed.

outputs (in the -o folder; README.md, "Output folder", says more):
  coefficients.ptm           the PTM (HP PTM 1.2, opens in RTIViewer)
  web/                       a relighting page to publish, and the PTM for OpenLIME (LRGB)
  coefficients.rti           with --hsh: HSH order 3 (RTIViewer's .rti)
  normals.npy, normals.png   unit normals (float32) and a 16-bit OpenGL-style normal map
  albedo.png                 the surface colour without shading (8-bit sRGB)
  height.tif                 float32 height map; millimetres with --pixel-size, else pixels
  mesh.ply, mesh.obj         textured mesh (the OBJ with mesh.mtl and mesh_texture.png)
  solid.stl, mesh.glb        with --solid, --glb
  mask.png                   the mask used, when --mask is given (or auto found one)
  loo_*.tif                  with --loo: leave-one-out relighting error of each basis
  light_positions.csv        with near lights: the light positions used (pixels)
  lights.lp                  with spheres and no .lp: the light directions calibrated from them
  report.json                inputs, parameters, timings, memory, warnings, accuracy
  report.html                one self-contained page to read the result
  comparison.json, distances.ply, histogram.png, overlay.png
                             with --scan: the comparison (see `reconstruct compare --help`)
  preview/                   not written by run: what you save from `reconstruct preview`;
                             a later run into the folder keeps it

example:
  reconstruct run tablet/ -o tablet_out --pixel-size 0.04 --normals ps --integrator dct
"""


class _Parser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` that takes a comma list starting with a negative number as
    a value, and reports bad arguments in one line.

    argparse of Python 3.10 to 3.13.0 takes only a plain number such as ``-0.7`` for a value:
    ``--light -0.7,0,0.71`` (every light from the left) failed with "expected one argument".
    CPython's later argparse widens the test to the one used here: a ``-`` followed by a digit,
    or by a point and a digit, is a value. No option of the command looks so, so none is
    hidden. Subparsers are of this class too (``add_subparsers`` makes them with ``type(self)``).
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # Private, but present and used alike from Python 3.10 to 3.14.
        self._negative_number_matcher = re.compile(r"-\.?\d")

    def error(self, message: str) -> NoReturn:
        """One line on stderr and exit status 2, like every other bad input; the usage, many
        lines for ``run``, is what ``--help`` shows."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _path(text: str) -> Path:
    """A path argument; an empty one is refused, as ``Path("")`` is the current folder, which
    the user never meant (``-o ""`` wrote every output file there)."""
    if not text:
        raise argparse.ArgumentTypeError("empty path; give a file or folder name")
    return Path(text)


def _choice(parser: argparse.ArgumentParser, options: type, name: str, **kw) -> None:
    """``--name`` taking the option's own values, with its own default (from the dataclass)."""
    parser.add_argument("--" + name.replace("_", "-"), choices=choices(options, name),
                        default=default(options, name), **kw)


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return v


def _whole(low: int, high: int | None = None) -> Callable[[str], int]:
    """An argument type: a whole number from ``low`` to ``high`` (no upper bound when None).

    The upper bound, where there is one, is the most work or memory the value may ask for:
    ``--sweep 1e8`` asked for a hundred million images.
    """
    def whole(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            # 1e8 is a whole number too, and is checked against the bound like 100000000.
            try:
                f = float(text)
            except ValueError:
                f = math.nan
            if not f.is_integer():
                raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
            v = int(f)
        if v < low or (high is not None and v > high):
            bound = f"at least {low}" if high is None else f"from {low} to {high}"
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text!r}")
        return v

    return whole


_positive_int = _whole(1)


def _size(smallest: int, largest: int | None = None, most_pixels: int | None = None) -> Callable[[str], tuple[int, int]]:
    """An argument type: ``WxH`` in pixels (``X`` also), each side from ``smallest`` to
    ``largest`` and ``W·H`` at most ``most_pixels`` (no bound when None); ``(W, H)``."""
    def size(text: str) -> tuple[int, int]:
        bound = f"at least {smallest}" if largest is None else f"from {smallest} to {largest}"
        try:
            width, height = (int(v) for v in text.lower().split("x"))
            if min(width, height) < smallest or (largest is not None and max(width, height) > largest):
                raise ValueError
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be WxH, both sides {bound} pixels, got {text!r}") from None
        if most_pixels is not None and width * height > most_pixels:
            side = math.isqrt(most_pixels)
            raise argparse.ArgumentTypeError(f"must be WxH of at most {most_pixels:,} pixels ({side}x{side}), got {text!r}")
        return width, height

    return size


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="reconstruct", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--version", action="version", version=f"reconstruct (ptm-reconstruct) {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_run_command(sub)
    _add_batch_command(sub)
    _add_relight_command(sub)
    _add_calibrate_command(sub)
    _add_compare_command(sub)
    _add_integrate_command(sub)
    _add_lights_command(sub)
    _add_check_command(sub)
    _add_demo_command(sub)
    _add_preview_command(sub)
    _add_warm_up_command(sub)
    return parser


def _add_run_command(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser(
        "run",
        help="reconstruct one capture: normals, height map and mesh",
        description="Reconstruct one capture: a folder of photographs with its .lp light file, a "
        "photometric-stereo dataset folder, or an existing .ptm file.",
        epilog=RUN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    run.add_argument("capture", type=_path,
                     help="capture folder (photographs and one .lp file), an .lp file, a .ptm file, or a "
                     "photometric-stereo dataset folder (filenames.txt, light_directions.txt, ...)")
    run.add_argument("-o", "--output", type=_path, required=True, help="output folder (created if needed)")
    _add_run_options(run)


BATCH_EPILOG = """\
outputs (in the -o folder):
  NAME/                      one folder per object, exactly as `reconstruct run` writes it
  batch.csv, batch.json      one row per object: status (done, skipped, failed), error, time,
                             memory, size, height range, accuracy, scan RMS, warnings
  index.html                 a gallery: failures first, then a card per object
  thumbnails/                the gallery's small relit images and height maps
An object named like one of these gets a suffix, as a repeated name does: index.html-2/.

Running the same command again skips the objects whose output is complete and whose
photographs, .lp, mask, scan, other inputs and options have not changed (--force redoes
them).

manifest (--manifest objects.csv): a header row, then one row per object; columns `capture`
(path relative to the CSV), `name`, `scan`, `scan_units`, and any run option by its long name
with underscores (pixel_size, mask, lp, normals, integrator, intrinsics, distance, ...).

exit status: 0 when every object is done or skipped, 1 when any failed, 2 for bad arguments.
See docs/cluster.md to run a batch on several machines.
"""


def _add_batch_command(sub: argparse._SubParsersAction) -> None:
    batch = sub.add_parser(
        "batch",
        help="reconstruct a whole collection, on a local Dask cluster or an existing one",
        description="Reconstruct many captures: capture folders, .lp or .ptm files, or parent folders "
        "whose sub-folders and .ptm files are captures, and/or the rows of a manifest. Each object is "
        "one task on Dask's distributed scheduler; a failure is reported and the others go on.",
        epilog=BATCH_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    batch.add_argument("sources", nargs="*", type=_path, metavar="SOURCE",
                       help="capture folder, .lp or .ptm file, or a folder of captures")
    batch.add_argument("-o", "--output", type=_path, required=True, help="the batch's output folder")
    batch.add_argument("--manifest", type=_path, metavar="CSV", help="one row per object, overriding options")
    batch.add_argument("--workers", type=_positive_int, metavar="N",
                       help="workers of the local cluster (default, and at most: as many as cores and memory allow)")
    batch.add_argument("--scheduler", metavar="ADDRESS",
                       help="run on an existing Dask cluster (tcp://host:8786); workers need the same paths")
    batch.add_argument("--force", action="store_true", help="redo objects that are complete and unchanged")
    _add_run_options(batch)


def _add_relight_command(sub: argparse._SubParsersAction) -> None:
    rel = sub.add_parser(
        "relight",
        help="render a result under a chosen light (its published basis, or a PTM in RTIViewer's modes), "
        "or a GIF of a circling light",
        description="Render a relightable image under any light. SOURCE is an output folder of `reconstruct "
        "run` (by default the relighting basis published in its web/, as its page shows it; else its "
        "coefficients.ptm), a web/ folder or its info.json, or a .ptm or .rti (HSH) file, rendered as "
        "RTIViewer does.",
        epilog=RELIGHT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rel.add_argument("source", type=_path, help="output folder, web/ folder or its info.json, .ptm or .rti file")
    rel.add_argument("-o", "--output", type=_path, required=True, help="image to write (.png, .jpg, .tif; .gif with --sweep)")
    rel.add_argument("--light", metavar="X,Y,Z", help="direction towards the light (x right, y up, z towards the camera)")
    rel.add_argument("--azimuth", type=float, metavar="DEG", help="light azimuth: 0 = from the right, 90 = from the top")
    rel.add_argument("--elevation", type=float, metavar="DEG", help="light elevation above the object (default with --sweep: 30)")
    rel.add_argument("--mode", choices=RELIGHT_MODES, default=RELIGHT_MODES[0],
                     help="default rendering, or RTIViewer's specular enhancement or diffuse gain, which are "
                          "defined on a PTM's polynomial: with an output folder they render its coefficients.ptm "
                          "(a web/ folder alone has none) (default: default)")
    # No defaults here: given with another --mode they would do nothing, which is an error
    # (cli.main); render() holds the defaults.
    rel.add_argument("--kd", type=float, help=f"with --mode specular: diffuse weight (default {DEFAULT_KD:g})")
    rel.add_argument("--ks", type=float, help=f"with --mode specular: specular weight (default {DEFAULT_KS:g})")
    rel.add_argument("--exponent", type=float, help=f"with --mode specular: Phong exponent (default {DEFAULT_EXPONENT:g})")
    rel.add_argument("--gain", type=float, help=f"with --mode diffuse-gain: the gain (default {DEFAULT_GAIN:g})")
    rel.add_argument("--basis", choices=RELIGHT_BASES, default=RELIGHT_BASES[0],
                     help="with an output folder: auto (default) the basis published in its web/ (the one "
                          "`reconstruct run --basis` chose), else its coefficients.ptm; ptm its coefficients.ptm; "
                          "hsh its HSH coefficients.rti")
    rel.add_argument("--sweep", type=_whole(1, MAX_SWEEP), metavar="N",
                     help=f"write an animated GIF of N frames (at most {MAX_SWEEP}) with the light circling the object")


def _add_calibrate_command(sub: argparse._SubParsersAction) -> None:
    cal = sub.add_parser(
        "calibrate",
        help="light directions from glossy spheres in the photographs (highlight RTI): writes an .lp",
        description="Find the black glossy spheres in a capture (or take them from --sphere), read the "
        "highlight on each in every photograph, and write the light directions as an .lp file. "
        "Photographs without a usable highlight are named and left out.",
    )
    cal.add_argument("capture", type=_path, help="folder of photographs")
    cal.add_argument("-o", "--output", type=_path, required=True, help="the .lp file to write")
    cal.add_argument("--sphere", action="append", metavar="X,Y,R",
                     help="a sphere's centre (column, row) and radius in pixels; repeat for several")
    cal.add_argument("--diagnostic", type=_path, metavar="PNG",
                     help="also draw the spheres and highlights on the first photograph, and a polar plot beside it")
    cam = cal.add_argument_group(
        "camera", "the view model of the reflection (default: orthographic, right for long lenses); "
        "with a short lens give one of these")
    cam.add_argument("--focal-mm", type=_positive_float, metavar="F",
                     help="lens focal length in mm (with --sensor-width-mm)")
    cam.add_argument("--sensor-width-mm", type=_positive_float, metavar="W",
                     help="width of the sensor area the photographs cover, in mm (with --focal-mm)")
    cam.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="pinhole camera in pixels")
    cam.add_argument("--exif", action="store_true",
                     help="read the focal length and sensor size from the first photograph's EXIF")


def _add_compare_command(sub: argparse._SubParsersAction) -> None:
    cmp_ = sub.add_parser(
        "compare",
        help="align a laser scan to a reconstruction and measure how far apart they are",
        description="Align a scan (mesh: PLY, OBJ, STL, OFF, GLB; or point cloud: PLY, PCD, XYZ/TXT/CSV, PTS) "
        "to a reconstruction (a mesh, or an output folder of `reconstruct run` made with --pixel-size) "
        "and measure signed point-to-surface distances, as CloudCompare's cloud-to-mesh distance does. "
        "Writes comparison.json, distances.ply, histogram.png and overlay.png.",
        epilog="exit status: 0, or 1 when --tolerance is given and too few points are within it; 2 for bad input",
    )
    cmp_.add_argument("reconstruction", type=_path, help="mesh or output folder of reconstruct run")
    cmp_.add_argument("scan", type=_path, help="the scan: a mesh or a point cloud")
    cmp_.add_argument("-o", "--output", type=_path, required=True, help="folder for the comparison files")
    _add_compare_options(cmp_)
    cmp_.add_argument("-q", "--quiet", action="store_true", help="no progress display")


def _add_integrate_command(sub: argparse._SubParsersAction) -> None:
    integ = sub.add_parser(
        "integrate",
        help="height map and meshes from a normal map made elsewhere",
        description="Integrate a normal map made by another tool (16- or 8-bit PNG/TIFF or JPEG in the "
        "OpenGL mapping R=x, G=y up, B=z, such as relight's normals.jpg, or a .npy array) into "
        "height.tif and meshes. Pixels without a valid normal are outside the object unless --mask "
        "says otherwise.",
    )
    integ.add_argument("normal_map", metavar="normals", type=_path, help="normal map (.png, .tif, .jpg or .npy)")
    integ.add_argument("-o", "--output", type=_path, required=True, help="output folder (created if needed)")
    integ.add_argument("--mask", metavar="FILE|auto", help="image whose non-zero pixels are the object, or 'auto'")
    integ.add_argument("--pixel-size", type=_positive_float, metavar="MM", help="millimetres per pixel (heights then in mm)")
    _choice(integ, RunOptions, "integrator", help="normal integration method (default: auto = with a mask of at most 1 megapixel, bilateral when it finds depth steps in the normals, else masked weighed by nz²; masked for a larger mask; dct without one)")
    integ.add_argument("--step", type=_positive_int, metavar="K", help="mesh vertex every K pixels")
    _add_camera_options(integ)
    integ.add_argument("-q", "--quiet", action="store_true", help="no progress display")


def _add_lights_command(sub: argparse._SubParsersAction) -> None:
    lights = sub.add_parser(
        "lights",
        help="check a light layout (.lp) before or without photographs: rank, coverage, polar plot",
        description="Check a light layout without photographs: whether the six PTM coefficients are all "
        "determined (rank and condition of the light matrix, and why not), the elevation and azimuth "
        "coverage, and a polar plot.",
    )
    lights.add_argument("lp", type=_path, help=".lp light file")
    lights.add_argument("-o", "--output", type=_path, help="write a polar plot of the lights (PNG)")


def _add_check_command(sub: argparse._SubParsersAction) -> None:
    check = sub.add_parser(
        "check",
        help="in seconds, before a long run: what is wrong with a capture (drift, exposure, lights, ...)",
        description="Look at a capture in a few seconds, from reduced photographs, before a long run: camera "
        "drift, stray light, clipped or black photographs, exposure differences between photographs, the colour profile and "
        "the light layout's weak directions. A run's report holds the same findings (drift measured on the full "
        "photographs). Exit status 0 whatever is found, 2 for a capture that cannot be read.",
    )
    check.add_argument("capture", type=_path, help="capture folder (photographs and one .lp file) or an .lp file")
    check.add_argument("--lp", type=_path, metavar="FILE", help="the light file (default: the one .lp in the folder, or in its assembly-files/ for an RTIBuilder project)")
    check.add_argument("--json", type=_path, metavar="FILE", help="also write the findings as JSON")


def _add_demo_command(sub: argparse._SubParsersAction) -> None:
    demo = sub.add_parser(
        "demo",
        help="render a synthetic clay tablet, reconstruct it and report the accuracy",
        description="Render a synthetic capture with known ground truth, reconstruct it, and print "
        "where the results are and how accurate they are.",
    )
    demo.add_argument("-o", "--output", type=_path, default=Path("demo_output"), help="folder for the capture and results (default: demo_output)")
    demo.add_argument("--size", type=_size(16), default="480x360",
                      help="image size WxH, at least 16 per side (default: 480x360; with the lights, at most 4 GiB to render)")
    demo.add_argument("--lights", type=_whole(3, DEMO_MAX_LIGHTS), default=48,
                      help=f"number of dome lights, 3 to {DEMO_MAX_LIGHTS} (default: 48)")
    demo.add_argument("--encoding", choices=DEMO_ENCODINGS, default="tiff16", help="photographs as 16-bit TIFF or 8-bit sRGB JPEG")
    demo.add_argument("--seed", type=_whole(0), default=0, help="random seed of the scene, 0 or more (default: 0)")
    _choice(demo, RunOptions, "normals", help="normal method (default: ps)")
    _choice(demo, RunOptions, "integrator", help="integrator (default: auto)")


def _add_warm_up_command(sub: argparse._SubParsersAction) -> None:
    sub.add_parser(
        "warm-up",
        help="compile the numerical kernels now, so that the first run does not (once per installation)",
        description="Reconstruct a few small synthetic captures, so that the compiled kernels every run uses "
        "are compiled and cached (beside the installed sources, or in NUMBA_CACHE_DIR). `make install` does it; "
        "run it again on a machine or container whose cache starts empty (a new cluster node).",
    )


def _add_preview_command(sub: argparse._SubParsersAction) -> None:
    prev = sub.add_parser(
        "preview",
        help="look at a result in a 3D window: relight it live, switch views, measure distances and profiles",
        description="Open a window on an output folder of `reconstruct run` (or a mesh file, or a .ptm shown "
        "as a flat relit plane): the textured mesh in millimetres, a light moved by the arrow keys or by "
        "dragging on a disk, views of the relit texture, albedo, normals, height, distance to a scan, "
        "RTIViewer's specular enhancement and diffuse gain and a relief shading, vertical exaggeration, "
        "and point picking for distances and height profiles, exported as CSV and PNG. With --screenshot "
        "it renders a figure (scale bar, light marker, no controls) off-screen to a PNG and exits.",
        epilog="keys in the window (figures and measurements go into RESULT/preview/):\n"
        + "\n".join("  " + line for line in preview_keys().splitlines()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    prev.add_argument("source", type=_path, help="output folder, mesh file (PLY, OBJ, STL, GLB, OFF) or .ptm file")
    prev.add_argument("--mode", choices=VIEW_MODES,
                      help="first view (default: relit when the source can be relit)")
    prev.add_argument("--light", metavar="X,Y,Z", help="direction towards the light (x right, y up, z towards the camera)")
    prev.add_argument("--azimuth", type=float, metavar="DEG",
                      help="light azimuth: 0 = from the right, 90 = from the top (default 135)")
    prev.add_argument("--elevation", type=float, metavar="DEG", help="light elevation above the object, 0 to 90 (default 40)")
    prev.add_argument("--comparison", type=_path, metavar="DIR", help="folder of `reconstruct compare` for the distance view")
    prev.add_argument("--screenshot", type=_path, metavar="PNG", help="render off-screen to this file and exit")
    prev.add_argument("--size", type=_size(64, PREVIEW_SIDE, PREVIEW_PIXELS), default="1280x900",
                      help=f"window or image size WxH, 64 to {PREVIEW_SIDE} per side and at most "
                      f"{PREVIEW_PIXELS / 2**20:g} megapixels (default 1280x900)")


def _add_compare_options(p: argparse.ArgumentParser) -> None:
    _choice(p, CompareOptions, "scan_units", help="unit of the scan's coordinates (default mm)")
    p.add_argument("--scale", action="store_true", help="also estimate a global scale (photometric heights may carry one)")
    p.add_argument("--initial", type=_path, metavar="FILE", help="4×4 matrix (text) taking the scan near the reconstruction")
    p.add_argument("--no-align", action="store_true", help="the two are already aligned")
    p.add_argument("--tolerance", type=_positive_float, metavar="MM",
                   help="report the share of points within this distance; exit 1 if below --min-fraction")
    p.add_argument("--min-fraction", type=float, default=default(CompareOptions, "min_fraction"), help="share within tolerance needed to pass (default 0.95)")
    p.add_argument("--reverse", action="store_true", help="also measure the reconstruction's distances to the scan")
    p.add_argument("--max-distance", type=_positive_float, metavar="MM",
                   help="points farther than this are outside the overlap (default: from the alignment residual)")


def _add_camera_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY",
                   help="perspective camera in pixels, for short lenses (default: orthographic)")
    lo, hi = BOUNDS["distance"]
    p.add_argument("--distance", type=_positive_float, metavar="MM",
                   help=f"with --intrinsics (needs it): camera-to-object distance, {lo:g} to {hi:g} mm, "
                   "so heights come out in mm")


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--lp", type=_path, help="light file to use (default: the .lp file in the capture folder, or "
                   "in its assembly-files/ for an RTIBuilder project); its photographs are looked for in the "
                   "capture folder first, then where it says, then in the project's jpeg-exports/")
    p.add_argument(
        "--pixel-size", type=_positive_float, metavar="MM",
        help="size of one pixel on the object in millimetres (%g to %g); heights and meshes are then in mm "
        "(else in pixels)" % BOUNDS["pixel_size"],
    )
    _choice(p, RunOptions, "normals", help="; ".join(f"{m.name}: {m.help}" for m in NORMAL_METHODS.values()))
    _choice(p, RunOptions, "fit",
            help="per-pixel fit: " + ", ".join(f"{f.name} ({f.help})" for f in FITS.values()))
    _choice(
        p, RunOptions, "integrator",
        help="normal integration: masked = least squares on the mask only; bilateral = the same keeping steps "
        "sharp; dct = least squares on the whole frame, free boundary; fc = Frankot-Chellappa; "
        "auto (default) = with a mask of at most 1 megapixel, bilateral when it finds depth steps in the normals, "
        "else masked weighed by nz²; masked for a larger mask; dct without one",
    )
    p.add_argument(
        "--step", type=_positive_int, metavar="K",
        help="mesh vertex every K pixels, at most %d (default: the smallest K keeping the mesh under 4 million "
        "vertices)" % BOUNDS["step"][1],
    )
    _choice(p, RunOptions, "ptm_format", help="coefficients.ptm as LRGB (default: one luminance polynomial and a colour per pixel) or RGB (one per channel)")
    _choice(p, RunOptions, "basis",
            help="the relighting basis of web/ (the page and OpenLIME's files), the report and `reconstruct relight`: "
                 "auto (default) = the one that best predicts each photograph left out of its fit, measured on this "
                 "capture, among --basis-candidates; ptm; hsh2, hsh3, hsh4 (hemispherical harmonics; OpenLIME shows up "
                 "to hsh3); rbf, bilinear (relight's interpolation of the photographs, compressed to 18 planes); neural "
                 "(NeuralRTI's learned basis: tens of seconds of training)")
    _choice(p, RunOptions, "basis_candidates",
            help="what --basis auto chooses from: standard (default: every basis but neural), openlime (only those "
                 "OpenLIME shows too: no hsh4), all (with neural; its training adds tens of seconds)")
    _choice(p, RunOptions, "basis_encoding",
            help="what the published basis is fitted to: srgb (the photographs as displayed), linear (linear light), "
                 "or auto (default: chosen with the basis, by the same measure)")
    _choice(p, RunOptions, "outputs",
            help="all (default); relight: only coefficients.ptm, web/ and the report, without normals, height "
                 "or meshes (seconds)")
    _choice(p, RunOptions, "ptm_encoding", help="what coefficients.ptm and .rti hold: srgb (default: the photographs "
            "display-encoded, as viewers show them, whatever their bit depth) or linear (linear light, e.g. for computing "
            "with the files; viewers show it dark)")
    _choice(p, RunOptions, "solver", help="{1}-inverse of the PTM light matrix: pinv (default, least squares, minimum norm), "
                   "lstsq (the same by another route), rohde (Rohde's form with zero blocks; docs/fitting.md)")
    p.add_argument("--intensities", metavar="FILE|estimate",
                   help="light intensity per photograph (a file: one value or 'r g b' per line, in .lp order), "
                   "or 'estimate' to estimate them from the photographs (uneven flash output)")
    p.add_argument("--hsh", action="store_true",
                   help="also write coefficients.rti, an HSH (order 3) relighting file that RTIViewer opens")
    p.add_argument("--loo", action="store_true",
                   help="compare relighting bases (PTM, HSH orders 2-4, RBF, bilinear) by leave-one-out error: "
                   "loo_*.tif maps and their RMS in report.json")
    p.add_argument("--mask", metavar="FILE|auto",
                   help="image whose non-zero pixels are the object, or 'auto' to find the object against its "
                   "background; height and mesh stay inside it")
    _add_camera_options(p)
    p.add_argument("--scan", type=_path, metavar="FILE",
                   help="compare with a laser scan as the last stage (needs --pixel-size); see `reconstruct compare`")
    # No default: without --scan it would do nothing, which is an error (cli.main).
    p.add_argument("--scan-units", choices=choices(CompareOptions, "scan_units"),
                   help="with --scan: unit of the scan (default mm)")
    p.add_argument("--decimate", type=_positive_int, metavar="FACES",
                   help="reduce the meshes to this many triangles (quadric edge collapse; error in report.json)")
    p.add_argument("--max-error", type=_positive_float, metavar="E",
                   help="reduce the meshes as far as the geometric error stays under E (height unit)")
    p.add_argument("--solid", type=_positive_float, metavar="THICKNESS",
                   help="also write solid.stl: the relief on a base this thick (height unit, %g to %g), "
                   "watertight, for 3D printing" % BOUNDS["solid"])
    p.add_argument("--glb", action="store_true", help="also write mesh.glb (binary glTF with the texture)")
    _choice(p, RunOptions, "flatten", help="remove low-frequency bending of the height map (from errors in the light directions): "
                   "a plane, a polynomial of order 2 or 3, or long wavelengths")
    p.add_argument("--flatten-cutoff", type=_positive_float, default=default(RunOptions, "flatten_cutoff"), metavar="PX",
                   help="with --flatten highpass (needs it): the wavelength in pixels that keeps half its height, "
                   "%g to %g (default 200)" % BOUNDS["flatten_cutoff"])
    p.add_argument("--no-linearize", dest="linearize", action="store_false", help="take 8-bit photographs as linear instead of sRGB")
    p.add_argument("--threads", type=_whole(1, 1024),
                   help="threads for decoding, the per-pixel fits, the integration and writing files (default: every CPU "
                        "this process may use: its affinity and its container's CPU quota)")
    p.add_argument("--memory-limit", type=_positive_float, metavar="MB",
                   help="memory the run may use: the photographs' stack stays in memory when the run fits "
                        "in it, else it goes to a temporary file beside the output folder. Default: a stack of "
                        f"{STACK_FILE_MB} MB or more always goes to the file (measured as fast), a smaller one when "
                        "the run would not fit in the memory available (in a Slurm job or a container: what its "
                        "memory cgroup has left)")
    p.add_argument("--ground-truth", type=_path, metavar="DIR", help="folder with normals.npy (and mask.png, height.npy) to report accuracy")
    p.add_argument("--light-positions", default=default(RunOptions, "light_positions"), metavar="FILE|auto|none",
                   help="near lights: a CSV of light positions (name,x,y,z in pixels) giving every pixel its own "
                        "light direction; auto (default): light_positions.csv beside the .lp, or lights triangulated "
                        "from two or more spheres when they are near; none: distant lights")
    _choice(p, RunOptions, "align",
            help="auto (default): measure the camera's drift (a bumped tripod) and resample the photographs onto "
                 "one frame before fitting when one is displaced by more than a pixel; off: measured and reported, not undone. "
                 "`reconstruct check` measures the drift in seconds")
    p.add_argument("--flat-field", type=_path, metavar="DIR",
                   help="a capture of a flat white or grey board under the same lights (same .lp names or order): "
                        "corrects lamps that light the frame unevenly (cones, vignetting, fall-off) and unequal lamps")
    p.add_argument("--reference-region", metavar="X,Y,W,H",
                   help="a grey card seen in every photograph (pixels: X column and Y row of its top-left corner): "
                        "each photograph's light intensity is read from it (not with --intensities)")
    p.add_argument("--ambient", type=_path, metavar="FILE",
                   help="a photograph with the lamps off (the room's light alone, same exposure), subtracted from "
                        "every photograph")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")


