"""``report.html``: one self-contained page that shows a person what a run made.

It reads top to bottom as a condition report would: a summary in words (the object, its size
and relief depth, how the surface was made, its accuracy when known, and the warnings, first);
then the pictures (relit renderings — of the relighting basis published in ``web/`` when the
run chose one, else of the PTM —, specular enhancement, albedo, normal map, height map and
its profile, the textured mesh at a stated vertical exaggeration, the lights, the photographs,
the comparison with a scan); then the files written, each with what it is and what opens it;
and last, folded, the technical parameters and timings.

The page is built from an output folder (``report.json``, ``comparison.json`` and the images
and maps beside them) plus, for the contact sheet and the lights, the photographs and their
light directions. Every picture is embedded as a ``data:`` URI (JPEG for photographic
pictures) and the style is inline, so the file opens anywhere (a USB stick, no network); the
only links are to the output files beside it. A picture that cannot be made (an unreadable
mesh, no matplotlib, an unreadable photograph) becomes a note in its place and a warning:
the page is always written.

The maps are subsampled once, first (:func:`reconstruct.report.figures.previews`, to about a
thousand pixels), and every picture is made from the subsamples; a caller that holds the maps
(the pipeline) passes them, and the photographs' thumbnails, so that nothing large is read
again. The mesh is drawn in a second thread while the other pictures are made: in software
(:mod:`reconstruct.report.raster`, compiled code that leaves the GIL to them), with no OpenGL
context to start.
"""

from __future__ import annotations

import base64
import html
import json
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime, timezone
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.relight import light_angles
from ptmcore.resources import cpu_count

from reconstruct.report import figures, plots, rendering, summary

#: At most this many photographs on the contact sheet.
CONTACT_SHEET = 8

_STYLE = """
body{font:15px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;color:#222;background:#f4f4f2;margin:0}
main{max-width:1100px;margin:0 auto;padding:12px 20px 40px;background:#fff}
h1{font-size:1.5em;margin:.4em 0 .1em}h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:1.6em}
.meta{color:#555;margin:0 0 .6em}nav a{margin-right:.8em}
table{border-collapse:collapse;margin:.4em 0;font-size:.92em}
td,th{border:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#f0f0ee}td.num{text-align:right;font-variant-numeric:tabular-nums}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(var(--min,320px),1fr));gap:10px}
.sheet{--min:120px}figure{margin:0}figure img{width:100%;height:auto;border:1px solid #ddd;display:block}
figcaption{font-size:.85em;color:#444;margin-top:2px}
.note{background:#eef3fb;border-left:4px solid #6a8fd0;padding:6px 10px;margin:.5em 0}
.warnings{background:#fff4e0;border:1px solid #e09a1a;border-left:6px solid #e09a1a;padding:4px 12px;margin:.6em 0}
.warnings h3{margin:.3em 0;color:#8a4b00}.warnings ul{margin:.2em 0 .4em;padding-left:20px}
.ok{color:#2d6a2d}h3{font-size:1.05em;margin:1.2em 0 .3em}
table.summary{font-size:1em;width:100%}table.summary th{width:9em;background:none;border:none;border-bottom:1px solid #eee}
table.summary td{border:none;border-bottom:1px solid #eee}
.tables{display:flex;flex-wrap:wrap;gap:0 28px;align-items:flex-start}
figure.wide{max-width:900px}figure.polar{max-width:620px}
table.files td:first-child{white-space:nowrap}code{font-size:.95em}
details{margin:.6em 0}summary{cursor:pointer;font-weight:600}
"""


def _esc(value: object) -> str:
    return html.escape(str(value), quote=True)


def _fmt(value: object) -> str:
    """A value as a short readable string: numbers to 4 significant digits, lists compactly."""
    if isinstance(value, bool) or value is None:
        return "—" if value is None else ("yes" if value else "no")
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        text = ", ".join(_fmt(v) for v in value)
        return text if len(text) <= 160 else text[:157] + "…"
    if isinstance(value, dict):
        return json.dumps(value, ensure_ascii=False)[:160]
    return str(value)


def _flatten(data: dict, prefix: str = "") -> Iterable[tuple[str, object]]:
    """Nested dictionaries as ``("a.b", value)`` rows."""
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            yield from _flatten(value, name + ".")
        else:
            yield name, value


