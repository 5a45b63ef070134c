"""The whole reconstruction of one capture: photographs → PTM → normals → height → mesh.

:func:`run` is what ``reconstruct run`` calls: :func:`run_capture` for photographs (with an
``.lp`` file, as a photometric-stereo dataset, or with spheres), :func:`run_ptm` for an existing
``.ptm`` file; :func:`run_normals` is ``reconstruct integrate``. Each composes the public stages
of :mod:`reconstruct.pipeline.capture` and :mod:`reconstruct.pipeline.stages`, which a notebook
user can call one by one (``docs/tutorial.md``).

Output folder layout (stable; later versions add files, never rename them)::

    coefficients.ptm   the PTM, HP PTM 1.2 (LRGB or RGB), as HP's PTMfitter fits it, of the
                       photographs display-encoded (sRGB) unless --ptm-encoding linear
    web/               a relighting page to publish (index.html, viewer.json, normals.png,
                       height.png) and the relighting basis chosen for the capture (--basis) in
                       Relight's format for OpenLIME (info.json, plane_*.jpg, or plane_*.dzi
                       and plane_*_files/ tiles for large images)
    normals.npy        H×W×3 float32 unit normals (x right, y up, z towards the camera)
    normals.png        16-bit RGB normal map, OpenGL convention (R=x, G=y, B=z)
    albedo.png         8-bit sRGB albedo
    height.tif         float32 height map, NaN outside the mask; unit in report.json
    mesh.ply           binary PLY: vertex colours, texture coordinates, normals
    mesh.obj           OBJ with mesh.mtl and mesh_texture.png
    mask.png           the mask used (when one was given or found)
    coefficients.rti   with --hsh: HSH of order 3 (RTIViewer's .rti)
    solid.stl          with --solid: watertight relief on a base, for 3D printing
    mesh.glb           with --glb: binary glTF with the texture
    loo_*.tif          with --loo: leave-one-out relighting error of each basis
    light_positions.csv  with near lights: the light positions used (pixels)
    lights.lp          for a capture with spheres: the light directions calibrated from them
    report.json        inputs, parameters, versions, stage times and memory, warnings, accuracy
    report.html        self-contained page for people: summary, pictures, files, parameters
    preview/           not written here: what the preview window saves; kept by later runs
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.bases import BasisChoice
from ptmcore.diskstack import is_disk_array
from ptmcore.fit import evaluate_at
from ptmcore.images import LUMA_WEIGHTS
from ptmcore.lp import write_lp
from ptmcore.nearlight import write_light_positions
from ptmcore.normals import normals_from_ptm
from ptmcore import read_ptm
from reconstruct.pipeline.capture import SPHERE_CAPTURE, Capture, load_capture, read_mask
from reconstruct.pipeline.options import RunOptions
from reconstruct.pipeline.profiling import ProgressFn, Stages
from reconstruct.pipeline.report import (
    Accuracy,
    CaptureInputs,
    LightLayout,
    MeshFacts,
    NormalMapInputs,
    PtmInputs,
    RunReport,
    json_safe,
)
from reconstruct.pipeline.staging import StagedOutput, staged_output
from reconstruct.pipeline.stages import (
    Relighting,
    basis_stage_rows,
    estimate_normals,
    fit_relighting,
    integrate_surface,
    leave_one_out,
    light_model,
    make_mesh,
    publish_relighting,
    resolve_mask,
    web_export,
    write_height,
    write_maps,
    write_meshes,
)
from reconstruct.pipeline.writer import FileWriter
from reconstruct.report import figures, outputs
from reconstruct.report.html import contact_sheet_picks
from reconstruct.report.html import write_report_html
from reconstruct.report.web import export_web_layers
from reconstruct.surface.accuracy import height_rmse, normal_accuracy
from reconstruct.surface.normalmaps import read_normal_map, shaded

#: A step after a run that writes files into its staged result, the page among them:
#: ``then(staged, page) -> names``, ``page`` the keyword arguments of the run's own page
#: (:func:`reconstruct.report.html.write_report_html`: its report, previews, thumbnails,
#: photographs), so the step's page is made from what the run holds.
Then = Callable[[StagedOutput, dict], list[str]]

__all__ = ["RunResult", "run", "run_capture", "run_normals", "run_ptm"]


@dataclass
class RunResult:
    """What a run produced: the output folder, its files (name → path) and the report."""

    output: Path
    files: dict[str, Path]
    report: RunReport


def _parameters(opt: RunOptions, step: int) -> dict:
    """report.json's ``parameters``: every option, and the mesh step used."""
    return {**json_safe({f.name: getattr(opt, f.name) for f in dataclasses.fields(opt)}), "step": step}


