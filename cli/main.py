"""The ``reconstruct`` command: a thin layer over :mod:`reconstruct.pipeline` and the others.

Arguments are defined in :mod:`reconstruct.cli.parser`; each ``_cmd_*`` turns them into the
Python API's options, calls it, and prints a summary. Bad input (an ``InputError``) is one line
on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from ptmcore.atomic import resolve_output
from ptmcore.errors import InputError
from ptmcore.images import allow_large_images
from reconstruct.cli.signals import handlers, interrupted
from reconstruct.cli.parser import build_parser
from reconstruct.report.summary import unit_words

EXIT_BAD_INPUT = 2


def _compare_summary(result) -> None:
    """What a comparison found, in a few lines."""
    report = result.report
    stats, al = report.statistics_mm, report.alignment
    print(f"Comparison in {result.output}/: {stats['count']:,} scan points in the overlap "
          f"({stats['overlap_fraction']:.0%}), alignment fitness {al.fitness:.2f}, "
          f"residual {al.inlier_rmse_mm:.4f} mm" + (f", scale {al.scale:.4f}" if abs(al.scale - 1) > 1e-9 else ""))
    print(f"  distances (mm): mean {stats['mean']:+.4f}, std {stats['std']:.4f}, RMS {stats['rms']:.4f}, "
          f"median |d| {stats['median_abs']:.4f}, 95% |d| {stats['p95_abs']:.4f}, max |d| {stats['max_abs']:.4f}")
    tol = report.tolerance
    if tol:
        verdict = "PASS" if tol.passed else "FAIL"
        print(f"  {tol.fraction_within:.1%} within ±{tol.tolerance_mm} mm (needed {tol.min_fraction:.0%}): {verdict}")
    for w in report.warnings:
        print(f"  warning: {w}")


def _parse_spheres(texts: list[str] | None) -> list[tuple[float, float, float]] | None:
    """The values of ``--sphere``, each ``X,Y,R`` in pixels; None when none is given. Their
    fit to the photographs is checked once these are read
    (:func:`reconstruct.calibration.spheres.check_sphere`)."""
    if not texts:
        return None
    spheres = []
    for text in texts:
        try:
            x, y, r = (float(v) for v in text.split(","))
            if not all(map(math.isfinite, (x, y, r))):
                raise ValueError
        except ValueError:
            raise InputError(f"--sphere must be three finite numbers X,Y,R in pixels, got {text!r}") from None
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
    from reconstruct.pipeline.capture import capture_images
    from reconstruct.calibration.triangulate import sphere_lights, write_near_light_files

    for output in (args.output, args.diagnostic):  # before the photographs are read
        if output is not None:
            resolve_output(output)
    spheres = _parse_spheres(args.sphere)  # before the photographs are read
    paths = capture_images(args.capture)
    stack = load_stack(paths, min_photographs=1)
    camera = calibration_camera(paths[0], stack.shape, intrinsics=args.intrinsics, focal_mm=args.focal_mm,
                                sensor_width_mm=args.sensor_width_mm, exif=args.exif)
    found = sphere_lights(stack, spheres=spheres, intrinsics=camera)
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
    # The highlights' dimming with elevation says whether the spheres' lobe is shaded × n·l
    # (reconstruct.calibration.highlights); shown because it moves broad highlights by degrees.
    print(f"  highlight model: lobe × (n·l)^{result.lobe_cosine:.2f}, read from how the highlights dim "
          "as the lights get lower")
    for line in found.left_out:
        print(f"  warning: {line}; left out")
    if args.diagnostic is not None:
        write_diagnostic(args.diagnostic, read_image(paths[0]), result, 0)
        polar = args.diagnostic.with_name(args.diagnostic.stem + "_lights.png")
        write_polar_plot(polar, found.directions, names=found.names, title=args.output.name)
        print(f"  diagnostics: {args.diagnostic}, {polar}")
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from reconstruct.pipeline import CompareOptions, run_compare

    options = _options(CompareOptions, args)
    resolve_output(args.output, folder=True)  # before the scan is read
    with _progress_display(not args.quiet and sys.stderr.isatty()) as progress:
        result = run_compare(args.reconstruction, args.scan, args.output, options, progress=progress)
    _compare_summary(result)
    return 1 if result.passed is False else 0


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
        "albedo": "Albedo and mask",
        "integrate": "Integrating heights",
        "mesh": "Building the mesh",
        "write": "Writing files",
        "report": "Making report.html",
        "scan_read": "Reading the scan",
        "scan_align": "Aligning the scan",
        "scan_distances": "Scan distances",
        "scan_write": "Comparison figures",
        "scan_report": "Comparison page",
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


def _options(cls: type, args: argparse.Namespace):
    """``cls`` (RunOptions, CompareOptions) from the arguments of the same names."""
    import dataclasses

    return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)})


def _cmd_run(args: argparse.Namespace) -> int:
    from reconstruct.pipeline import CompareOptions, RunOptions, run
    from reconstruct.pipeline.options import default

    options = _options(RunOptions, args)
    if args.scan is not None and args.pixel_size is None:
        raise InputError("--scan needs --pixel-size: a scan is compared in millimetres")
    if args.scan is None and args.scan_units is not None:
        raise InputError("--scan-units needs --scan: it is the unit of the scan's coordinates")
    scan_units = args.scan_units or default(CompareOptions, "scan_units")
    resolve_output(args.output, folder=True)  # before a scan is read
    if args.scan is None:
        with _progress_display(not args.quiet and sys.stderr.isatty()) as progress:
            result = run(args.capture, args.output, options, progress=progress)
        _print_summary(result.report, result.output)
        return 0
    # With --scan the scan is read before anything else, and the comparison is written into the
    # run's staged result, so the reconstruction and its comparison are published together.
    from reconstruct.pipeline.compare_run import ScanStep

    with _progress_display(not args.quiet and sys.stderr.isatty()) as progress:
        step = ScanStep(args.scan, CompareOptions(scan_units=scan_units), progress=progress)
        result = run(args.capture, args.output, options, progress=progress, then=step)
    try:
        compared = step.result(result.output, result.files)
    except InputError:
        _print_summary(result.report, result.output)
        raise
    _print_summary(result.report, result.output)
    if compared is not None:
        _compare_summary(compared)
    return 0


def _print_summary(report, out: Path) -> None:
    """What a run made, in a few lines: size, time, unit, mesh, accuracy, warnings."""
    inputs = report.inputs
    source = f"{inputs.photographs} photographs" if hasattr(inputs, "photographs") else getattr(inputs, "format", "PTM")
    print(f"Results in {out}/ ({source}, {inputs.width}×{inputs.height}, {report.seconds:.1f} s)")
    if report.mesh is not None:
        print(f"  heights in {unit_words(report.height_unit)}; mesh: {report.mesh.vertices:,} vertices, "
              f"{report.mesh.faces:,} triangles (step {report.mesh.step})")
    chosen = getattr(report, "relighting", None)
    if chosen:
        margin = f", {chosen['margin_db']:+.1f} dB over {chosen['runner_up']}" if "margin_db" in chosen else ""
        best = chosen["scores"][0]["psnr"] if chosen.get("scores") else None
        said = f" ({chosen['chosen_by']} {best:.1f} dB{margin})" if best is not None and chosen["chosen_by"] != "asked" else ""
        print(f"  relighting basis in web/: {chosen['name']}, {chosen['encoding']}{said}")
    acc = report.accuracy
    if acc:
        n = acc.normals
        line = f"  accuracy: normals {n['mean_deg']:.2f}° mean, {n['median_deg']:.2f}° median"
        if acc.height_rmse_mm is not None:
            line += f"; height RMSE {acc.height_rmse_mm:.4f} mm"
        print(line)
    for w in report.warnings:
        print(f"  warning: {w}")
    if (out / "report.html").is_file():
        print(f"  report: {out / 'report.html'}; look at it in 3D: {_own_command()} preview {shlex.quote(str(out))}")


def _own_command() -> str:
    """This command as a shell runs it whether its environment is activated or not: the
    ``reconstruct`` script it was started as, else this interpreter with ``-m reconstruct``
    (``sys.executable`` keeps the virtual environment's path)."""
    script = Path(sys.argv[0])
    if script.name == "reconstruct" and script.is_file():
        return shlex.quote(str(script.absolute()))
    return f"{shlex.quote(sys.executable)} -m reconstruct"


def _parse_vector(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise InputError(f"--light must be three numbers x,y,z, got {text!r}")
    return values


#: The rendering parameters of each relighting mode; one given for another mode would do nothing.
_MODE_PARAMETERS = {"specular": ("kd", "ks", "exponent"), "diffuse-gain": ("gain",)}


def _relight_params(args: argparse.Namespace) -> dict[str, float]:
    """The rendering parameters given, each checked to belong to ``--mode`` (render() holds
    the defaults of the others)."""
    from ptmcore.relight import check_parameters

    params = {}
    for mode, names in _MODE_PARAMETERS.items():
        for name in names:
            value = getattr(args, name)
            if value is None:
                continue
            if args.mode != mode:
                raise InputError(f"--{name} needs --mode {mode}: it does nothing in mode {args.mode}")
            params[name] = value
    try:  # before the source is read
        check_parameters(**params)
    except ValueError as exc:
        raise InputError(f"--{exc}") from None
    return params


def _cmd_relight(args: argparse.Namespace) -> int:
    from ptmcore.published import PublishedBasis
    from ptmcore.relight import light_direction
    from reconstruct.report.figures import for_display, holds_linear_light
    from reconstruct.viewer.relighting import (
        check_sweep,
        describe,
        image_size,
        load_source,
        render,
        renders,
        sweep_lights,
        write_gif,
        write_image,
    )

    params = _relight_params(args)
    if args.sweep is not None and (args.light is not None or args.azimuth is not None):
        raise InputError("--sweep circles the light around the object at --elevation: "
                         "--light and --azimuth do not go with it")
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
    else:
        elevation = 30.0 if args.elevation is None else args.elevation
        if not 0 < elevation <= 90:
            raise InputError(f"--elevation must be in (0, 90] degrees, got {elevation}")
    resolve_output(args.output)
    ptm = load_source(args.source, args.basis, mode=args.mode)
    for w in getattr(ptm, "warnings", ()):  # a .ptm of little use (PTMFile.warnings); an .rti has none
        print(f"  warning: {w}", file=sys.stderr)
    # Every image a person sees is display-encoded: a published basis encodes its own (display);
    # a file of linear light is encoded here.
    linear = not isinstance(ptm, PublishedBasis) and holds_linear_light(args.source)
    try:
        if args.sweep is None:
            write_image(args.output, for_display(render(ptm, light, args.mode, **params), linear))
        else:
            check_sweep(args.sweep, *image_size(ptm), args.source)
            write_gif(args.output, (for_display(image, linear)
                                    for image in renders(ptm, sweep_lights(args.sweep, elevation), args.mode, **params)))
    except ValueError as exc:
        raise InputError(str(exc)) from None
    print(f"Wrote {args.output} ({describe(ptm)})")
    return 0


#: The warning filter (``PYTHONWARNINGS``) that quiets the resource tracker (see _cmd_batch).
_TRACKER_QUIET = "ignore::UserWarning:multiprocessing.resource_tracker"


def _cmd_batch(args: argparse.Namespace) -> int:
    from reconstruct.batch import run_batch
    from reconstruct.pipeline import RunOptions

    if args.scan is not None:
        raise InputError("--scan is one scan for one object: give each object's scan in the manifest's scan column")
    if args.scan_units is not None:
        raise InputError("--scan-units goes with one object's scan: give it in the manifest's scan_units column")
    if not args.sources and args.manifest is None:
        raise InputError("give capture folders, .ptm files or --manifest")
    options = _options(RunOptions, args)
    # A batch ended at once (SIGTERM, a second Ctrl-C: reconstruct.cli.signals) leaves the
    # semaphores of its cluster's queues to multiprocessing's resource tracker, a process of
    # its own that removes them and warns of them after our one-line message. The removal
    # is right; the warning, two lines of a standard-library file, is not for our users. Set
    # before run_batch starts the tracker (reconstruct.batch.scheduler), which reads it then.
    os.environ["PYTHONWARNINGS"] = ",".join(filter(None, [os.environ.get("PYTHONWARNINGS"), _TRACKER_QUIET]))
    with _batch_progress(not args.quiet and sys.stderr.isatty()) as progress:
        rows = run_batch(args.sources, args.output, options, manifest=args.manifest, scheduler=args.scheduler,
                         workers=args.workers, force=args.force, progress=progress, echo=print)
    counts = {s: sum(r.status == s for r in rows) for s in ("done", "skipped", "failed")}
    print(f"Batch in {args.output}/: {counts['done']} done, {counts['skipped']} skipped, {counts['failed']} failed "
          f"of {len(rows)}; gallery: {args.output / 'index.html'}")
    for row in rows:
        if row.status == "failed":
            print(f"  failed: {row.name}: {row.error}")
    return 1 if counts["failed"] else 0


@contextmanager
def _batch_progress(enabled: bool) -> Iterator[Callable | None]:
    """One bar over the objects: done, failed, remaining and the time left."""
    if not enabled:
        yield None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    failed = [0]
    with Progress(TextColumn("objects"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[failed]} failed"),
                  TimeRemainingColumn(), console=_stderr_console()) as bar:
        task = None

        def update(row, done: int, total: int) -> None:
            nonlocal task
            if task is None:
                task = bar.add_task("objects", total=total, failed=0)
            failed[0] += row.status == "failed"
            bar.update(task, completed=done, failed=failed[0])

        yield update


def _cmd_integrate(args: argparse.Namespace) -> int:
    from reconstruct.pipeline import RunOptions, run_normals

    options = _options(RunOptions, args)
    with _progress_display(not args.quiet and sys.stderr.isatty()) as progress:
        result = run_normals(args.normal_map, args.output, options, progress=progress)
    report = result.report
    print(f"Results in {result.output}/ ({report.inputs.width}×{report.inputs.height} normal map)")
    print(f"  heights in {unit_words(report.height_unit)}; mesh: {report.mesh.vertices:,} vertices, "
          f"{report.mesh.faces:,} triangles (step {report.mesh.step})")
    for w in report.warnings:
        print(f"  warning: {w}")
    return 0


def _cmd_lights(args: argparse.Namespace) -> int:
    from ptmcore.lp import read_lp
    from reconstruct.calibration.lightcheck import check_lights, report_text, write_polar_plot

    lights = read_lp(args.lp)
    print(report_text(check_lights(lights.directions)))
    if args.output is not None:
        write_polar_plot(args.output, lights.directions, names=[p.name for p in lights.paths], title=args.lp.name)
        print(f"Polar plot: {args.output}")
    return 0


def _cmd_check(args: argparse.Namespace) -> int:
    from reconstruct.pipeline.check import check_capture, check_text

    found = check_capture(args.capture, lp=args.lp)
    print(check_text(found))
    if args.json is not None:
        from ptmcore.atomic import atomic_write

        with atomic_write(args.json, "w") as f:
            json.dump(found.to_dict(), f, indent=2)
        print(f"Findings: {args.json}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from data_synthetic import write_capture
    from data_synthetic.capture import check_capture_size
    from reconstruct.pipeline import RunOptions, run_capture

    w, h = args.size
    check_capture_size((h, w), args.lights)
    resolve_output(args.output / "result", folder=True)
    capture_dir = args.output / "capture"
    print(f"Rendering a synthetic clay tablet ({w}×{h}, {args.lights} lights, {args.encoding}) in {capture_dir}/ ...")
    # The folders made for the capture go again if it cannot be finished (a full disk, Ctrl-C).
    new = next((p for p in [*reversed(capture_dir.absolute().parents), capture_dir.absolute()] if not p.exists()), None)
    try:
        info = write_capture(capture_dir, scene="tablet", shape=(h, w), n_lights=args.lights, encoding=args.encoding,
                             seed=args.seed)
    except BaseException:
        if new is not None:
            shutil.rmtree(new, ignore_errors=True)
        raise
    options = RunOptions(pixel_size=info.pixel_size, normals=args.normals, integrator=args.integrator)
    with _progress_display(sys.stderr.isatty()) as progress:
        result = run_capture(capture_dir, args.output / "result", options, progress=progress)
    _print_summary(result.report, result.output)
    print(f"Open {result.output / 'mesh.obj'} or mesh.ply in MeshLab, Blender or CloudCompare;")
    print(f"the synthetic photographs and their ground truth are in {capture_dir}/.")
    return 0


def _cmd_warm_up(args: argparse.Namespace) -> int:
    from reconstruct.pipeline.warmup import warm_up

    print("Compiling the numerical kernels for this machine (a few synthetic runs, about half a minute) ...",
          flush=True)
    result = warm_up(progress=lambda done, total: print(f"  {done}/{total}", flush=True))
    for failure in result.failed:
        print(f"reconstruct: warning: warm-up run failed: {failure}", file=sys.stderr)
    print(f"Done in {result.seconds:.0f} s: the next runs start without compiling.")
    return 0


def _cmd_preview(args: argparse.Namespace) -> int:
    from ptmcore.relight import light_direction
    from reconstruct.viewer.preview import (
        DEFAULT_AZIMUTH,
        DEFAULT_ELEVATION,
        build_plotter,
        has_display,
        render_screenshot,
    )
    from reconstruct.viewer.scene import load_scene

    width, height = args.size
    azimuth = DEFAULT_AZIMUTH if args.azimuth is None else args.azimuth
    elevation = DEFAULT_ELEVATION if args.elevation is None else args.elevation
    if args.light is not None and (args.azimuth is not None or args.elevation is not None):
        raise InputError("give either --light X,Y,Z or --azimuth/--elevation")
    try:  # before the scene is read
        if args.light is not None:
            x, y, z = light_direction(light=_parse_vector(args.light))
            azimuth, elevation = math.degrees(math.atan2(y, x)) % 360, math.degrees(math.asin(z))
        else:
            light_direction(azimuth_deg=azimuth, elevation_deg=elevation)
    except ValueError as exc:
        raise InputError(str(exc)) from None
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
    allow_large_images()
    commands = {"run": _cmd_run, "batch": _cmd_batch, "relight": _cmd_relight, "integrate": _cmd_integrate, "compare": _cmd_compare,
                "calibrate": _cmd_calibrate, "preview": _cmd_preview,
                "lights": _cmd_lights, "check": _cmd_check, "demo": _cmd_demo, "warm-up": _cmd_warm_up}
    with handlers():
        try:
            return commands[args.command](args)
        except InputError as exc:
            print(f"reconstruct: error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except KeyboardInterrupt:
            return interrupted()
        except BrokenPipeError:
            # Output piped into a command that stopped reading (`| head`): not an error.
            sys.stderr.close()
            return 0


if __name__ == "__main__":
    sys.exit(main())
