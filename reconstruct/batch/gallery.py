"""The batch's gallery: ``OUT/index.html`` over every object and the thumbnails it shows.

Each finished object gets two small pictures in ``OUT/thumbnails/`` (:func:`write_thumbnails`,
run by the worker right after the object), and the page (:func:`write_index`) links them by
relative path. Unlike ``report.html``, nothing is embedded: a collection of a thousand objects
would make a page of hundreds of megabytes, whereas thumbnails loaded lazily keep it at about
a kilobyte per object. The page is plain HTML with inline style (no script, nothing fetched
from elsewhere), so ``OUT/`` can be copied anywhere and browsed as it is.
"""

from __future__ import annotations

import functools
import html
import json
import math
from collections import Counter
from datetime import datetime
from pathlib import Path
from urllib.parse import quote

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError, read_input_text
from ptmcore.images import image_size
from reconstruct.batch.rows import DONE, FAILED, SKIPPED, BatchRow
from reconstruct.report import figures

__all__ = ["write_index", "write_thumbnails"]

#: The thumbnails' kinds and file-name suffixes: ``<name>_relit.jpg``, ``<name>_height.png``.
THUMBNAILS = {"relit": "_relit.jpg", "height": "_height.png"}

# The light of the relit thumbnail: the one of report.html's renderings that comes from the
# upper left, the direction under which reliefs are conventionally read.
_UPPER_LEFT = next(k for k, (_, az, el) in enumerate(figures.RELIGHT_LIGHTS) if az == 135.0)

# Where a height map has no value (outside the mask): the light grey of report.html's map.
_NO_HEIGHT = 235

_STYLE = """
body{font:14px/1.4 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;color:#222;background:#f4f4f2;margin:0}
main{max-width:1600px;margin:0 auto;padding:10px 18px 40px}
h1{font-size:1.5em;margin:.3em 0 .1em}h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:1.2em}
.meta{color:#555;margin:0 0 .4em}.fail{color:#b02020}
table{border-collapse:collapse;background:#fff;font-size:.92em;width:100%}
td,th{border:1px solid #ddd;padding:3px 8px;text-align:left;vertical-align:top}th{background:#f0f0ee}
pre{margin:0;white-space:pre-wrap;word-break:break-word;font-size:.95em}
.cards{display:grid;grid-template-columns:repeat(auto-fill,minmax(300px,1fr));gap:10px}
.c{background:#fff;border:1px solid #ddd;border-radius:4px;padding:6px 8px}
.c h3{font-size:1em;margin:0 0 4px;overflow-wrap:anywhere}.sk{border-style:dashed;opacity:.85}
.tag{font-size:.8em;font-weight:normal;background:#e6e6e2;border-radius:3px;padding:0 4px}
.p{display:grid;grid-template-columns:1fr 1fr;gap:4px;align-items:start}
.p img{width:100%;height:auto;background:#eee;display:block}
.p span{background:#eee;color:#777;font-size:.85em;padding:30px 0;text-align:center}
dl{display:grid;grid-template-columns:auto 1fr;gap:0 8px;margin:4px 0 0;font-size:.88em}
dt{color:#666}dd{margin:0;font-variant-numeric:tabular-nums}.w{color:#a06000}
"""


def write_thumbnails(folder: Path, thumbs: Path, name: str, max_side: int = 240) -> dict[str, str]:
    """Write an object's two gallery pictures: relit and height map, at most ``max_side`` pixels.

    ``<name>_relit.jpg`` is the PTM rendered under a light from the upper left (only a
    subsample of the file is decoded); a run without a PTM (from a normal map) shows its
    ``albedo.png`` instead. ``<name>_height.png`` is the height map in viridis, grey outside
    the mask. A picture that cannot be made (a file missing or unreadable) is left out: the
    gallery never fails an object.

    Parameters
    ----------
    folder : Path
        The object's output folder, as ``reconstruct run`` writes it.
    thumbs : Path
        The thumbnails' folder (``OUT/thumbnails``); created if needed.
    name : str
        The object's name, the start of the file names.
    max_side : int
        The pictures' longer side at most, in pixels.

    Returns
    -------
    dict of str to str
        ``{"relit": ..., "height": ...}``: the files written, relative to ``thumbs.parent``
        (``OUT/``) with ``/`` separators, as the page links them. Only those written.
    """
    folder, thumbs = Path(folder), Path(thumbs)
    report = _read_report(folder)
    makers = {"relit": lambda: _relit(folder, report, max_side), "height": lambda: _height(folder, max_side)}
    written = {}
    for kind, make in makers.items():
        file = f"{name}{THUMBNAILS[kind]}"
        try:
            data = make()
            if data is None:
                continue
            thumbs.mkdir(parents=True, exist_ok=True)
            with atomic_write(thumbs / file) as f:
                f.write(data)
        except Exception:  # noqa: BLE001 - a thumbnail must never fail an object that reconstructed
            continue
        written[kind] = f"{thumbs.name}/{file}"
    return written