def _mask_source(option: Path | str | None, mask: np.ndarray | None) -> str | None:
    """How report.json describes the mask used."""
    if option == "auto":
        return "automatic" if mask is not None else "automatic (failed: whole frame)"
    return str(option) if option else None


def _surface_and_files(normals: np.ndarray, texture: np.ndarray, mask: np.ndarray | None, opt: RunOptions,
                       staged: StagedOutput, stages: Stages,
                       writer: FileWriter) -> tuple[np.ndarray, MeshFacts, list[str], Callable[[], None]]:
    """Integrate and mesh while the files every run has are written by ``writer``, each
    started as soon as its data exists; return height, mesh facts, the files' names, and the
    end of the stage "write" (which overlaps the others) to call once they are written (an
    error leaves it to ``Stages.close``)."""
    folder = staged.staging
    _, end = stages.begin("write")
    names = write_maps(folder, writer, normals=normals, texture=texture, mask=mask)
    with stages("integrate"):
        surface = integrate_surface(normals, mask, opt)
    writer.check()
    names += write_height(folder, writer, surface, opt)
    web = folder / "web"
    if (web / "info.json").is_file():  # the web page of an LRGB PTM: its normal and height layers
        names += writer.submit(["web/normals.png", "web/height.png", "web/viewer.json"], export_web_layers, web,
                               normals=normals, height=surface.height, unit=surface.unit)
    with stages("mesh"):
        mesh, step, decimation = make_mesh(surface, texture, normals, opt)
    writer.check()
    names += write_meshes(folder, writer, mesh, texture, opt)
    facts = MeshFacts(len(mesh.vertices), len(mesh.faces), surface.unit, step, surface.integrator,
                      surface.reason, json_safe(decimation))
    return surface.height, facts, names, end


def _finish(staged: StagedOutput, report: RunReport, stages: Stages, names: list[str], *,
            writer: FileWriter, end_write: Callable[[], None], then: Then | None = None,
            **html) -> dict[str, Path]:
    """Write report.html while ``writer`` finishes the files, then, once they are written (and
    ``end_write()`` ended their stage), report.json; or with ``then``, report.json and then
    ``then(staged, page)``, the step that follows and writes the page (its names join the
    result); then publish every file in one step.

    report.json comes after the page and the files so that it holds their times.
    """
    report.stages = stages.timer.stages  # the same dict: the page's own time joins it
    report.peak_rss_scope = stages.timer.scope
    writer.check()
    if then is None:
        with stages("report"):
            write_report_html(staged.staging, report=report.to_dict(), written_after=writer.names,
                              wait_for=writer.wait_for, **html)
        names = [*names, "report.html"]
    writer.wait()
    end_write()
    report.seconds = round(stages.timer.elapsed(), 3)
    report.peak_rss_mb = max((s.get("peak_rss_mb", 0.0) for s in report.stages.values()), default=None)
    outputs.write_json(staged / "report.json", report.to_dict())
    names = [*names, "report.json"]
    if then is not None:
        names += [n for n in then(staged, {"report": report.to_dict(), **html}) if n not in names]
    return staged.publish(names)


def run(
    source: str | os.PathLike,
    output: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: ProgressFn | None = None,
    fingerprint: str | None = None,
    then: Then | None = None,
) -> RunResult:
    """Reconstruct a capture folder, an ``.lp`` file or an existing ``.ptm`` file.

    See :func:`run_capture` and :func:`run_ptm`. ``then(staged, page)`` is a step that
    follows (:data:`Then`): called with the staged result before it is published, it writes
    files of its own there, the page among them, and returns their names, which are published
    with the run's in one step (``run --scan``: :class:`reconstruct.pipeline.compare_run.ScanStep`,
    whose page shows the comparison too). ``fingerprint`` is written into report.json (a batch's, to resume).
    """
    kw = {"progress": progress, "fingerprint": fingerprint, "then": then}
    if Path(source).suffix.lower() == ".ptm" and Path(source).is_file():
        return run_ptm(source, output, options, **kw)
    return run_capture(source, output, options, **kw)


