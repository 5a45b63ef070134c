"""``report.html``: one self-contained page that shows what a run made and how.

The page is built from an output folder (``report.json``, ``comparison.json`` and the images
and maps beside them) plus, for the contact sheet, a few of the photographs. Every picture is
embedded as a ``data:`` URI and the style is inline, so the file opens anywhere (a USB stick,
no network) and references nothing else. A picture that cannot be made (no off-screen
rendering, no matplotlib, an unreadable photograph) becomes a note in its place: the page is
always written.

The maps are subsampled once, first (:func:`reconstruct.report.figures.previews`, to about a
thousand pixels), and every picture is made from the subsamples; a caller that holds the maps
(the pipeline) passes them, and the photographs' thumbnails, so that nothing large is read
again. The mesh is rendered in a second thread while the other pictures are made: most of its
time is the start of an OpenGL context, in VTK's C++ code, which leaves the GIL to them.
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

import numpy as np

from ptmcore.atomic import atomic_write

from reconstruct.report import figures

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
.warnings{background:#fff4e0;border-left:4px solid #e09a1a;padding:6px 10px 6px 28px}
.tables{display:flex;flex-wrap:wrap;gap:0 28px}
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


def _figure(data: bytes, mime: str, caption: str) -> str:
    return f"<figure>{_img(data, mime, caption)}<figcaption>{_esc(caption)}</figcaption></figure>"


def _note(text: str) -> str:
    return f'<p class="note">{_esc(text)}</p>'


class _Folder:
    """Files of the report: the folder being written first, then earlier output folders."""

    def __init__(self, folder: Path, also: Sequence[Path]) -> None:
        self.places = [folder, *also]

    def find(self, name: str) -> Path | None:
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
        with ThreadPoolExecutor(max_workers=min(len(missing), os.cpu_count() or 1, 4)) as pool:
            thumbs.update(zip(missing, pool.map(lambda k: figures.photograph_thumbnail(photographs[k][0]), missing)))
    items = []
    for k in picks:
        path, light = photographs[k]
        light = np.asarray(light, dtype=np.float64)
        az = np.degrees(np.arctan2(light[1], light[0])) % 360
        el = np.degrees(np.arcsin(np.clip(light[2], -1, 1)))
        items.append(_figure(figures.encode(thumbs[k], "JPEG"), "image/jpeg",
                             f"{Path(path).name} — light az {az:.0f}°, el {el:.0f}°"))
    shown = f"{len(picks)} of {n} photographs" if len(picks) < n else f"all {n} photographs"
    return f"<p>{_esc(shown)}; azimuth 0° = light from the right, 90° = from the top.</p>" \
           f'<div class="grid sheet">{"".join(items)}</div>'


def _previews(files: _Folder, notes: list[str]) -> figures.Previews:
    """The subsamples of the folder's normals and heights (memory-mapped: only the rows taken
    are read); a map that cannot be read is left out with a note."""
    maps = {}
    for key, name in (("normals", "normals.npy"), ("height", "height.tif")):
        path = files.find(name)
        if path is not None:
            maps[key] = _attempt(lambda path=path: figures.map_array(path), f"{name} subsample", notes)
    return _attempt(lambda: figures.previews(**maps), "maps", notes, figures.Previews())


def _relit(files: _Folder, report: dict | None, previews: figures.Previews) -> str:
    ptm = files.find("coefficients.ptm")
    source = ((report or {}).get("inputs") or {}).get("ptm")
    if ptm is None and source and Path(source).is_file():
        ptm = Path(source)  # a run from a .ptm file: relight the file itself
    if ptm is not None:
        # Only a subsample is decoded: for a run from a .ptm file this re-reads the source
        # file, at the cost of the subsample.
        linear = figures.linear_ptm(report)
        images = figures.relit_from_ptm(ptm, linear=linear)
        how = f"RTIViewer's default rendering of {ptm.name}" + (
            " (a PTM of linear light, from 16-bit photographs: shown sRGB-encoded)" if linear else "")
    elif previews.normals is not None:
        # A normal map from elsewhere has no albedo (its albedo.png is a shaded rendering).
        from_normal_map = "normal_map" in ((report or {}).get("inputs") or {})
        albedo = None if from_normal_map else previews.albedo
        albedo_path = files.find("albedo.png")
        if albedo is None and albedo_path and not from_normal_map:
            from ptmcore.images import read_image

            albedo = read_image(albedo_path)  # a PNG is decoded whole; only without a PTM
        images = figures.relit_lambertian(previews.normals, albedo)
        how = "Lambertian shading of the normals" + (" and albedo" if albedo is not None else " (uniform grey)")
    else:
        return _note("no relit renderings: neither coefficients.ptm nor normals.npy is in the folder")
    items = "".join(_figure(figures.encode(img, "JPEG"), "image/jpeg", label) for label, img in images)
    return f"<p>{_esc(how)}, under six lights (elevation above the object plane).</p>" \
           f'<div class="grid">{items}</div>'


def _maps(report: dict | None, previews: figures.Previews, notes: list[str]) -> str:
    parts = []
    if previews.normals is not None:
        def normal_map() -> bytes:
            return figures.encode(figures.fit_side(figures.normal_colors(previews.normals), figures.MAX_WIDTH // 2))

        parts.append(_attempt(lambda: _figure(normal_map(), "image/png",
            "normal map (R = x right, G = y up, B = z towards the camera)"), "normal map picture", notes, _note))
    if previews.height is not None:
        unit = (report or {}).get("height_unit", "pixel")
        pixel_size = figures.display_pixel_size(report)

        def make() -> str:
            png = figures.height_figure(previews.height, previews.stride, unit, pixel_size)
            bar = "scale bar in mm" if pixel_size else "scale bar in pixels (no pixel size given)"
            return _figure(png, "image/png", f"height map in {unit}; {bar}")

        parts.append(_attempt(make, "height map picture", notes, _note))
    if not parts:
        return _note("no normal or height map in the folder")
    return f'<div class="grid" style="--min:420px">{"".join(parts)}</div>'


def _mesh(files: _Folder, report: dict | None, previews: figures.Previews, notes: list[str]) -> str:
    mesh = files.find("mesh.ply")
    if mesh is None:
        return _note("no mesh.ply in the folder")
    faces = figures.ply_face_count(mesh)

    def make() -> str:
        if faces is not None and faces <= figures.MAX_RENDER_FACES or previews.height is None:
            image = figures.mesh_render(mesh)
            what = "mesh.ply"
        else:
            sub, k = figures.thin(previews.height, figures.MESH_RENDER_SIDE)
            stride = previews.stride * k
            image = figures.mesh_render(figures.surface_from_height(sub, stride, figures.display_pixel_size(report)))
            what = f"mesh.ply's surface ({faces:,} triangles) sampled every {stride} pixels"
        return _figure(figures.encode(image, "JPEG", 90), "image/jpeg",
                       f"{what}, shaded, seen obliquely from the front (true scale)")

    return _attempt(make, "mesh render", notes, _note)


def _comparison(files: _Folder, comparison: dict, notes: list[str]) -> str:
    stats = comparison.get("statistics_mm") or {}
    tables = [_table(stats.items(), ("scan → reconstruction", "mm"))]
    if comparison.get("reverse_statistics_mm"):
        tables.append(_table(comparison["reverse_statistics_mm"].items(), ("reconstruction → scan", "mm")))
    alignment = {k: v for k, v in (comparison.get("alignment") or {}).items()
                 if k != "transform_scan_to_reconstruction"}
    tables.append(_table(alignment.items(), ("alignment", "")))
    if comparison.get("tolerance"):
        tables.append(_table(comparison["tolerance"].items(), ("tolerance", "")))
    parts = [f'<p>{_esc(comparison.get("sign_convention", ""))}. Scan: {_esc(comparison.get("scan", ""))}</p>',
             f'<div class="tables">{"".join(tables)}</div>']
    for name, fmt, caption in (("histogram.png", "PNG", "histogram of the signed distances"),
                               ("overlay.png", "JPEG", "aligned pair and distance map")):
        path = files.find(name)
        if path is not None:
            parts.append(_attempt(lambda path=path, fmt=fmt, caption=caption: _figure(
                figures.downscale_file(path, fmt=fmt), f"image/{fmt.lower()}", caption), name, notes, _note))
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
    total = sum(r[1] or 0 for r in rows)
    scope = (report or {}).get("peak_rss_scope", "per stage")
    return _table([*rows, ("total", round(total, 3), None)], ("stage", "wall time (s)", f"peak memory (MiB, {scope})"))


def _run_sections(report: dict, files: _Folder, previews: figures.Previews,
                  photographs: Sequence[tuple[str | os.PathLike, np.ndarray]] | None,
                  thumbnails: Mapping[int, np.ndarray] | None, notes: list[str]) -> list[tuple[str, str, str]]:
    """The sections of a run before its mesh: inputs, photographs, relit renderings, maps."""
    inputs = report.get("inputs") or {}
    tables = [_table(inputs.items(), ("input", "")),
              _table((report.get("parameters") or {}).items(), ("parameter", "value"))]
    result = dict(report.get("mesh") or {})
    for key in ("albedo_scale", "lights", "ptm", "intensities", "leave_one_out"):
        if report.get(key) is not None:
            result.update(_flatten({key: report[key]}))
    tables.append(_table(result.items(), ("result", "")))
    sections = [("inputs", "Inputs and parameters", f'<div class="tables">{"".join(tables)}</div>')]
    if photographs is None:
        photographs = _attempt(lambda: _photographs_from_report(report), "contact sheet", notes)
    if photographs:
        sections.append(("photographs", "Photographs",
                         _attempt(lambda: _contact_sheet(photographs, thumbnails), "contact sheet", notes, _note)))
    sections.append(("relit", "Relit renderings",
                     _attempt(lambda: _relit(files, report, previews), "relit renderings", notes, _note)))
    sections.append(("maps", "Normal map and height map", _maps(report, previews, notes)))
    return sections


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
        The photographs of the capture, for the contact sheet (at most
        :data:`CONTACT_SHEET`, evenly spread, are shown). Default: those of the ``.lp`` file
        named in ``report.json``, when it still exists.
    title : str, optional
        The page's title (default: the source's name).
    also : sequence of paths
        Further folders to look in for files not in ``folder`` (an output folder published
        earlier, e.g. the reconstruction a comparison was written beside).
    previews : Previews, optional
        Subsamples of the run's normals, heights and albedo
        (:func:`reconstruct.report.figures.previews` of the arrays in memory), from which the
        maps, the Lambertian relighting and the mesh render are made. Default: subsamples of
        ``normals.npy`` and ``height.tif`` read through memory maps.
    thumbnails : mapping of int to ndarray, optional
        8-bit RGB thumbnails of photographs by their index in ``photographs``
        (:func:`reconstruct.report.figures.stack_thumbnail`; :func:`contact_sheet_picks` says
        which are shown); the others are decoded from the files.

    Returns
    -------
    str
        A complete HTML5 document with every picture embedded.
    """
    # The same folder may be given twice (a comparison written into the run's own folder).
    places = dict.fromkeys(Path(p).resolve() for p in also if Path(p).resolve() != Path(folder).resolve())
    files = _Folder(Path(folder), list(places))
    report = report if report is not None else files.json("report.json")
    comparison = comparison if comparison is not None else files.json("comparison.json")
    notes: list[str] = []
    inputs = (report or {}).get("inputs") or {}
    source = inputs.get("capture") or inputs.get("ptm") or inputs.get("normal_map") \
        or (comparison or {}).get("reconstruction") or str(folder)
    title = title or f"ptm-reconstruct report: {Path(source).name}"
    versions = (report or comparison or {}).get("versions") or {}

    sections: list[tuple[str, str, str]] = []
    if report is not None:
        previews = previews if previews is not None else _previews(files, notes)
        mesh_notes: list[str] = []
        # The mesh is rendered in its own thread while the other pictures are made (see the
        # module's docstring); its notes join the others in the order of the sections.
        with ThreadPoolExecutor(max_workers=1) as render:
            mesh_section = render.submit(_mesh, files, report, previews, mesh_notes)
            sections += _run_sections(report, files, previews, photographs, thumbnails, notes)
            sections.append(("mesh", "Mesh", mesh_section.result()))
        notes += mesh_notes
        if report.get("accuracy"):
            sections.append(("accuracy", "Accuracy against ground truth",
                             _table(_flatten(report["accuracy"]), ("measure", "value"))))
    if comparison is not None:
        sections.append(("comparison", "Comparison with the scan", _comparison(files, comparison, notes)))
    sections.append(("timings", "Stage timings", _timings(report, comparison)))
    warnings = [*((report or {}).get("warnings") or []), *((comparison or {}).get("warnings") or []), *notes]
    warning_body = ("<ul class=\"warnings\">" + "".join(f"<li>{_esc(w)}</li>" for w in warnings) + "</ul>"
                    if warnings else "<p>none</p>")
    sections.append(("warnings", f"Warnings ({len(warnings)})", warning_body))

    made = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    meta = [f"source: {source}", f"made {made}", f"ptm-reconstruct {versions.get('ptm-reconstruct', '?')}"]
    if report is not None:
        meta.append(f"heights in {report.get('height_unit')}")
    nav = "".join(f'<a href="#{key}">{_esc(name)}</a>' for key, name, _ in sections)
    body = "".join(f'<section id="{key}"><h2>{_esc(name)}</h2>{content}</section>' for key, name, content in sections)
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
    photographs: Sequence[tuple[str | os.PathLike, np.ndarray]] | None = None,
    title: str | None = None,
    also: Sequence[str | os.PathLike] = (),
    previews: figures.Previews | None = None,
    thumbnails: Mapping[int, np.ndarray] | None = None,
) -> Path:
    """Write ``report.html`` into ``folder`` (atomically); see :func:`report_html`.

    Returns
    -------
    Path
        The file written.
    """
    text = report_html(folder, report=report, comparison=comparison, photographs=photographs, title=title,
                       also=also, previews=previews, thumbnails=thumbnails)
    path = Path(folder) / "report.html"
    with atomic_write(path, "w") as f:
        f.write(text)
    return path