def write_index(
    out: Path,
    rows: list[BatchRow],
    *,
    title: str = "Batch",
    thumbs: dict[str, dict[str, str]] | None = None,
) -> Path:
    """Write ``out/index.html``: the batch's counts, its failures, then one card per object.

    Failures come first, in a table with their full error. Done and skipped objects follow
    in the rows' order, as cards linking ``<name>/report.html``, with the two thumbnails
    (loaded lazily) and the row's key figures. The page is about a kilobyte per object.

    Parameters
    ----------
    out : Path
        The batch's output folder (it must exist).
    rows : list of BatchRow
        The batch's rows, in the order of the cards.
    title : str
        The page's title.
    thumbs : dict, optional
        ``{name: {"relit": path, "height": path}}`` relative to ``out``, as
        :func:`write_thumbnails` returns them. Objects not in it use
        ``thumbnails/<name>_relit.jpg`` and ``thumbnails/<name>_height.png`` if those exist.

    Returns
    -------
    Path
        The page written.
    """
    out = Path(out)
    thumbs = thumbs or {}
    failed = [r for r in rows if r.status == FAILED]
    cards = [_card(out, r, thumbs.get(r.name)) for r in rows if r.status != FAILED]
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width,initial-scale=1">',
        f"<title>{_esc(title)}</title><style>{_STYLE}</style></head><body><main>",
        f"<h1>{_esc(title)}</h1>",
        _summary(rows),
    ]
    if failed:
        parts.append(f'<h2 class="fail">Failed ({len(failed)})</h2>'
                     "<table><tr><th>name</th><th>source</th><th>error</th></tr>")
        parts.extend(f"<tr><td>{_esc(r.name)}</td><td>{_esc(r.source)}</td>"
                     f"<td><pre>{_esc(r.error)}</pre></td></tr>" for r in failed)
        parts.append("</table>")
    parts.append(f"<h2>Objects ({len(cards)})</h2>")
    parts.append(f'<div class="cards">\n{chr(10).join(cards)}\n</div>' if cards else "<p>No object finished.</p>")
    parts.append("</main></body></html>\n")
    path = out / "index.html"
    with atomic_write(path, "w") as f:
        f.write("\n".join(parts))
    return path


def _esc(value: object) -> str:
    return html.escape(str(value), quote=True)


def _url(path: str) -> str:
    """A relative path as an attribute value: percent-encoded (a name may hold ``#``, ``?`` or
    ``%``, which would cut a URL short) then escaped."""
    return _esc(quote(path, safe="/"))


def _read_report(folder: Path) -> dict | None:
    try:
        report = json.loads(read_input_text(folder / "report.json", "report"))
    except (InputError, ValueError):
        return None
    return report if isinstance(report, dict) else None


def _relit(folder: Path, report: dict | None, max_side: int) -> bytes | None:
    from reconstruct.report.webread import published_folder

    ptm = folder / "coefficients.ptm"
    source = ((report or {}).get("inputs") or {}).get("ptm")
    if not ptm.is_file() and source:
        ptm = Path(source)  # a run from a .ptm file writes none: its source is the PTM
    web = published_folder(folder)
    image = None
    if web is not None:  # the basis people relight, as report.html shows it
        try:
            image = figures.relit_from_basis(web, max_side)[_UPPER_LEFT][1]
        except InputError:
            image = None
    if image is None and ptm.is_file():
        renderings = figures.relit_from_ptm(ptm, max_side, linear=figures.linear_ptm(report))
        image = renderings[_UPPER_LEFT][1]
    if image is None and (folder / "albedo.png").is_file():
        image = figures.photograph_thumbnail(folder / "albedo.png", max_side)
    if image is None:
        return None
    return figures.encode(image, "JPEG")


@functools.cache
def _viridis() -> np.ndarray:
    """Matplotlib's viridis as a 256 × 3 uint8 table (report.html's height colours)."""
    import matplotlib as mpl

    return mpl.colormaps["viridis"](np.linspace(0.0, 1.0, 256), bytes=True)[:, :3]