def _accuracy(capture: Capture, normals: np.ndarray, height: np.ndarray, opt: RunOptions) -> Accuracy | None:
    """Errors against the capture's ground truth, when it has one."""
    if capture.truth is None:
        return None
    rmse = height_rmse(height, capture.truth) if opt.pixel_size else None
    return Accuracy(capture.truth_source, normal_accuracy(normals, capture.truth), rmse)


def _capture_inputs(capture: Capture, mask: np.ndarray | None, opt: RunOptions) -> CaptureInputs:
    h, w = capture.shape
    return CaptureInputs(
        str(capture.source.resolve()), str(capture.lp_path.resolve()) if capture.lp_path else None,
        capture.layout, len(capture.lights), w, h, capture.stack.bit_depth, _mask_source(opt.mask, mask),
        "file" if is_disk_array(capture.stack.luminance) else "memory")


def _relight_only(loaded: Capture, opt: RunOptions, staged: StagedOutput, stages: Stages, writer: FileWriter,
                  relit: Relighting | None, web_names: list[str], choice: BasisChoice, *,
                  fingerprint: str | None, then: Then | None) -> RunResult:
    """The rest of a run of ``--outputs relight``: ``coefficients.ptm`` (if not yet written)
    and the report; no normals, height or meshes."""
    h, w = loaded.shape
    thumbnails = {k: figures.stack_thumbnail(loaded.stack, k) for k in contact_sheet_picks(len(loaded.lights))}
    inputs = _capture_inputs(loaded, loaded.mask, opt)
    loaded.stack = None
    if relit is None:
        with stages("ptm", len(loaded.lights)) as advance:
            relit = fit_relighting(loaded.lights, opt, staged.staging, progress=advance,
                                   corrections=loaded.corrections)
    _, end_write = stages.begin("write")
    report = RunReport(
        inputs, _parameters(opt, 0), "", None, {}, "", [*loaded.warnings, *relit.warnings],
        lights=LightLayout.from_rank(loaded.rank), light_model=light_model(loaded.near, (h, w), opt),
        intensities=json_safe(loaded.intensities), ptm=relit.summary,
        capture_checks=json_safe(loaded.checks), fingerprint=fingerprint, relighting=choice.to_dict(),
    )
    files = _finish(staged, report, stages, [*relit.names, *web_names], writer=writer, end_write=end_write,
                    then=then, photographs=list(zip(loaded.lights.paths, loaded.lights.directions)),
                    thumbnails=thumbnails)
    return RunResult(staged.output, files, report)


