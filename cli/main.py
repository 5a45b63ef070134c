"""The ``reconstruct`` command: a thin layer over :mod:`reconstruct.pipeline.run`."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from ptmcore import __version__
from ptmcore.errors import InputError

EXIT_BAD_INPUT = 2
INTEGRATOR_CHOICES = ("auto", "dct", "fc", "masked", "bilateral")

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

outputs (in the -o folder):
  coefficients.ptm           the PTM (HP PTM 1.2, opens in RTIViewer); web/ for OpenLIME
  coefficients.rti           with --hsh: HSH order 3 (RTIViewer's .rti)
  normals.npy, normals.png   unit normals (float32) and a 16-bit OpenGL-style normal map
  albedo.png                 the surface colour without shading (8-bit sRGB)
  height.tif                 float32 height map; millimetres with --pixel-size, else pixels
  mesh.ply, mesh.obj         textured mesh (OBJ with mesh.mtl and mesh_texture.png)
  mask.png                   the mask, when --mask is given
  loo_ptm.tif, loo_hsh*.tif  leave-one-out relighting error maps, with --loo
  report.json                inputs, parameters, timings, memory, warnings, accuracy

example:
  reconstruct run tablet/ -o tablet_out --pixel-size 0.04 --normals ps --integrator dct
"""


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return v


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return v


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="reconstruct", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--version", action="version", version=f"reconstruct (ptm-reconstruct) {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    run = sub.add_parser(
        "run",
        help="reconstruct one capture: normals, height map and mesh",
        description="Reconstruct one capture: a folder of photographs with its .lp light file, a "
        "photometric-stereo dataset folder, or an existing .ptm file.",
        epilog=RUN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    run.add_argument("capture", type=Path,
                     help="capture folder (photographs and one .lp file), an .lp file, a .ptm file, or a "
                     "photometric-stereo dataset folder (filenames.txt, light_directions.txt, ...)")
    run.add_argument("-o", "--output", type=Path, required=True, help="output folder (created if needed)")
    _add_run_options(run)

    rel = sub.add_parser(
        "relight",
        help="render a PTM under a chosen light (RTIViewer's modes), or a GIF of a circling light",
        description="Render a PTM or HSH file under any light, as RTIViewer does. SOURCE is a .ptm or "
        ".rti (HSH) file, or an output folder of `reconstruct run` (its coefficients.ptm, or with "
        "--basis hsh its coefficients.rti).",
        epilog=RELIGHT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rel.add_argument("source", type=Path, help=".ptm file or output folder")
    rel.add_argument("-o", "--output", type=Path, required=True, help="image to write (.png, .jpg, .tif; .gif with --sweep)")
    rel.add_argument("--light", metavar="X,Y,Z", help="direction towards the light (x right, y up, z towards the camera)")
    rel.add_argument("--azimuth", type=float, metavar="DEG", help="light azimuth: 0 = from the right, 90 = from the top")
    rel.add_argument("--elevation", type=float, metavar="DEG", help="light elevation above the object (default with --sweep: 30)")
    rel.add_argument("--mode", choices=("default", "specular", "diffuse-gain"), default="default",
                     help="default rendering, specular enhancement, or diffuse gain (default: default)")
    rel.add_argument("--kd", type=float, default=0.4, help="specular enhancement: diffuse weight (default 0.4)")
    rel.add_argument("--ks", type=float, default=0.7, help="specular enhancement: specular weight (default 0.7)")
    rel.add_argument("--exponent", type=float, default=75.0, help="specular enhancement: Phong exponent (default 75)")
    rel.add_argument("--gain", type=float, default=2.0, help="diffuse gain (default 2)")
    rel.add_argument("--basis", choices=("ptm", "hsh"), default="ptm",
                     help="with an output folder: relight its coefficients.ptm (default) or its HSH coefficients.rti")
    rel.add_argument("--sweep", type=_positive_int, metavar="N", help="write an animated GIF of N frames with the light circling the object")

    cal = sub.add_parser(
        "calibrate",
        help="light directions from glossy spheres in the photographs (highlight RTI): writes an .lp",
        description="Find the black glossy spheres in a capture (or take them from --sphere), read the "
        "highlight on each in every photograph, and write the light directions as an .lp file. "
        "Photographs without a usable highlight are named and left out.",
    )
    cal.add_argument("capture", type=Path, help="folder of photographs")
    cal.add_argument("-o", "--output", type=Path, required=True, help="the .lp file to write")
    cal.add_argument("--sphere", action="append", metavar="X,Y,R",
                     help="a sphere's centre (column, row) and radius in pixels; repeat for several")
    cal.add_argument("--diagnostic", type=Path, metavar="PNG",
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

    cmp_ = sub.add_parser(
        "compare",
        help="align a laser scan to a reconstruction and measure how far apart they are",
        description="Align a scan (mesh: PLY, OBJ, STL, OFF, GLB; or point cloud: PLY, PCD, XYZ/TXT/CSV, PTS) "
        "to a reconstruction (a mesh, or an output folder of `reconstruct run` made with --pixel-size) "
        "and measure signed point-to-surface distances, as CloudCompare's cloud-to-mesh distance does. "
        "Writes comparison.json, distances.ply, histogram.png and overlay.png.",
        epilog="exit status: 0, or 1 when --tolerance is given and too few points are within it; 2 for bad input",
    )
    cmp_.add_argument("reconstruction", type=Path, help="mesh or output folder of reconstruct run")
    cmp_.add_argument("scan", type=Path, help="the scan: a mesh or a point cloud")
    cmp_.add_argument("-o", "--output", type=Path, required=True, help="folder for the comparison files")
    _add_compare_options(cmp_)

    integ = sub.add_parser(
        "integrate",
        help="height map and meshes from a normal map made elsewhere",
        description="Integrate a normal map made by another tool (16- or 8-bit PNG/TIFF or JPEG in the "
        "OpenGL mapping R=x, G=y up, B=z, such as relight's normals.jpg, or a .npy array) into "
        "height.tif and meshes. Pixels without a valid normal are outside the object unless --mask "
        "says otherwise.",
    )
    integ.add_argument("normals", type=Path, help="normal map (.png, .tif, .jpg or .npy)")
    integ.add_argument("-o", "--output", type=Path, required=True, help="output folder (created if needed)")
    integ.add_argument("--mask", metavar="FILE|auto", help="image whose non-zero pixels are the object, or 'auto'")
    integ.add_argument("--pixel-size", type=_positive_float, metavar="MM", help="millimetres per pixel (heights then in mm)")
    integ.add_argument("--integrator", choices=INTEGRATOR_CHOICES, default="auto",
                       help="normal integration method (default: auto = masked when a mask is known, else dct)")
    integ.add_argument("--step", type=_positive_int, metavar="K", help="mesh vertex every K pixels")
    _add_camera_options(integ)
    integ.add_argument("-q", "--quiet", action="store_true", help="no progress display")

    lights = sub.add_parser(
        "lights",
        help="check a light layout (.lp) before or without photographs: rank, coverage, polar plot",
        description="Check a light layout without photographs: whether the six PTM coefficients are all "
        "determined (rank and condition of the light matrix, and why not), the elevation and azimuth "
        "coverage, and a polar plot.",
    )
    lights.add_argument("lp", type=Path, help=".lp light file")
    lights.add_argument("-o", "--output", type=Path, help="write a polar plot of the lights (PNG)")

    demo = sub.add_parser(
        "demo",
        help="render a synthetic clay tablet, reconstruct it and report the accuracy",
        description="Render a synthetic capture with known ground truth, reconstruct it, and print "
        "where the results are and how accurate they are.",
    )
    demo.add_argument("-o", "--output", type=Path, default=Path("demo_output"), help="folder for the capture and results (default: demo_output)")
    demo.add_argument("--size", default="480x360", help="image size WxH (default: 480x360)")
    demo.add_argument("--lights", type=_positive_int, default=48, help="number of dome lights (default: 48)")
    demo.add_argument("--encoding", choices=("tiff16", "jpeg8"), default="tiff16", help="photographs as 16-bit TIFF or 8-bit sRGB JPEG")
    demo.add_argument("--seed", type=int, default=0, help="random seed of the scene (default: 0)")
    demo.add_argument("--normals", choices=("ps", "ptm", "ptm-debiased"), default="ps", help="normal method (default: ps)")
    demo.add_argument("--integrator", choices=INTEGRATOR_CHOICES, default="auto", help="integrator (default: auto)")

    prev = sub.add_parser(
        "preview",
        help="look at a result in a 3D window: relight it live, switch views, measure distances and profiles",
        description="Open a window on an output folder of `reconstruct run` (or a mesh file, or a .ptm shown "
        "as a flat relit plane): the textured mesh in millimetres, sliders that move the light, views of "
        "the relit texture, albedo, normals, height and distance to a scan, and point picking for distances "
        "and height profiles. With --screenshot it renders off-screen to a PNG and exits.",
    )
    prev.add_argument("source", type=Path, help="output folder, mesh file (PLY, OBJ, STL, GLB, OFF) or .ptm file")
    prev.add_argument("--mode", choices=("relit", "albedo", "normals", "height", "distance"),
                      help="first view (default: relit when the source can be relit)")
    prev.add_argument("--light", metavar="X,Y,Z", help="direction towards the light (x right, y up, z towards the camera)")
    prev.add_argument("--azimuth", type=float, metavar="DEG",
                      help="light azimuth: 0 = from the right, 90 = from the top (default 135)")
    prev.add_argument("--elevation", type=float, metavar="DEG", help="light elevation above the object, 0 to 90 (default 40)")
    prev.add_argument("--comparison", type=Path, metavar="DIR", help="folder of `reconstruct compare` for the distance view")
    prev.add_argument("--screenshot", type=Path, metavar="PNG", help="render off-screen to this file and exit")
    prev.add_argument("--size", default="1280x900", help="window or image size WxH (default 1280x900)")
    return parser


def _add_compare_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scan-units", choices=("mm", "cm", "m", "in"), default="mm",
                   help="unit of the scan's coordinates (default mm)")
    p.add_argument("--scale", action="store_true", help="also estimate a global scale (photometric heights may carry one)")
    p.add_argument("--initial", type=Path, metavar="FILE", help="4×4 matrix (text) taking the scan near the reconstruction")
    p.add_argument("--no-align", action="store_true", help="the two are already aligned")
    p.add_argument("--tolerance", type=_positive_float, metavar="MM",
                   help="report the share of points within this distance; exit 1 if below --min-fraction")
    p.add_argument("--min-fraction", type=float, default=0.95, help="share within tolerance needed to pass (default 0.95)")
    p.add_argument("--reverse", action="store_true", help="also measure the reconstruction's distances to the scan")
    p.add_argument("--max-distance", type=_positive_float, metavar="MM",
                   help="points farther than this are outside the overlap (default: from the alignment residual)")


def _compare_summary(result) -> None:
    stats = result.report["statistics_mm"]
    al = result.report["alignment"]
    print(f"Comparison in {result.output}/: {stats['count']:,} scan points in the overlap "
          f"({stats['overlap_fraction']:.0%}), alignment fitness {al['fitness']:.2f}, "
          f"residual {al['inlier_rmse_mm']:.4f} mm" + (f", scale {al['scale']:.4f}" if abs(al["scale"] - 1) > 1e-9 else ""))
    print(f"  distances (mm): mean {stats['mean']:+.4f}, std {stats['std']:.4f}, RMS {stats['rms']:.4f}, "
          f"median |d| {stats['median_abs']:.4f}, 95% |d| {stats['p95_abs']:.4f}, max |d| {stats['max_abs']:.4f}")
    tol = result.report.get("tolerance")
    if tol:
        verdict = "PASS" if tol["passed"] else "FAIL"
        print(f"  {tol['fraction_within']:.1%} within ±{tol['tolerance_mm']} mm "
              f"(needed {tol['min_fraction']:.0%}): {verdict}")
    for w in result.report["warnings"]:
        print(f"  warning: {w}")


def _parse_spheres(texts: list[str] | None) -> list[tuple[float, float, float]] | None:
    if not texts:
        return None
    spheres = []
    for text in texts:
        try:
            x, y, r = (float(v) for v in text.split(","))
        except ValueError:
            raise InputError(f"--sphere must be X,Y,R in pixels, got {text!r}") from None
        if not r > 0:
            raise InputError(f"--sphere radius must be positive, got {text!r}")
        spheres.append((x, y, r))
    return spheres


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from ptmcore.images import load_stack, read_image
    from ptmcore.nearlight import typical_distance
    from reconstruct.calibration.calibrate import (
        calibration_camera,
        write_calibration_lp,
        write_diagnostic,
    )
    from reconstruct.calibration.lightcheck import write_polar_plot
    from reconstruct.pipeline.run import capture_images
    from reconstruct.calibration.triangulate import sphere_lights, write_near_light_files

    paths = capture_images(args.capture)
    stack = load_stack(paths, min_photographs=1)
    camera = calibration_camera(paths[0], stack.shape, intrinsics=args.intrinsics, focal_mm=args.focal_mm,
                                sensor_width_mm=args.sensor_width_mm, exif=args.exif)
    found = sphere_lights(stack, spheres=_parse_spheres(args.sphere), intrinsics=camera)
    result = found.calibration
    if found.triangulation is None:
        count = write_calibration_lp(args.output, result)
        print(f"{args.output}: {count} of {len(paths)} photographs with a light direction, from "
              f"{len(result.spheres)} sphere(s), {result.view_model} view")
    else:
        positions_file = args.output.with_name("light_positions.csv")
        write_near_light_files(args.output, positions_file, found.triangulation, stack.shape)
        print(f"{args.output}, {positions_file.name}: near lights triangulated from {len(result.spheres)} "
              f"spheres for {len(found.names)} of {len(paths)} photographs (median distance "
              f"{typical_distance(found.positions, stack.shape):.0f} px); `run` gives "
              "every pixel its own light direction")
    for line in found.left_out:
        print(f"  warning: {line}; left out")
    if args.diagnostic is not None:
        write_diagnostic(args.diagnostic, read_image(paths[0]), result, 0)
        polar = args.diagnostic.with_name(args.diagnostic.stem + "_lights.png")
        write_polar_plot(polar, found.directions, title=args.output.name)
        print(f"  diagnostics: {args.diagnostic}, {polar}")
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from reconstruct.pipeline.run import CompareOptions, run_compare

    options = CompareOptions(
        scan_units=args.scan_units, scale=args.scale, initial=args.initial, no_align=args.no_align,
        tolerance=args.tolerance, min_fraction=args.min_fraction, reverse=args.reverse,
        max_distance=args.max_distance,
    )
    result = run_compare(args.reconstruction, args.scan, args.output, options)
    _compare_summary(result)
    return 1 if result.passed is False else 0


def _add_camera_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--intrinsics", metavar="FX,FY,CX,CY",
                   help="perspective camera in pixels, for short lenses (default: orthographic)")
    p.add_argument("--distance", type=_positive_float, metavar="MM",
                   help="with --intrinsics: camera-to-object distance, so heights come out in mm")


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--lp", type=Path, help="light file to use (default: the .lp file in the capture folder)")
    p.add_argument(
        "--pixel-size", type=_positive_float, metavar="MM",
        help="size of one pixel on the object in millimetres; heights and meshes are then in mm (else in pixels)",
    )
    p.add_argument(
        "--normals", choices=("ps", "ptm", "ptm-debiased"), default="ps",
        help="ps: photometric stereo (default, the most accurate); ptm: maximum of each pixel's PTM; "
        "ptm-debiased: that maximum corrected for the PTM's bias towards the view direction",
    )
    p.add_argument(
        "--fit", choices=("irls", "trimmed", "plain"), default="irls",
        help="per-pixel fit: irls (default: robust, down-weights shadowed, clipped and specular samples), "
        "trimmed (robust, leaves them out), plain (least squares)",
    )
    p.add_argument(
        "--integrator", choices=INTEGRATOR_CHOICES, default="auto",
        help="normal integration: masked = least squares on the mask only; bilateral = the same keeping steps "
        "sharp; dct = least squares on the whole frame, free boundary; fc = Frankot-Chellappa; "
        "auto (default) = masked when a mask is known, else dct",
    )
    p.add_argument(
        "--step", type=_positive_int, metavar="K",
        help="mesh vertex every K pixels (default: the smallest K keeping the mesh under 4 million vertices)",
    )
    p.add_argument("--ptm-format", choices=("lrgb", "rgb"), default="lrgb",
                   help="coefficients.ptm as LRGB (default: one luminance polynomial and a colour per pixel) or RGB (one per channel)")
    p.add_argument("--solver", choices=("pinv", "lstsq", "rohde"), default="pinv",
                   help="{1}-inverse of the PTM light matrix: pinv (default, least squares, minimum norm), "
                   "lstsq (the same by another route), rohde (Rohde's form with zero blocks; docs/fitting.md)")
    p.add_argument("--intensities", metavar="FILE|estimate",
                   help="light intensity per photograph (a file: one value or 'r g b' per line, in .lp order), "
                   "or 'estimate' to estimate them from the photographs (uneven flash output)")
    p.add_argument("--hsh", action="store_true",
                   help="also write coefficients.rti, an HSH (order 3) relighting file that RTIViewer opens")
    p.add_argument("--loo", action="store_true",
                   help="compare relighting bases (PTM, HSH orders 2 and 3) by leave-one-out error: "
                   "loo_*.tif maps and their RMS in report.json")
    p.add_argument("--mask", metavar="FILE|auto",
                   help="image whose non-zero pixels are the object, or 'auto' to find the object against its "
                   "background; height and mesh stay inside it")
    _add_camera_options(p)
    p.add_argument("--scan", type=Path, metavar="FILE",
                   help="compare with a laser scan as the last stage (needs --pixel-size); see `reconstruct compare`")
    p.add_argument("--scan-units", choices=("mm", "cm", "m", "in"), default="mm", help="unit of the scan (default mm)")
    p.add_argument("--decimate", type=_positive_int, metavar="FACES",
                   help="reduce the meshes to this many triangles (quadric edge collapse; error in report.json)")
    p.add_argument("--max-error", type=_positive_float, metavar="E",
                   help="reduce the meshes as far as the geometric error stays under E (height unit)")
    p.add_argument("--solid", type=_positive_float, metavar="THICKNESS",
                   help="also write solid.stl: the relief on a base this thick, watertight, for 3D printing")
    p.add_argument("--glb", action="store_true", help="also write mesh.glb (binary glTF with the texture)")
    p.add_argument("--flatten", choices=("plane", "poly2", "poly3", "highpass"),
                   help="remove low-frequency bending of the height map (from errors in the light directions): "
                   "a plane, a polynomial of order 2 or 3, or long wavelengths")
    p.add_argument("--flatten-cutoff", type=_positive_float, default=200.0, metavar="PX",
                   help="with --flatten highpass: the wavelength in pixels that keeps half its height (default 200)")
    p.add_argument("--no-linearize", dest="linearize", action="store_false", help="take 8-bit photographs as linear instead of sRGB")
    p.add_argument("--threads", type=_positive_int, help="image decoding threads (default: all CPUs)")
    p.add_argument("--ground-truth", type=Path, metavar="DIR", help="folder with normals.npy (and mask.png, height.npy) to report accuracy")
    p.add_argument("--light-positions", default="auto", metavar="FILE|auto|none",
                   help="near lights: a CSV of light positions (name,x,y,z in pixels) giving every pixel its own "
                        "light direction; auto (default): light_positions.csv beside the .lp, or lights triangulated "
                        "from two or more spheres when they are near; none: distant lights")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")


@contextmanager
def _progress_display(enabled: bool) -> Iterator[Callable[[str, int, int], None] | None]:
    if not enabled:
        yield None
        return
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    labels = {
        "decode": "Decoding photographs",
        "fit_ptm": "Fitting the PTM",
        "ptm": "Writing the .ptm",
        "loo": "Leave-one-out check",
        "normals": "Estimating normals",
        "integrate": "Integrating heights",
        "mesh": "Writing meshes",
        "write": "Writing images",
    }
    tasks: dict[str, int] = {}
    with Progress(
        TextColumn("{task.description:<22}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(), transient=False, console=_stderr_console(),
    ) as bar:

        def update(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(labels.get(stage, stage), total=total)
            bar.update(tasks[stage], completed=done)

        yield update


def _stderr_console():
    from rich.console import Console

    return Console(stderr=True)


def _cmd_run(args: argparse.Namespace) -> int:
    from reconstruct.pipeline.run import RunOptions, run

    options = RunOptions(
        lp=args.lp, pixel_size=args.pixel_size, normals=args.normals, integrator=args.integrator,
        step=args.step, linearize=args.linearize, threads=args.threads,
        mask=None if args.mask is None else (args.mask if args.mask == "auto" else Path(args.mask)),
        flatten=args.flatten, flatten_cutoff=args.flatten_cutoff, decimate=args.decimate,
        max_error=args.max_error, solid=args.solid, glb=args.glb,
        intrinsics=args.intrinsics, distance=args.distance,
        ground_truth=args.ground_truth, ptm_format=args.ptm_format, solver=args.solver,
        loo=args.loo, intensities=args.intensities, fit=args.fit, hsh=args.hsh,
        light_positions=args.light_positions if args.light_positions in ("auto", "none") else Path(args.light_positions),
    )
    if args.scan is not None and args.pixel_size is None:
        raise InputError("--scan needs --pixel-size: a scan is compared in millimetres")
    # With --scan, the comparison writes report.html, once, with the run's report and its own.
    with _progress_display(not args.quiet and sys.stderr.isatty()) as progress:
        result = run(args.capture, args.output, options, progress=progress, report_page=args.scan is None)
    compared = None
    if args.scan is not None:
        from reconstruct.pipeline.run import CompareOptions, run_compare
        from reconstruct.report.html import write_report_html

        try:
            compared = run_compare(args.output, args.scan, args.output, CompareOptions(scan_units=args.scan_units))
        except InputError:
            write_report_html(result.output, report=result.report)  # the run's page, without the scan
            _print_summary(result.report, result.output)
            raise
    _print_summary(result.report, result.output)
    if compared is not None:
        _compare_summary(compared)
    return 0


def _print_summary(report: dict, out: Path) -> None:
    total = sum(s["seconds"] for s in report["stages"].values())
    inputs = report["inputs"]
    source = f"{inputs['photographs']} photographs" if "photographs" in inputs else inputs.get("format", "PTM")
    print(f"Results in {out}/ ({source}, {inputs['width']}×{inputs['height']}, {total:.1f} s)")
    print(f"  heights in {report['height_unit']}; mesh: {report['mesh']['vertices']:,} vertices, "
          f"{report['mesh']['faces']:,} triangles (step {report['mesh']['step']})")
    acc = report.get("accuracy")
    if acc:
        n = acc["normals"]
        line = f"  accuracy: normals {n['mean_deg']:.2f}° mean, {n['median_deg']:.2f}° median"
        if "height_rmse_mm" in acc:
            line += f"; height RMSE {acc['height_rmse_mm']:.4f} mm"
        print(line)
    for w in report["warnings"]:
        print(f"  warning: {w}")
    if (out / "report.html").is_file():
        print(f"  report: {out / 'report.html'}; look at it in 3D: reconstruct preview {out}")


def _parse_vector(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise InputError(f"--light must be three numbers x,y,z, got {text!r}")
    return values


def _cmd_relight(args: argparse.Namespace) -> int:
    from ptmcore.relight import light_direction
    from reconstruct.viewer.relighting import (
        load_source,
        render,
        sweep_lights,
        write_gif,
        write_image,
    )

    params = {"kd": args.kd, "ks": args.ks, "exponent": args.exponent, "gain": args.gain}
    if args.sweep is None:
        if (args.light is None) == (args.azimuth is None and args.elevation is None):
            raise InputError("give either --light X,Y,Z or --azimuth and --elevation (or --sweep N)")
        try:
            if args.light is not None:
                light = light_direction(light=_parse_vector(args.light))
            else:
                if args.azimuth is None or args.elevation is None:
                    raise InputError("--azimuth and --elevation go together")
                light = light_direction(azimuth_deg=args.azimuth, elevation_deg=args.elevation)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    ptm = load_source(args.source, args.basis)
    try:
        if args.sweep is None:
            write_image(args.output, render(ptm, light, args.mode, **params))
        else:
            elevation = 30.0 if args.elevation is None else args.elevation
            if not 0 < elevation <= 90:
                raise InputError(f"--elevation must be in (0, 90] degrees, got {elevation}")
            frames = [render(ptm, lt, args.mode, **params) for lt in sweep_lights(args.sweep, elevation)]
            write_gif(args.output, frames)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    print(f"Wrote {args.output}")
    return 0


def _cmd_integrate(args: argparse.Namespace) -> int:
    from reconstruct.pipeline.run import RunOptions, run_normals

    mask = None if args.mask is None else (args.mask if args.mask == "auto" else Path(args.mask))
    options = RunOptions(pixel_size=args.pixel_size, integrator=args.integrator, step=args.step, mask=mask,
                         intrinsics=args.intrinsics, distance=args.distance)
    with _progress_display(not args.quiet and sys.stderr.isatty()) as progress:
        result = run_normals(args.normals, args.output, options, progress=progress)
    report = result.report
    print(f"Results in {result.output}/ ({report['inputs']['width']}×{report['inputs']['height']} normal map)")
    print(f"  heights in {report['height_unit']}; mesh: {report['mesh']['vertices']:,} vertices, "
          f"{report['mesh']['faces']:,} triangles (step {report['mesh']['step']})")
    for w in report["warnings"]:
        print(f"  warning: {w}")
    return 0


def _cmd_lights(args: argparse.Namespace) -> int:
    from ptmcore.lp import read_lp
    from reconstruct.calibration.lightcheck import check_lights, report_text, write_polar_plot

    lights = read_lp(args.lp)
    print(report_text(check_lights(lights.directions)))
    if args.output is not None:
        write_polar_plot(args.output, lights.directions, title=args.lp.name)
        print(f"Polar plot: {args.output}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from data_synthetic import write_capture
    from reconstruct.pipeline.run import RunOptions, run_capture

    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
        if w < 16 or h < 16:
            raise ValueError
    except ValueError:
        raise InputError(f"--size must be WxH with both at least 16, got {args.size!r}") from None
    capture_dir = args.output / "capture"
    print(f"Rendering a synthetic clay tablet ({w}×{h}, {args.lights} lights, {args.encoding}) in {capture_dir}/ ...")
    info = write_capture(capture_dir, scene="tablet", shape=(h, w), n_lights=args.lights, encoding=args.encoding, seed=args.seed)
    options = RunOptions(pixel_size=info.pixel_size, normals=args.normals, integrator=args.integrator)
    with _progress_display(sys.stderr.isatty()) as progress:
        result = run_capture(capture_dir, args.output / "result", options, progress=progress)
    _print_summary(result.report, result.output)
    print(f"Open {result.output / 'mesh.obj'} or mesh.ply in MeshLab, Blender or CloudCompare;")
    print(f"the synthetic photographs and their ground truth are in {capture_dir}/.")
    return 0


def _cmd_preview(args: argparse.Namespace) -> int:
    import math

    from ptmcore.relight import light_direction
    from reconstruct.viewer.preview import (
        DEFAULT_AZIMUTH,
        DEFAULT_ELEVATION,
        build_plotter,
        has_display,
        render_screenshot,
    )
    from reconstruct.viewer.scene import load_scene

    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
        if width < 64 or height < 64:
            raise ValueError
    except ValueError:
        raise InputError(f"--size must be WxH with both at least 64, got {args.size!r}") from None
    # The angles are checked where they are used (a ValueError, made an InputError below).
    azimuth = DEFAULT_AZIMUTH if args.azimuth is None else args.azimuth
    elevation = DEFAULT_ELEVATION if args.elevation is None else args.elevation
    if args.light is not None:
        if args.azimuth is not None or args.elevation is not None:
            raise InputError("give either --light X,Y,Z or --azimuth/--elevation")
        try:
            x, y, z = light_direction(light=_parse_vector(args.light))
        except ValueError as exc:
            raise InputError(str(exc)) from None
        azimuth, elevation = math.degrees(math.atan2(y, x)) % 360, math.degrees(math.asin(z))
    if args.screenshot is None and not has_display():
        raise InputError("no display to open a window on (DISPLAY is not set): render to a file with --screenshot FILE")
    scene = load_scene(args.source, comparison=args.comparison)
    options = {"mode": args.mode, "azimuth": azimuth, "elevation": elevation, "size": (width, height)}
    if args.screenshot is not None:
        print(f"Wrote {render_screenshot(scene, args.screenshot, **options)}")
        return 0
    try:
        window = build_plotter(scene, **options)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    except RuntimeError as exc:
        raise InputError(f"{exc}; use --screenshot FILE to render off-screen") from None
    window.plotter.show(title=f"reconstruct preview: {scene.name}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``reconstruct`` command; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        commands = {"run": _cmd_run, "relight": _cmd_relight, "integrate": _cmd_integrate, "compare": _cmd_compare,
                    "calibrate": _cmd_calibrate, "preview": _cmd_preview,
                    "lights": _cmd_lights, "demo": _cmd_demo}
        return commands[args.command](args)
    except InputError as exc:
        print(f"reconstruct: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("reconstruct: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # Output piped into a command that stopped reading (`| head`): not an error.
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