def _height(folder: Path, max_side: int) -> bytes | None:
    path = folder / "height.tif"
    if not path.is_file():
        return None
    sub, _ = figures.read_subsampled(path, max_side)
    lo, hi = figures.finite_range(sub)
    finite = np.isfinite(sub)
    level = np.clip(np.round((np.where(finite, sub, lo) - lo) * (255 / (hi - lo))), 0, 255)
    image = _viridis()[level.astype(np.uint8)]
    image[~finite] = _NO_HEIGHT
    return figures.encode(image, "PNG")


def _thumbnail(out: Path, rel: str | None, alt: str) -> str:
    size = image_size(out / rel) if rel else None
    if size is None:
        return "<span>no picture</span>"
    return (f'<img loading="lazy" src="{_url(rel)}" width="{size[0]}" height="{size[1]}" '
            f'alt="{_esc(alt)}">')


def _number(value: float | None) -> str | None:
    return None if value is None or not math.isfinite(value) else f"{value:.3g}"


def _duration(seconds: float) -> str:
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, s = divmod(round(seconds), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min" if hours else f"{minutes} min {s:02d} s"


def _memory(mb: float | None) -> str | None:
    if mb is None or not math.isfinite(mb):
        return None
    return f"{mb / 1024:.1f} GB" if mb >= 1024 else f"{mb:.0f} MB"


def _figures(row: BatchRow) -> list[tuple[str, str]]:
    """The card's key figures as (label, value), those the row has."""
    items = []
    if row.photographs is not None:
        items.append(("photographs", str(row.photographs)))
    if row.width is not None and row.height is not None:
        items.append(("image", f"{row.width} × {row.height} px"))
    if row.normals:
        items.append(("normals", row.normals))
    lo, hi = _number(row.height_min), _number(row.height_max)
    if lo is not None and hi is not None:
        items.append(("height", f"{lo} to {hi} {row.height_unit or ''}".rstrip()))
    if (accuracy := _number(row.accuracy_mean_deg)) is not None:
        items.append(("accuracy", f"{accuracy}° mean"))
    if (rms := _number(row.scan_rms_mm)) is not None:
        items.append(("scan RMS", f"{rms} mm"))
    # A skipped object was not run: its 0 s says nothing.
    if row.status != SKIPPED:
        items.append(("time", _duration(row.seconds)))
    if (memory := _memory(row.peak_rss_mb)) is not None:
        items.append(("peak memory", memory))
    return items


def _card(out: Path, row: BatchRow, paths: dict[str, str] | None) -> str:
    if paths is None:
        paths = {kind: f"thumbnails/{row.name}{suffix}" for kind, suffix in THUMBNAILS.items()}
    skipped = row.status == SKIPPED
    tag = ' <span class="tag">skipped: unchanged</span>' if skipped else ""
    pictures = (_thumbnail(out, paths.get("relit"), f"{row.name}, relit")
                + _thumbnail(out, paths.get("height"), f"{row.name}, height map"))
    facts = "".join(f"<dt>{_esc(label)}</dt><dd>{_esc(value)}</dd>" for label, value in _figures(row))
    warn = ' class="w"' if row.warnings else ""
    facts += f"<dt>warnings</dt><dd{warn}>{row.warnings}</dd>"
    return (f'<article class="c{" sk" if skipped else ""}"><h3><a href="{_url(row.name + "/report.html")}" '
            f'title="{_esc(row.source)}">{_esc(row.name)}</a>{tag}</h3>'
            f'<div class="p">{pictures}</div><dl>{facts}</dl></article>')


def _summary(rows: list[BatchRow]) -> str:
    counts = Counter(r.status for r in rows)
    failed = f"{counts[FAILED]} failed"
    if counts[FAILED]:
        failed = f'<b class="fail">{failed}</b>'
    text = (f"{len(rows)} objects: {counts[DONE]} done, {counts[SKIPPED]} skipped, {failed}"
            f" · object time {_duration(sum(r.seconds for r in rows))} (summed over the objects)")
    peaks = [r.peak_rss_mb for r in rows if r.peak_rss_mb is not None and math.isfinite(r.peak_rss_mb)]
    if peaks:
        text += f" · largest peak memory {_memory(max(peaks))}"
    written = datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    return f'<p class="meta">{text}</p><p class="meta">Written {_esc(written)}.</p>'