def _table(rows: Iterable[Sequence[object]], header: Sequence[str] | None = None) -> str:
    head = "<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in header) + "</tr>" if header else ""
    body = []
    for row in rows:
        cells = []
        for k, value in enumerate(row):
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
            cls = ' class="num"' if numeric and k > 0 else ""
            cells.append(f"<td{cls}>{_esc(_fmt(value))}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table>{head}{''.join(body)}</table>"


def _data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def _img(data: bytes, mime: str, alt: str) -> str:
    return f'<img src="{_data_uri(data, mime)}" alt="{_esc(alt)}">'


def _figure(data: bytes, mime: str, caption: str, cls: str = "") -> str:
    kind = f' class="{cls}"' if cls else ""
    return f"<figure{kind}>{_img(data, mime, caption)}<figcaption>{_esc(caption)}</figcaption></figure>"


def _note(text: str) -> str:
    return f'<p class="note">{_esc(text)}</p>'


class _Folder:
    """Files of the report: the folder being written first, then earlier output folders.

    ``wait_for(name)``, when given, is called before a file is looked for: files the caller is
    still writing in other threads (:class:`reconstruct.pipeline.writer.FileWriter`).
    """

    def __init__(self, folder: Path, also: Sequence[Path], wait_for: Callable[[str], None] | None = None,
                 pending: Sequence[str] = ()) -> None:
        self.places = [folder, *also]
        self.wait_for = wait_for
        self.pending = set(pending)

    def has(self, name: str) -> bool:
        """Whether the file is there or being written, without waiting for it."""
        return name in self.pending or any((p / name).is_file() for p in self.places)

    def find(self, name: str) -> Path | None:
        if self.wait_for is not None:
            self.wait_for(name)
        return next((p / name for p in self.places if (p / name).is_file()), None)

    def json(self, name: str) -> dict | None:
        path = self.find(name)
        return json.loads(path.read_text(encoding="utf-8")) if path else None


def _attempt(make: Callable[[], object], what: str, notes: list[str], fallback=None):
    """``make()``, or ``fallback`` with a warning when it fails (``fallback(message)`` when
    callable: a note in place of a picture)."""
    try:
        return make()
    except Exception as exc:  # noqa: BLE001 - a picture must never fail the run, whatever the cause
        message = f"no {what}: {exc}"
        notes.append(message)
        return fallback(message) if callable(fallback) else fallback


def _photographs_from_report(report: dict | None) -> list[tuple[Path, np.ndarray]] | None:
    """The photographs named by the run's ``.lp`` file, when it is still where it was."""
    lp = ((report or {}).get("inputs") or {}).get("lp")
    if not lp or not Path(lp).is_file():
        return None
    from ptmcore.lp import read_lp

    lights = read_lp(lp)
    return list(zip(lights.paths, lights.directions))


def contact_sheet_picks(n: int) -> list[int]:
    """Indices of the photographs on the contact sheet of ``n``: at most :data:`CONTACT_SHEET`,
    evenly spread, the first and the last included."""
    return sorted(set(np.linspace(0, n - 1, min(n, CONTACT_SHEET)).round().astype(int).tolist()))


def _contact_sheet(photographs: Sequence[tuple[Path, np.ndarray]],
                   thumbnails: Mapping[int, np.ndarray] | None = None) -> str:
    n = len(photographs)
    picks = contact_sheet_picks(n)
    thumbs = {k: v for k, v in (thumbnails or {}).items() if k in picks and v is not None}
    missing = [k for k in picks if k not in thumbs]
    if missing:
        # Entropy decoding dominates even at an eighth of the size (0.15 s for a 24-megapixel
        # JPEG), and Pillow leaves the GIL while it decodes: the photographs go in parallel.
        with ThreadPoolExecutor(max_workers=min(len(missing), cpu_count(), 4)) as pool:
            thumbs.update(zip(missing, pool.map(lambda k: figures.photograph_thumbnail(photographs[k][0]), missing)))
    items = []
    for k in picks:
        path, light = photographs[k]
        az, el = light_angles(light)
        items.append(_figure(figures.encode(thumbs[k], "JPEG"), "image/jpeg",
                             f"{Path(path).name} — light az {az:.0f}°, el {el:.0f}°"))
    shown = f"{len(picks)} of {n} photographs" if len(picks) < n else f"all {n} photographs"
    return f"<p>{_esc(shown)}; azimuth 0° = light from the right, 90° = from the top.</p>" \
           f'<div class="grid sheet">{"".join(items)}</div>'


def _previews(files: _Folder, report: dict, notes: list[str]) -> figures.Previews:
    """The subsamples of the folder's normals, heights (memory-mapped: only the rows taken are
    read) and albedo (a PNG is decoded whole: only when the caller holds no previews); a map
    that cannot be read is left out with a note."""
    maps = {}
    for key, name in (("normals", "normals.npy"), ("height", "height.tif")):
        path = files.find(name)
        if path is not None:
            maps[key] = _attempt(lambda path=path: figures.map_array(path), f"{name} subsample", notes)
    albedo = files.find("albedo.png")
    # A normal map from elsewhere has no albedo (its albedo.png is a shaded rendering).
    if albedo is not None and "normal_map" not in (report.get("inputs") or {}):
        from ptmcore.images import read_image

        maps["albedo"] = _attempt(lambda: read_image(albedo), "albedo.png", notes)
    return _attempt(lambda: figures.previews(**maps), "maps", notes, figures.Previews())


def _ptm_preview(files: _Folder, report: dict, notes: list[str]):
    """A subsample of the run's PTM (its own, or the source .ptm of a run from one), or None."""
    ptm = files.find("coefficients.ptm")
    source = (report.get("inputs") or {}).get("ptm")
    if ptm is None and source and Path(source).is_file():
        ptm = Path(source)  # a run from a .ptm file: relight the file itself
    if ptm is None:
        return None
    from ptmcore.ptmfile import read_ptm

    # Only a subsample is decoded: for a run from a .ptm file this re-reads the source file,
    # at the cost of the subsample.
    return _attempt(lambda: (ptm.name, read_ptm(ptm, max_side=figures.RELIT_SIDE)), f"renderings of {ptm.name}",
                    notes)


def _published_preview(files: _Folder, notes: list[str]):
    """The relighting basis the run published in ``web/`` (the one chosen for the capture), read
    at the pictures' size, or None (none published, or unreadable: a note says so)."""
    from reconstruct.report.webread import published_folder, read_relightable

    def read():
        info = files.find("web/info.json")
        web = None if info is None else published_folder(info.parent.parent)
        return None if web is None else read_relightable(web, max_side=figures.RELIT_SIDE)

    return _attempt(read, "renderings of web/", notes)


def _basis_caption(report: dict, basis) -> str:
    """The published basis in words, and how it was chosen, from report.json's ``relighting``:
    ``"HSH order 3 (chosen by leave-one-out: 1.2 dB better than rbf (srgb))"``."""
    chosen = report.get("relighting") or {}
    words = figures.basis_words(basis.name or basis.type)
    how = chosen.get("chosen_by") if chosen.get("name") in (None, basis.name) else None
    if how == "asked":
        words += " (as asked: --basis)"
    elif isinstance(how, str) and how:
        margin, runner = chosen.get("margin_db"), chosen.get("runner_up")
        if isinstance(margin, (int, float)) and isinstance(runner, str):
            words += f" (chosen by {how}: {margin:.1f} dB better than {runner})"
        else:
            words += f" (chosen by {how})"
    if basis.encoding == "linear":
        words += ", fitted to linear light and shown sRGB-encoded"
    return words


def _relit(report: dict, previews: figures.Previews, ptm, published=None) -> str:
    linear = figures.linear_ptm(report)
    if published is not None:
        images = figures.relit_from_basis(published, figures.RELIT_SIDE)
        how = f"The relighting basis published in web/, {_basis_caption(report, published)}, as its page shows it"
    elif ptm is not None:
        name, small = ptm
        images = figures.relit_from_ptm(small, linear=linear)
        how = f"RTIViewer's default rendering of {name}" + (
            " (a PTM of linear light, from 16-bit photographs: shown sRGB-encoded)" if linear else "")
    elif previews.normals is not None:
        # Previews hold no albedo for a normal map made elsewhere (its albedo.png is a rendering).
        images = figures.relit_lambertian(previews.normals, previews.albedo)
        how = "Lambertian shading of the normals" + (" and albedo" if previews.albedo is not None
                                                     else " (uniform grey)")
    else:
        return _note("no relit renderings: neither coefficients.ptm nor normals.npy is in the folder")
    items = "".join(_figure(figures.encode(img, "JPEG"), "image/jpeg", label) for label, img in images)
    return (f"<p>{_esc(how)}, under six lights (elevation above the object plane). Raking light shows "
            f"the relief: marks, tool traces and inscriptions.</p>" f'<div class="grid">{items}</div>')


def _surface(report: dict, previews: figures.Previews, ptm, notes: list[str]) -> str:
    """Specular enhancement, albedo and normal map, side by side."""
    parts = []
    if ptm is not None:
        def specular() -> str:
            image = figures.specular_from_ptm(ptm[1], linear=figures.linear_ptm(report))
            label, _, _ = figures.SPECULAR_LIGHT
            return _figure(figures.encode(image, "JPEG"), "image/jpeg",
                           f"specular enhancement (RTIViewer's, light {label}): surface shape without colour")

        parts.append(_attempt(specular, "specular enhancement", notes, _note))
    if previews.albedo is not None:
        albedo = figures.fit_side(previews.albedo, figures.MAX_WIDTH // 2)
        parts.append(_figure(figures.encode(albedo, "JPEG"), "image/jpeg",
                             "albedo: the surface's colour without shading (sRGB)"))
    if previews.normals is not None:
        def normal_map() -> str:
            image = figures.fit_side(figures.normal_colors(previews.normals), figures.MAX_WIDTH // 2)
            return _figure(figures.encode(image), "image/png",
                           "normal map (R = x right, G = y up, B = z towards the camera)")

        parts.append(_attempt(normal_map, "normal map picture", notes, _note))
    return f'<div class="grid">{"".join(parts)}</div>' if parts else _note("no surface pictures")


def _height(report: dict, previews: figures.Previews, notes: list[str]) -> str:
    if previews.height is None:
        return _note("no height map in the folder")
    unit = report.get("height_unit", "pixel")
    pixel_size = figures.display_pixel_size(report)
    row = plots.profile_row(previews.height)

    def height_map() -> str:
        png = figures.height_figure(previews.height, previews.stride, unit, pixel_size, profile=row)
        bar = "scale bar in mm" if pixel_size else "scale bar in pixels (no pixel size given)"
        return _figure(png, "image/png", f"height map in {summary.unit_words(unit)}; {bar}; "
                                         "the dashed line is where the profile below is taken", "wide")

    def profile() -> str:
        png = plots.profile_figure(previews.height, row, previews.stride, unit, pixel_size)
        return _figure(png, "image/png", f"height profile along row {row * previews.stride} of the height map "
                                         "(the dashed line), left to right", "wide")

    return _attempt(height_map, "height map picture", notes, _note) + _attempt(profile, "height profile", notes, _note)


def _mesh(files: _Folder, report: dict, previews: figures.Previews, extent: summary.Extent | None,
          notes: list[str]) -> str:
    # The run's own count when it has one: then mesh.ply is read only to be drawn whole (it
    # may still be being written).
    faces = (report.get("mesh") or {}).get("faces")

    def whole() -> bool:
        return previews.height is None or (faces is not None and faces <= figures.MAX_RENDER_FACES)

    mesh = None
    if faces is None or whole():
        mesh = files.find("mesh.ply")
        if mesh is None:
            return _note("no mesh.ply in the folder")
        faces = faces if faces is not None else figures.ply_face_count(mesh)
    elif not files.has("mesh.ply"):
        return _note("no mesh.ply in the folder")
    # x, y and z share a unit only with a pixel size on an orthographic camera, or in pixels.
    same_units = figures.display_pixel_size(report) or report.get("height_unit") == "pixel"
    factor = figures.vertical_exaggeration(extent.width, extent.height, extent.depth) if extent and same_units else 1
    scale = "true scale" if factor == 1 else f"vertical exaggeration ×{factor}: heights drawn {factor} times deeper"

    def make() -> str:
        if whole():
            image = figures.mesh_render(mesh, exaggeration=factor)
            what = "mesh.ply"
        else:
            sub, k = figures.thin(previews.height, figures.MESH_RENDER_SIDE)
            texture = None if previews.albedo is None else previews.albedo[::k, ::k]
            stride = previews.stride * k
            image = figures.mesh_render(figures.surface_from_height(sub, stride, figures.display_pixel_size(report),
                                                                    texture), exaggeration=factor)
            what = f"mesh.ply's surface ({faces:,} triangles) sampled every {stride} pixels"
        return _figure(figures.encode(image, "JPEG", 90), "image/jpeg",
                       f"{what}, with its colours, seen obliquely from the front ({scale})", "wide")

    return _attempt(make, "mesh render", notes, _note)


def _lights(photographs: Sequence[tuple[str | os.PathLike, np.ndarray]], notes: list[str]) -> str:
    def make() -> str:
        from reconstruct.calibration.lightcheck import polar_plot_png

        directions = np.array([d for _, d in photographs], dtype=np.float64)
        png = polar_plot_png(directions, names=[str(p) for p, _ in photographs], size=620)
        return _figure(png, "image/png", f"the {len(photographs)} lights seen from above the object, each labelled "
                                         "by its photograph; centre = overhead, rim = grazing; 0° = light from the "
                                         "right, 90° = from the top", "polar")

    return _attempt(make, "light plot", notes, _note)


def _comparison(files: _Folder, comparison: dict, notes: list[str]) -> str:
    stats = comparison.get("statistics_mm") or {}
    labels = {"rms": "RMS distance", "mean": "mean (signed)", "std": "standard deviation",
              "median_abs": "median |distance|", "p95_abs": "95% of |distances| below", "max_abs": "largest |distance|"}
    rows = [(label, f"{stats[key]:.3g} mm") for key, label in labels.items() if stats.get(key) is not None]
    parts = [f'<p>Scan {_esc(Path(comparison.get("scan", "")).name)} aligned onto the reconstruction; '
             f'{_esc(comparison.get("sign_convention", ""))}.</p>', _table(rows, ("scan → reconstruction", ""))]
    for name, fmt, caption in (("histogram.png", "PNG", "histogram of the signed distances"),
                               ("overlay.png", "JPEG", "aligned pair and distance map")):
        path = files.find(name)
        if path is not None:
            parts.append(_attempt(lambda path=path, fmt=fmt, caption=caption: _figure(
                figures.downscale_file(path, fmt=fmt), f"image/{fmt.lower()}", caption, "wide"), name, notes, _note))
        elif name == "overlay.png":
            parts.append(_note("no overlay.png (see the warnings)"))
    return "".join(parts)


def _timings(report: dict | None, comparison: dict | None) -> str:
    rows = []
    for prefix, doc in (("", report), ("compare: ", comparison)):
        for name, s in ((doc or {}).get("stages") or {}).items():
            rows.append((prefix + name, s.get("seconds"), s.get("peak_rss_mb")))
    if not rows:
        return _note("no stage timings recorded")
    # The files are written in the background beside the later stages: their stage "write"
    # overlaps the others, so the run's own wall time is the total, when report.json has it.
    rows = [(f"{name} (in the background)" if name == "write" else name, t, m) for name, t, m in rows]
    run_stages = (report or {}).get("stages") or {}
    seconds = (report or {}).get("seconds")
    if seconds is not None:
        total = seconds + sum(s.get("seconds") or 0 for s in ((comparison or {}).get("stages") or {}).values())
        label = "total (wall time)"
    else:
        total = sum(r[1] or 0 for r in rows)
        label = "total so far (files still being written)" if run_stages and "write" not in run_stages else "total"
    scope = (report or {}).get("peak_rss_scope", "per stage")
    return _table([*rows, (label, round(total, 3), None)], ("stage", "wall time (s)", f"peak memory (MiB, {scope})"))


def _given(rows: Iterable[tuple[str, object]]) -> list[tuple[str, object]]:
    """Rows with a value: an option not given has no row (it is not a missing result)."""
    return [(k, v) for k, v in rows if v is not None and v != [] and v != {}]


def _parameters(report: dict | None, comparison: dict | None) -> str:
    """Every technical value of the run and the comparison, in tables (the page folds them)."""
    blocks = []
    if report is not None:
        options = [(f"--{k.replace('_', '-')}", v) for k, v in (report.get("parameters") or {}).items()]
        results = list(_flatten({"mesh": report.get("mesh") or {}}))
        for key in ("albedo_scale", "lights", "light_model", "reflectance_lobe", "ptm", "intensities", "leave_one_out"):
            if report.get(key) is not None:
                results += _flatten({key: report[key]})
        blocks += [("Inputs", _table(_given((report.get("inputs") or {}).items()), ("input", "value"))),
                   ("Options (as on the command line; those not given are left out)",
                    _table(_given(options), ("option", "value"))),
                   ("Results", _table(_given(results), ("value", "")))]
        if report.get("accuracy"):
            blocks.append(("Accuracy against ground truth", _table(_flatten(report["accuracy"]), ("measure", "value"))))
    if comparison is not None:
        tables = [_table((comparison.get("statistics_mm") or {}).items(), ("scan → reconstruction", "mm"))]
        if comparison.get("reverse_statistics_mm"):
            tables.append(_table(comparison["reverse_statistics_mm"].items(), ("reconstruction → scan", "mm")))
        alignment = {k: v for k, v in (comparison.get("alignment") or {}).items()
                     if k != "transform_scan_to_reconstruction"}
        tables.append(_table(alignment.items(), ("alignment", "")))
        if comparison.get("tolerance"):
            tables.append(_table(comparison["tolerance"].items(), ("tolerance", "")))
        blocks.append(("Comparison with the scan", f'<div class="tables">{"".join(tables)}</div>'))
    blocks.append(("Stage timings", _timings(report, comparison)))
    versions = (report or comparison or {}).get("versions") or {}
    if versions:
        blocks.append(("Software versions", _table(versions.items(), ("package", "version"))))
    body = "".join(f"<h3>{_esc(name)}</h3>{content}" for name, content in blocks)
    return f"<details><summary>Show the technical parameters, timings and versions</summary>{body}</details>"


def _files(folder: Path, written_after: Sequence[str], also: Sequence[Path]) -> str:
    rows = "".join(f'<tr><td><a href="{_esc(quote(e.name))}">{_esc(e.name)}</a></td><td>{_esc(e.what)}</td>'
                   f"<td>{_esc(e.how)}</td></tr>" for e in summary.file_entries(folder, written_after))
    elsewhere = "".join(f"<p>The reconstruction's own files are in {_esc(p)}.</p>" for p in also)
    return ("<p>In the folder of this page; the links open them where the browser can.</p>"
            f'<table class="files"><tr><th>file</th><th>what it is</th><th>open it with</th></tr>{rows}</table>'
            + elsewhere)


def capture_check_rows(checks: dict) -> list[tuple[str, str]]:
    """The findings of ``report.json``'s ``capture_checks`` (and of ``reconstruct check``) in
    words, one row each: colour, drift, exposure, stray light, the ambient frame, the flat field."""
    rows = []
    if checks.get("colour"):
        rows.append(("Colour", str(checks["colour"])))
    drift = checks.get("drift")
    if drift:
        moved = f"largest displacement {drift['largest_px']:.2f} px ({drift['largest_photograph']})"
        measured, total = drift.get("measured"), len(drift.get("photographs", ()))
        if measured is not None and measured < total:
            moved += f"; {total - measured} of {total} photographs not measured (too little detail, or details moved by the shading)"
        if measured == 0:
            moved, state = "not measured", "too little detail to tell the camera's move from the shading's"
        elif drift.get("aligned"):
            state = "aligned onto one frame before fitting"
        elif drift["largest_px"] > drift["threshold_px"]:
            state = "not aligned (--align off)"
        else:
            state = f"steady (under {drift['threshold_px']:g} px)"
        rows.append(("Camera drift", f"{moved}: {state}"))
    exposure = checks.get("exposure")
    if exposure is not None:
        parts = [f"{len(exposure[key])} {what}" for key, what in
                 (("clipped", "with over 1 % clipped pixels"), ("dark", "mostly black"),
                  ("odd_brightness", "brighter or darker than their light explains")) if exposure.get(key)]
        rows.append(("Exposure", "; ".join(parts) if parts else "no clipped, black or oddly exposed photograph"))
    stray = checks.get("stray_light")
    if stray:
        if stray.get("level") is None:
            rows.append(("Stray light", stray.get("note", "not measured")))
        else:
            verdict = "raised: room light or a reflection" if stray.get("warned") else "dark room"
            rows.append(("Stray light", f"{stray['level']:.1%} of the lamps' light in attached shadows ({verdict})"))
    if checks.get("ambient"):
        rows.append(("Ambient frame", f"{checks['ambient']['frame']} subtracted"))
    flat = checks.get("flat_field")
    if flat:
        rows.append(("Flat field", f"{flat['capture']}: {flat['summary']}" if flat.get("summary") else str(flat["capture"])))
    return rows


def _capture_checks(report: dict | None) -> str | None:
    """The section on the capture's defects: the findings, and each photograph's offset."""
    checks = (report or {}).get("capture_checks")
    if not checks:
        return None
    html = _table(capture_check_rows(checks), ("check", "found"))
    drift = checks.get("drift")
    if drift and drift.get("photographs"):
        offsets = _table([(p["name"], p["dx"], p["dy"], p["rotation_deg"], p["confidence"]) for p in drift["photographs"]],
                         ("photograph", "dx (px, right)", "dy (px, up)", "rotation (°)", "confidence"))
        html += f"<details><summary>Each photograph's offset</summary>{offsets}</details>"
    return html


def _summary(rows: Sequence[tuple[str, str]], warnings: Sequence[str]) -> str:
    if warnings:
        items = "".join(f"<li>{_esc(w)}</li>" for w in warnings)
        box = (f'<div class="warnings" id="warnings"><h3>{len(warnings)} warning{"s" if len(warnings) > 1 else ""}'
               f"</h3><ul>{items}</ul></div>")
    else:
        box = '<p class="ok" id="warnings">No warnings.</p>'
    ids = {"Accuracy": ' id="accuracy"'}
    table = "".join(f"<tr{ids.get(label, '')}><th>{_esc(label)}</th><td>{_esc(text)}</td></tr>" for label, text in rows)
    return f'{box}<table class="summary">{table}</table>'


def report_html(
    folder: str | os.PathLike,
    *,
    report: dict | None = None,
    comparison: dict | None = None,
    photographs: Sequence[tuple[str | os.PathLike, np.ndarray]] | None = None,
    title: str | None = None,
    also: Sequence[str | os.PathLike] = (),
    previews: figures.Previews | None = None,
    thumbnails: Mapping[int, np.ndarray] | None = None,
    written_after: Sequence[str] = (),
    wait_for: Callable[[str], None] | None = None,
) -> str:
    """The text of ``report.html`` for an output folder.

    Parameters
    ----------
    folder : path
        The folder holding ``report.json`` and/or ``comparison.json`` and the maps.
    report, comparison : dict, optional
        The run's report and the comparison's, when the caller holds them (they are written
        after the page, with its time); by default read from ``report.json`` and
        ``comparison.json`` in the folders.
    photographs : sequence of (path, light direction), optional
        The photographs of the capture, for the light plot and the contact sheet (at most
        :data:`CONTACT_SHEET`, evenly spread, are shown). Default: those of the ``.lp`` file
        named in ``report.json``, when it still exists.
    title : str, optional
        The page's title (default: the object's name).
    also : sequence of paths
        Further folders to look in for files not in ``folder`` (an output folder published
        earlier, e.g. the reconstruction a comparison was written beside).
    previews : Previews, optional
        Subsamples of the run's normals, heights and albedo
        (:func:`reconstruct.report.figures.previews` of the arrays in memory), from which the
        maps, the Lambertian relighting and the mesh render are made. Default: subsamples of
        ``normals.npy``, ``height.tif`` and ``albedo.png``.
    thumbnails : mapping of int to ndarray, optional
        8-bit RGB thumbnails of photographs by their index in ``photographs``
        (:func:`reconstruct.report.figures.stack_thumbnail`; :func:`contact_sheet_picks` says
        which are shown); the others are decoded from the files.
    written_after : sequence of str
        Files the caller writes into ``folder`` after the page, or is still writing (the
        list of files names them; :func:`write_report_html` adds its JSON documents and the
        page).
    wait_for : callable, optional
        ``wait_for(name)`` returns once the file ``name`` of ``folder`` is written, when the
        caller writes files in other threads while the page is made
        (:meth:`reconstruct.pipeline.writer.FileWriter.wait_for`); the page waits only for
        the files it reads.

    Returns
    -------
    str
        A complete HTML5 document with every picture embedded; its only links are to the
        files of ``folder``.
    """
    # The same folder may be given twice (a comparison written into the run's own folder).
    places = list(dict.fromkeys(Path(p).resolve() for p in also if Path(p).resolve() != Path(folder).resolve()))
    files = _Folder(Path(folder), places, wait_for, written_after)
    report = report if report is not None else files.json("report.json")
    comparison = comparison if comparison is not None else files.json("comparison.json")
    notes: list[str] = []
    inputs = (report or {}).get("inputs") or {}
    source = inputs.get("capture") or inputs.get("ptm") or inputs.get("normal_map") \
        or (comparison or {}).get("reconstruction") or str(folder)
    name = Path(source).stem if Path(source).suffix.lower() in (".ptm", ".png", ".tif", ".tiff", ".npy", ".jpg",
                                                                ".ply") else Path(source).name
    title = title or f"{name} — ptm-reconstruct report"
    versions = (report or comparison or {}).get("versions") or {}

    pictures: list[tuple[str, str, str]] = []
    extent = None
    if report is not None:
        previews = previews if previews is not None else _previews(files, report, notes)
        if previews.height is not None:
            extent = summary.extent(previews.height, previews.stride, figures.display_pixel_size(report))
        mesh_notes: list[str] = []
        # The mesh is rendered in its own thread while the other pictures are made (see the
        # module's docstring); its notes join the others in the order of the sections. Both
        # threads may use matplotlib (pyvista, reading a mesh file, imports it): it is
        # imported first, once.
        rendering.import_plotting()
        with ThreadPoolExecutor(max_workers=1) as render:
            mesh_section = render.submit(_mesh, files, report, previews, extent, mesh_notes)
            ptm = _ptm_preview(files, report, notes)
            published = _published_preview(files, notes)
            pictures.append(("relit", "Relit under several lights",
                             _attempt(lambda: _relit(report, previews, ptm, published), "relit renderings", notes,
                                      _note)))
            pictures.append(("surface", "Specular enhancement, albedo and normals", _surface(report, previews, ptm, notes)))
            pictures.append(("maps", "Height map and profile", _height(report, previews, notes)))
            if photographs is None:
                photographs = _attempt(lambda: _photographs_from_report(report), "contact sheet", notes)
            lights = _lights(photographs, notes) if photographs else None
            sheet = (_attempt(lambda: _contact_sheet(photographs, thumbnails), "contact sheet", notes, _note)
                     if photographs else None)
            pictures.append(("mesh", "The 3D mesh", mesh_section.result()))
        notes += mesh_notes
        if lights:
            pictures.append(("lights", "The lights", lights))
        if sheet:
            pictures.append(("photographs", "Photographs", sheet))
    if comparison is not None:
        pictures.append(("comparison", "Comparison with the scan", _comparison(files, comparison, notes)))

    warnings = [*((report or {}).get("warnings") or []), *((comparison or {}).get("warnings") or []), *notes]
    rows = summary.summary_rows(report, comparison, extent, object_name=name)
    pictures_body = "".join(f'<section id="{key}"><h3>{_esc(heading)}</h3>{content}</section>'
                            for key, heading, content in pictures) or _note("no pictures: the folder holds no run")
    checks = _capture_checks(report)
    capture = f'<h3 id="capture">The capture</h3>{checks}' if checks else ""
    sections = [("summary", "Summary", _summary(rows, warnings) + capture),
                ("pictures", "Pictures", pictures_body),
                ("files", "Files", _files(Path(folder), written_after, places)),
                ("parameters", "Technical parameters", _parameters(report, comparison))]

    made = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    meta = [f"source: {source}", f"made {made}", f"ptm-reconstruct {versions.get('ptm-reconstruct', '?')}"]
    nav = "".join(f'<a href="#{key}">{_esc(heading)}</a>' for key, heading, _ in sections)
    body = "".join(f'<section id="{key}"><h2>{_esc(heading)}</h2>{content}</section>'
                   for key, heading, content in sections)
    return (
        "<!DOCTYPE html>\n"
        f'<html lang="en"><head><meta charset="utf-8">'
        f'<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_esc(title)}</title><style>{_STYLE}</style></head>\n"
        f"<body><main><h1>{_esc(title)}</h1>"
        f'<p class="meta">{" · ".join(_esc(m) for m in meta)}</p><nav>{nav}</nav>\n'
        f"{body}</main></body></html>\n"
    )


def write_report_html(
    folder: str | os.PathLike,
    *,
    report: dict | None = None,
    comparison: dict | None = None,
    written_after: Sequence[str] = (),
    **page: Any,
) -> Path:
    """Write ``report.html`` into ``folder`` (atomically); see :func:`report_html`.

    The documents given (``report``, ``comparison``) are listed among the files as
    ``report.json`` and ``comparison.json``: the pipeline writes them right after the page.

    Parameters
    ----------
    folder, report, comparison, written_after
        As :func:`report_html`.
    **page
        The other keyword arguments of :func:`report_html`, passed on as they are.

    Returns
    -------
    Path
        The file written.
    """
    after = [*written_after, "report.html", *(["report.json"] if report is not None else []),
             *(["comparison.json"] if comparison is not None else [])]
    text = report_html(folder, report=report, comparison=comparison, written_after=after, **page)
    path = Path(folder) / "report.html"
    with atomic_write(path, "w") as f:
        f.write(text)
    return path