def run_capture(
    capture: str | os.PathLike,
    output: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: ProgressFn | None = None,
    fingerprint: str | None = None,
    then: Then | None = None,
) -> RunResult:
    """Reconstruct one capture and write the output folder.

    Parameters
    ----------
    capture : path
        A capture folder (photographs and one ``.lp`` file), an ``.lp`` file, a
        photometric-stereo dataset folder, or a folder of photographs with glossy spheres.
    output : path
        Output folder; created if needed, or where it points if it is a symbolic link. Files
        are written to a staging folder beside it and moved into place only when every stage
        succeeded, so a failed run (a full disk among the causes) leaves earlier results
        untouched and nothing half-written (:func:`reconstruct.pipeline.staging.staged_output`).
    options : RunOptions, optional
    progress : callable, optional
        ``progress(stage, done, total)`` as work advances.
    then : callable, optional
        A step that follows and writes the page (:data:`Then`; :func:`run`).
    fingerprint : str, optional
        Written into report.json: a batch's fingerprint of the inputs and options.

    Returns
    -------
    RunResult

    Raises
    ------
    InputError
        For any problem with the inputs or the output folder.
    """
    opt = options or RunOptions()
    with Stages(progress) as stages, staged_output(output) as staged, FileWriter(opt.threads) as writer:
        loaded = load_capture(capture, opt, stages=stages, scratch=staged.staging)
        (h, w), warnings = loaded.shape, loaded.warnings
        relit = None
        if loaded.fits is not None:
            # Fitted while decoding: the viewers' files are written now, so that their
            # coefficients (0.65 GB at 24 megapixels, 2.6 GB more with --hsh) are not held
            # through the normals.
            with stages("ptm", len(loaded.lights)) as advance:
                relit = fit_relighting(loaded.lights, opt, staged.staging, progress=advance, fits=loaded.fits)
            loaded.fits = None
        with stages("basis", basis_stage_rows(opt, h)) as advance:
            web_names, choice = publish_relighting(loaded, opt, staged.staging, progress=advance)
        if opt.outputs == "relight":
            return _relight_only(loaded, opt, staged, stages, writer, relit, web_names, choice,
                                 fingerprint=fingerprint, then=then)
        with stages("normals", h) as advance:
            found = estimate_normals(loaded, opt, progress=advance)
        if found.undetermined:
            warnings.append(f"{found.undetermined} pixels ({found.undetermined / (h * w):.2%}) had too few lit, "
                            "unsaturated photographs to determine a normal; their normal is set to (0, 0, 1)")
        with stages("albedo"):
            texture, albedo_scale = outputs.albedo_texture(loaded.stack.chroma, found.albedo, threads=opt.threads)
            mask = resolve_mask(opt.mask, loaded.mask, lambda: loaded.stack.chroma * found.albedo[..., None],
                                found.normals, warnings)
        loo = None
        if opt.loo:
            with stages("loo", (5 + (len(loaded.lights.directions) > 16)) * h) as advance:
                loo = leave_one_out(loaded, mask, staged.staging, threads=opt.threads, progress=advance)
        inputs = _capture_inputs(loaded, mask, opt)
        # The page's contact sheet from the decoded photographs: decoding eight 24-megapixel
        # JPEGs again for it cost a second.
        thumbnails = {k: figures.stack_thumbnail(loaded.stack, k) for k in contact_sheet_picks(len(loaded.lights))}
        loaded.stack = None  # by far the largest array; no later stage needs it
        if relit is None:  # a second pass over the files, once the stack is released
            with stages("ptm", len(loaded.lights)) as advance:
                relit = fit_relighting(loaded.lights, opt, staged.staging, progress=advance,
                                       corrections=loaded.corrections)
        warnings += relit.warnings
        height, mesh, names, end_write = _surface_and_files(found.normals, texture, mask, opt, staged, stages, writer)
        report = RunReport(
            inputs, _parameters(opt, mesh.step), mesh.unit, mesh, {}, "", warnings,
            accuracy=_accuracy(loaded, found.normals, height, opt), albedo_scale=albedo_scale,
            lights=LightLayout.from_rank(loaded.rank), light_model=light_model(loaded.near, (h, w), opt),
            intensities=json_safe(loaded.intensities), reflectance_lobe=found.lobe, ptm=relit.summary, leave_one_out=loo,
            capture_checks=json_safe(loaded.checks), fingerprint=fingerprint, relighting=choice.to_dict(),
        )
        if loaded.near is not None:
            write_light_positions(staged / "light_positions.csv", [p.name for p in loaded.lights.paths],
                                  loaded.near.positions)
            names.append("light_positions.csv")
        if loaded.layout == SPHERE_CAPTURE:
            # What the spheres gave: copied beside the photographs, it makes the capture an
            # ordinary one for other tools (RTIBuilder) and later runs.
            write_lp(staged / "lights.lp", [p.name for p in loaded.lights.paths], loaded.lights.directions)
            names.append("lights.lp")
        loo_names = [f"loo_{b}.tif" for b in (loo or {}).get("rms_levels", {})]
        files = _finish(staged, report, stages, [*relit.names, *web_names, *loo_names, *names], writer=writer,
                        end_write=end_write,
                        then=then,
                        photographs=list(zip(loaded.lights.paths, loaded.lights.directions)),
                        thumbnails=thumbnails,
                        previews=figures.previews(normals=found.normals, height=height, albedo=texture))
    return RunResult(staged.output, files, report)


def _ptm_normals_and_texture(ptm, threads: int | None) -> tuple[np.ndarray, np.ndarray]:
    """A PTM's maxima as normals, and its colour under the light of its maximum (its albedo in
    the file's own encoding) as an 8-bit texture."""
    coef = ptm.coefficients
    # RGB format: one polynomial per channel, and luminance is linear in them.
    luminance = coef if coef.ndim == 3 else np.einsum("hwck,c->hwk", coef, LUMA_WEIGHTS)
    normals = normals_from_ptm(luminance, threads=threads)
    lu, lv = normals[..., 0], normals[..., 1]
    if ptm.rgb is not None:
        top = evaluate_at(luminance, lu, lv)[..., None] * ptm.rgb / np.float32(255)
    else:
        top = evaluate_at(coef, lu, lv)
    return normals, np.clip(np.round(top), 0, 255).astype(np.uint8)


