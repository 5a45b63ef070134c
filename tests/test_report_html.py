"""``report.html``: written in every output folder, valid, self-contained, with its sections in
the order a person reads them (summary, pictures, files, parameters)."""

import base64
import html
import io
import json
import re
from html.parser import HTMLParser
from urllib.parse import unquote

import numpy as np
import pytest
import tifffile
from helpers import dome, sphere_normals
from PIL import Image

from reconstruct.cli.main import main
from ptmcore.lp import write_lp
from reconstruct.report import figures as report_figures
from reconstruct.pipeline import RunOptions, run_capture
from reconstruct.report.html import report_html

VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta", "source", "track", "wbr"}


class _Checker(HTMLParser):
    """Collects structure errors, section ids, references and text of an HTML page."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.ids: set[str] = set()
        self.refs: list[tuple[str, str, str]] = []  # (attribute, value, alt)
        self.doctype = False
        self.text: list[str] = []
        self.sections: list[str] = []  # top-level sections, in order
        self.section_text: dict[str, list[str]] = {}

    def handle_decl(self, decl: str) -> None:
        self.doctype |= decl.lower() == "doctype html"

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if "id" in a:
            if a["id"] in self.ids:
                self.errors.append(f"duplicate id {a['id']}")
            self.ids.add(a["id"])
        for key in ("src", "href"):
            if key in a:
                self.refs.append((key, a[key], a.get("alt", "")))
        if tag == "section" and "section" not in self.stack:
            self.sections.append(a.get("id", ""))
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in VOID:
            self.stack.pop()

    def handle_endtag(self, tag):
        if tag in VOID:
            self.errors.append(f"end tag for void element {tag}")
        elif not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes <{self.stack[-1] if self.stack else None}>")
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)
        if "section" in self.stack:
            self.section_text.setdefault(self.sections[-1], []).append(data)

    def in_section(self, key: str) -> str:
        return " ".join(self.section_text.get(key, []))


SECTIONS = ["summary", "pictures", "files", "parameters"]


def check_page(path) -> _Checker:
    """Parse a report and assert it is well formed, its sections in order, its pictures
    embedded and its links to files beside it that exist."""
    text = path.read_text(encoding="utf-8")
    checker = _Checker()
    checker.feed(text)
    checker.close()
    assert checker.doctype
    assert not checker.errors, checker.errors[:5]
    assert not checker.stack, f"unclosed: {checker.stack}"
    assert "http://" not in text and "https://" not in text and "url(" not in text
    assert checker.sections == SECTIONS
    assert '<section id="parameters"><h2>Technical parameters</h2><details>' in text, "parameters not folded"
    for attribute, value, alt in checker.refs:
        if attribute == "href":
            if value.startswith("#"):
                assert value[1:] in checker.ids, value
            else:  # a file of the output folder, by a relative path inside it
                assert not value.startswith("/") and ":" not in value and ".." not in value, value
                assert (path.parent / unquote(value)).is_file(), value
            continue
        match = re.fullmatch(r"data:image/(png|jpeg);base64,([A-Za-z0-9+/=]+)", value)
        assert match, f"{alt}: not an embedded PNG or JPEG: {value[:60]}"
        image = Image.open(io.BytesIO(base64.b64decode(match.group(2), validate=True)))
        assert image.format == match.group(1).upper(), alt
        image.load()
        assert 0 < image.width <= 1000, (alt, image.size)
    # No placeholder rows beside what exists (an option not given has no row).
    assert "<td>—</td></tr>" not in text.split('<section id="parameters">')[1].split("Stage timings")[0]
    return checker


def _files_linked(checker: _Checker) -> set[str]:
    return {unquote(value) for attribute, value, _ in checker.refs if attribute == "href" and not value.startswith("#")}


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    """A synthetic tablet reconstructed with ground truth and compared with its scan."""
    from data_synthetic import write_capture

    root = tmp_path_factory.mktemp("report")
    info = write_capture(root / "cap", "tablet", shape=(90, 120), n_lights=24, seed=8)
    out = root / "out"
    assert main(["run", str(info.folder), "-o", str(out), "--pixel-size", str(info.pixel_size), "-q",
                 "--scan", str(info.scan_path)]) == 0
    return info, out


def test_run_with_scan_writes_a_complete_self_contained_report(scanned):
    _, out = scanned
    checker = check_page(out / "report.html")
    assert {"summary", "warnings", "accuracy", "pictures", "relit", "surface", "maps", "mesh", "lights",
            "photographs", "comparison", "files", "parameters"} <= checker.ids
    text = " ".join(checker.text)
    alts = [alt for _, _, alt in checker.refs]
    # The summary in words: size and relief in mm, the method, the accuracy; no internal keys.
    summary = checker.in_section("summary")
    assert "80 × 60 mm" in summary and "Relief depth" in summary and "photometric stereo" in summary
    assert "of the ground truth" in summary and "Against the laser scan scan.ply: RMS distance" in summary
    assert "No warnings" in summary
    assert not re.search(r"\b[a-z]+_[a-z_]+\b", summary), "snake_case in the summary"
    # The contact sheet shows at most 8 of the 24 photographs, named, with their lights.
    assert sum("light az" in a for a in alts) == 8
    assert sum("raking" in a for a in alts) >= 3 and any("overhead" in a for a in alts)
    for picture in ("specular enhancement", "albedo", "normal map", "height map in mm; scale bar in mm",
                    "height profile along row", "the 24 lights seen from above", "histogram", "distance map"):
        assert any(picture in a for a in alts), picture
    mesh = next(a for a in alts if a.startswith("mesh.ply"))
    assert re.search(r"vertical exaggeration ×\d+", mesh), mesh
    # The files written, each linked (check_page: they exist), and only those.
    linked = _files_linked(checker)
    assert {"coefficients.ptm", "mesh.ply", "mesh.obj", "height.tif", "normals.png", "albedo.png", "report.json",
            "comparison.json", "distances.ply", "report.html"} <= linked
    assert linked == {p.name for p in out.iterdir() if p.is_file()} | ({"web/index.html"} if (out / "web/index.html").is_file()
                                                                     else {"web/info.json"})
    assert "MeshLab" in checker.in_section("files") and "RTIViewer" in checker.in_section("files")
    # Statistics of the comparison and the other stages' timings are in the page.
    stats = json.loads((out / "comparison.json").read_text())["statistics_mm"]
    assert f"{stats['rms']:.4g}" in text
    report = json.loads((out / "report.json").read_text())
    for name in ("decode", "normals", "ptm", "integrate", "mesh", "write (in the background)", "compare: align"):
        assert name in checker.in_section("parameters"), name
    # The files were written beside the later stages: the total is the run's wall time, not a sum.
    assert "total (wall time)" in checker.in_section("parameters") and report["seconds"] > 0
    # The page is made once, by the comparison that follows the run: its own time is recorded
    # in comparison.json, written after it (a run alone records it in report.json).
    assert "report" in json.loads((out / "comparison.json").read_text())["stages"]
    assert "report" not in report["stages"]
    assert "accuracy" in report and "height_rmse_mm" in checker.in_section("parameters")
    # The relit renderings are of the basis the run chose and published in web/, named as
    # report.json's relighting section names it; a basis of linear light says it is encoded
    # for display.
    chosen = report["relighting"]
    relit = " ".join(checker.text).split("Relit under several lights")[1].split("Specular enhancement, albedo")[0]
    assert (f"published in web/, {report_figures.basis_words(chosen['name'])} (chosen by {chosen['chosen_by']}: "
            f"{chosen['margin_db']:.1f} dB better than {chosen['runner_up']})") in relit, relit
    assert ("shown sRGB-encoded" in relit) == (chosen["encoding"] == "linear")


def test_compare_into_another_folder_and_escaping(scanned, tmp_path):
    info, out = scanned
    other = tmp_path / "vs"
    assert main(["compare", str(out), str(info.scan_path), "-o", str(other)]) == 0
    checker = check_page(other / "report.html")
    # The reconstruction's report is shown beside the comparison made from its folder.
    assert {"comparison", "summary", "mesh", "files", "parameters"} <= checker.ids
    # Only the comparison's own files are linked; the reconstruction's folder is named.
    assert _files_linked(checker) == {p.name for p in other.iterdir() if p.is_file()}
    assert str(out.resolve()) in checker.in_section("files")
    page = report_html(other, title='<script>alert("x")</script> & co')
    assert "<script>" not in page and "&lt;script&gt;" in page


def test_report_from_a_ptm_and_from_a_normal_map(scanned, tmp_path):
    _, out = scanned
    from_ptm = tmp_path / "ptm"
    assert main(["run", str(out / "coefficients.ptm"), "-o", str(from_ptm), "-q", "--pixel-size", "0.5"]) == 0
    checker = check_page(from_ptm / "report.html")
    assert {"summary", "relit", "maps", "mesh", "warnings", "files", "parameters"} <= checker.ids
    assert "photographs" not in checker.ids and "lights" not in checker.ids
    assert "PTM's maximum" in checker.in_section("summary"), "the run's warning is shown first"
    assert "1 warning" in checker.in_section("summary")
    assert any("default rendering of coefficients.ptm" in t for t in checker.text), "relit from the source PTM"
    assert "report" in json.loads((from_ptm / "report.json").read_text())["stages"]

    from_normals = tmp_path / "normals"
    assert main(["integrate", str(out / "normals.png"), "-o", str(from_normals), "-q"]) == 0
    checker = check_page(from_normals / "report.html")
    alts = [alt for _, _, alt in checker.refs]
    assert any("scale bar in pixels (no pixel size given)" in a for a in alts)
    assert any("uniform grey" in t for t in checker.text)


def _small_capture(folder, n=10, h=40, w=48):
    folder.mkdir(parents=True)
    normals, _ = sphere_normals(h, w, 18.0)
    names = []
    for k, d in enumerate(dome(n, seed=3)):
        shade = np.clip(normals @ d, 0, None) * 0.7
        names.append(f"p{k}.tif")
        tifffile.imwrite(folder / names[-1], np.round(np.repeat(shade[..., None], 3, axis=2) * 65535).astype(np.uint16))
    write_lp(folder / "lights.lp", names, dome(n, seed=3))
    return folder


def test_report_is_written_with_a_note_when_rendering_fails(tmp_path, monkeypatch):
    def no_context(*args, **kwargs):
        raise RuntimeError("off-screen rendering is not available (no OpenGL context: no EGL or OSMesa)")

    monkeypatch.setattr(report_figures, "mesh_render", no_context)
    result = run_capture(_small_capture(tmp_path / "cap"), tmp_path / "out", RunOptions(pixel_size=0.1))
    checker = check_page(result.files["report.html"])
    assert "no mesh render: off-screen rendering is not available" in checker.in_section("summary")
    assert "no mesh render: off-screen rendering is not available" in checker.in_section("pictures")
    assert not any(alt.startswith("mesh.ply") for _, _, alt in checker.refs)
    # The rest of the page is still there, and the run's outputs are all published.
    assert {"relit", "maps", "parameters"} <= checker.ids
    assert (tmp_path / "out" / "mesh.ply").is_file()


def test_height_figure_scale_bar_measures_the_full_map():
    height = np.add.outer(np.arange(50.0), np.arange(80.0)).astype(np.float32)
    height[:5] = np.nan
    png = report_figures.height_figure(height, 4, "mm", 0.05, width_px=600)
    image = Image.open(io.BytesIO(png))
    assert image.format == "PNG" and image.width == 600
    # 80 pixels at stride 4 and 0.05 mm: 16 mm wide, so the bar is the 2 mm nearest a quarter.
    assert report_figures.nice_length(0.25 * 80 * 4 * 0.05) == 2


def test_run_with_an_unreadable_scan_stops_before_writing_anything(tmp_path, capsys):
    # Issue 16: every input is checked before the first output byte (the reconstruction is not
    # made, and an earlier result would stay as it was).
    (tmp_path / "scan.ply").write_text("not a mesh")
    out = tmp_path / "out"
    code = main(["run", str(_small_capture(tmp_path / "cap")), "-o", str(out), "--pixel-size", "0.1", "-q",
                 "--scan", str(tmp_path / "scan.ply")])
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scan.ply" in err[0]
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "scan.ply"]


def test_round_ticks_and_vertical_exaggeration():
    from reconstruct.report import plots

    # The colour bar of a relief from -1.87 to 1.54 mm: ticks at round values, not -1.87, -0.736.
    ticks = plots.round_ticks().tick_values(-1.87, 1.54)
    steps = np.diff(ticks)
    assert np.allclose(steps, steps[0]) and any(np.isclose(steps[0], m * 10.0 ** k) for m in (1, 2, 5) for k in (-1, 0))
    assert np.allclose(ticks / steps[0], np.round(ticks / steps[0]))
    # A 2 mm relief on an 80 mm tablet is drawn 5 times deeper; a deep one at true scale.
    assert report_figures.vertical_exaggeration(80, 60, 2) == 5
    assert report_figures.vertical_exaggeration(80, 60, 30) == 1
    assert report_figures.vertical_exaggeration(80, 60, None) == 1


def test_summary_in_words_and_files_listed_only_when_written(tmp_path):
    from reconstruct.report import summary

    height = np.full((30, 40), np.nan, np.float32)
    height[5:25, 10:30] = np.linspace(0, 2, 20, dtype=np.float32)[None, :]
    size = summary.extent(height, 4, 0.1)
    assert (size.width, size.height, size.unit, size.whole_frame) == (8.0, 8.0, "mm", False)
    assert 1.9 < size.depth <= 2.0
    report = {"inputs": {"capture": "/x/tablet", "photographs": 12, "bit_depth": 8, "width": 160, "height": 120},
              "parameters": {"pixel_size": 0.1, "normals": "ps", "fit": "irls"}, "height_unit": "mm",
              "mesh": {"integrator": "masked", "integrator_reason": "a mask is known"}}
    rows = dict(summary.summary_rows(report, None, size, object_name="tablet"))
    assert rows["Size"] == "8 × 8 mm (the object's outline)" and rows["Relief depth"].startswith(f"{size.depth:.3g} mm (")
    assert "photometric stereo" in rows["Method"] and "least squares on the object only" in rows["Method"]
    assert rows["Accuracy"].startswith("not measured")
    rows = dict(summary.summary_rows({**report, "parameters": {}}, None, summary.extent(height, 4, None),
                                     object_name="tablet"))
    assert "pixels" in rows["Size"] and "no pixel size" in rows["Scale"]
    for name in ("mesh.ply", "height.tif", "notes #1.txt", ".stack.tmp"):
        (tmp_path / name).write_bytes(b"x")
    entries = {e.name: e for e in summary.file_entries(tmp_path, ["report.json", "mesh.obj", "web/index.html"])}
    assert set(entries) == {"mesh.ply", "height.tif", "notes #1.txt", "report.json", "mesh.obj", "web/index.html"}
    assert "MeshLab" in entries["mesh.ply"].how and "float" in entries["height.tif"].what


def test_matplotlib_is_imported_before_the_render_thread(tmp_path):
    """The page's charts (main thread) and the mesh render's pyvista (its own thread) both
    import matplotlib; imported for the first time from both at once, one got a half-made
    module and its pictures became notes (two 6 MP reports in three). In a fresh interpreter,
    matplotlib must be whole before the render thread starts."""
    import subprocess
    import sys

    folder = tmp_path / "res"
    code = f"""