def run_ptm(
    ptm_path: str | os.PathLike,
    output: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: ProgressFn | None = None,
    fingerprint: str | None = None,
    then: Then | None = None,
) -> RunResult:
    """Normals, height and meshes from an existing ``.ptm`` file (no photographs needed).

    The normals are the PTM's maxima (photometric stereo needs the photographs); the texture
    is the PTM's colour under the light of its maximum, i.e. its albedo in the file's own
    encoding. Parameters and output folder as :func:`run_capture`.
    """
    opt = dataclasses.replace(options or RunOptions(), normals="ptm")
    ptm_path = Path(ptm_path)
    warnings = ["normals come from the PTM's maximum: a .ptm file carries no photographs for photometric stereo"]
    with Stages(progress) as stages, staged_output(output) as staged, FileWriter(opt.threads) as writer:
        with stages("decode"):
            ptm = read_ptm(ptm_path)
        warnings += ptm.warnings
        h, w = ptm.coefficients.shape[:2]
        mask = read_mask(opt.mask, (h, w), "the PTM") if opt.mask is not None and opt.mask != "auto" else None
        with stages("normals", h):
            normals, texture = _ptm_normals_and_texture(ptm, opt.threads)
        mask = resolve_mask(opt.mask, mask, texture.astype(np.float32) / 255, normals, warnings)
        # A run's own coefficients.ptm may hold linear light (its report.json says): the page encodes it.
        encoding = "linear" if figures.holds_linear_light(ptm_path) else "srgb"
        web = [] if ptm.rgb is None else web_export(staged.staging, ptm.coefficients, ptm.rgb, opt.pixel_size,
                                                    encoding)
        height, mesh, names, end_write = _surface_and_files(normals, texture, mask, opt, staged, stages, writer)
        inputs = PtmInputs(str(ptm_path.resolve()), ptm.format, w, h, _mask_source(opt.mask, mask))
        report = RunReport(inputs, _parameters(opt, mesh.step), mesh.unit, mesh, {}, "", warnings,
                           fingerprint=fingerprint)
        # The page relights a subsample of the source .ptm: read again, only that is decoded.
        files = _finish(staged, report, stages, [*web, *names], writer=writer, end_write=end_write, then=then,
                        previews=figures.previews(normals=normals, height=height, albedo=texture))
    return RunResult(staged.output, files, report)


def run_normals(
    normal_map: str | os.PathLike,
    output: str | os.PathLike,
    options: RunOptions | None = None,
    *,
    progress: ProgressFn | None = None,
) -> RunResult:
    """Height map and meshes from a normal map made elsewhere (``reconstruct integrate``).

    The map is read by :func:`reconstruct.surface.normalmaps.read_normal_map`; pixels without a
    valid normal are outside the object unless a mask says otherwise. The texture is a grey
    shaded rendering of the normals. Parameters and output folder as :func:`run_capture`.
    """
    opt = options or RunOptions()
    path = Path(normal_map)
    warnings: list[str] = []
    with Stages(progress) as stages, staged_output(output) as staged, FileWriter(opt.threads) as writer:
        with stages("decode"):
            normals = read_normal_map(path)
        h, w = normals.shape[:2]
        valid = np.isfinite(normals[..., 0])
        if opt.mask == "auto":
            mask = resolve_mask("auto", None, shaded(normals).astype(np.float32) / 255, np.nan_to_num(normals), warnings)
        elif opt.mask is not None:
            mask = read_mask(opt.mask, (h, w), "the normal map")
            if (mask & ~valid).any():
                warnings.append(f"{int((mask & ~valid).sum())} pixels inside the mask have no valid normal")
        else:
            mask = None if valid.all() else valid
        height, mesh, names, end_write = _surface_and_files(normals, shaded(normals), mask, opt, staged, stages, writer)
        source = _mask_source(opt.mask, mask) if opt.mask else ("valid normals" if mask is not None else None)
        report = RunReport(NormalMapInputs(str(path.resolve()), w, h, source), _parameters(opt, mesh.step),
                           mesh.unit, mesh, {}, "", warnings)
        files = _finish(staged, report, stages, names, writer=writer, end_write=end_write,
                        previews=figures.previews(normals=normals, height=height))
    return RunResult(staged.output, files, report)