import sys
from pathlib import Path
import numpy as np
from reconstruct.report import html
from reconstruct.report.outputs import write_json
folder = Path({str(folder)!r})
folder.mkdir()
write_json(folder / "report.json", {{"inputs": {{"capture": "x"}}, "parameters": {{}}, "height_unit": "pixel"}})
seen = []
original = html._mesh
def mesh(*args, **kwargs):
    seen.append("matplotlib.backends.backend_agg" in sys.modules and "matplotlib.colors" in sys.modules)
    return original(*args, **kwargs)
html._mesh = mesh
html.write_report_html(folder, report={{"inputs": {{"capture": "x"}}, "parameters": {{}}, "height_unit": "pixel"}})
print(seen)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[True]"


def test_a_run_page_made_while_its_files_are_written(tmp_path):
    """The page of a run is made while the files are written: it lists them, and its timings
    say the total is so far."""
    from data_synthetic import write_capture

    info = write_capture(tmp_path / "cap", "tablet", shape=(40, 56), n_lights=16, seed=2)
    out = tmp_path / "out"
    assert main(["run", str(info.folder), "-o", str(out), "-q"]) == 0
    checker = check_page(out / "report.html")
    assert {"mesh.obj", "mesh.ply", "normals.npy", "height.tif", "web/index.html"} <= _files_linked(checker)
    params = checker.in_section("parameters")
    assert "total so far (files still being written)" in params and "write (in the background)" not in params
    report = json.loads((out / "report.json").read_text())
    assert "write" in report["stages"] and report["seconds"] >= report["stages"]["write"]["seconds"]


def test_specular_picture_of_an_rgb_ptm():
    """An RGB-format PTM (one polynomial per channel) gets its specular picture too, as
    ``reconstruct relight --mode specular`` renders it."""
    from ptmcore.ptmfile import PTMFile
    from reconstruct.report import figures

    rng = np.random.default_rng(0)
    coef = rng.uniform(-20, 20, (12, 16, 3, 6)).astype(np.float32)
    coef[..., 5] += 120
    ptm = PTMFile("PTM_FORMAT_RGB", "PTM_1.2", 16, 12, np.ones(6, np.float32), np.zeros(6, np.int32), coef, None)
    image = figures.specular_from_ptm(ptm)
    assert image.shape == (12, 16, 3) and image.dtype == np.uint8 and image.max() > 0


def test_comparison_json_times_its_reading_of_the_scan(scanned):
    """The comparison's own reading of the scan is one of its stages (it used to be timed by a
    throwaway timer)."""
    _, out = scanned
    assert list(json.loads((out / "comparison.json").read_text())["stages"])[:2] == ["read", "align"]


def _relit_images(text):
    """The relit section's pictures, decoded, by their captions."""
    section = text.split('<section id="relit">')[1].split("</section>")[0]
    found = re.findall(r'<img src="data:image/jpeg;base64,([A-Za-z0-9+/=]+)" alt="([^"]*)"', section)
    return {alt: np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB")) for data, alt in found}


@pytest.mark.parametrize("encoding", ["srgb", "linear"])
def test_relit_pictures_are_the_published_basis(scanned, tmp_path, encoding):
    """The relit pictures render the basis of web/ as its page shows it, captioned with its name
    and how report.json says it was chosen; without a published basis, the PTM; an unreadable
    web/ is a note and the PTM."""
    import shutil
    from dataclasses import replace

    from reconstruct.report.web import export_relightable
    from reconstruct.report.webread import read_relightable

    _, out = scanned
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    basis = read_relightable(copy / "web")
    hsh = replace(basis, type="hsh", colorspace="lrgb", order=2, name="hsh2", encoding=encoding,
                  colour=np.full(basis.shape + (3,), 180, np.uint8),
                  planes=np.stack([np.full(basis.shape, 1.8), *(0.3 * np.sin(np.arange(basis.shape[1]) / (4 + k))
                                   * np.ones(basis.shape) for k in range(3))], -1).astype(np.float32),
                  basis=None, lights=None, sigma=None, resolution=None)
    export_relightable(copy / "web", hsh, tiles=False)
    report = json.loads((copy / "report.json").read_text())
    report["relighting"].update(name="hsh2", encoding=encoding, chosen_by="leave-one-out", margin_db=1.3,
                                runner_up="rbf (srgb)")
    text = html.unescape(report_html(copy, report=report))
    assert ("The relighting basis published in web/, HSH order 2 (chosen by leave-one-out: 1.3 dB better than "
            "rbf (srgb))") in text
    assert ("fitted to linear light and shown sRGB-encoded" in text) == (encoding == "linear")
    shown = _relit_images(text)
    expected = dict(report_figures.relit_from_basis(copy / "web"))
    assert set(shown) == set(expected) == {label for label, _, _ in report_figures.RELIGHT_LIGHTS}
    for label, image in expected.items():
        assert image.shape == shown[label].shape and max(image.shape) <= report_figures.RELIT_SIDE
        assert np.abs(shown[label].astype(int) - image).mean() < 2, label  # the page's JPEG
    # A basis asked for is said so.
    report["relighting"]["chosen_by"] = "asked"
    assert "HSH order 2 (as asked: --basis)" in report_html(copy, report=report)
    # web/ of the PTM itself (no basis named): the PTM's renderings, as before.
    viewer = json.loads((copy / "web" / "viewer.json").read_text())
    (copy / "web" / "viewer.json").write_text(json.dumps({k: v for k, v in viewer.items() if k != "basis"}))
    text = html.unescape(report_html(copy, report=report))
    assert "RTIViewer's default rendering of coefficients.ptm" in text and "published in web/" not in text
    # An unreadable web/: a note, and the PTM's renderings.
    (copy / "web" / "viewer.json").write_text(json.dumps(viewer))
    (copy / "web" / "plane_1.jpg").write_bytes(b"not a jpeg")
    text = html.unescape(report_html(copy, report=report))
    assert "no renderings of web/" in text and "plane_1.jpg" in text
    assert "RTIViewer's default rendering of coefficients.ptm" in text
