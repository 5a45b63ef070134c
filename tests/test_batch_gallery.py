"""The batch gallery: thumbnails of a real output folder and ``index.html`` over many rows."""

import re
import shutil
import time
from pathlib import Path
from urllib.parse import quote

import pytest
from PIL import Image

from reconstruct.batch.gallery import write_index, write_thumbnails
from reconstruct.batch.rows import DONE, FAILED, SKIPPED, BatchRow


@pytest.fixture(scope="module")
def out(tmp_path_factory) -> Path:
    """A batch output folder holding one real run, ``a/``."""
    from data_synthetic import write_capture
    from reconstruct.pipeline import RunOptions, run_capture

    root = tmp_path_factory.mktemp("batch")
    write_capture(root / "cap", shape=(48, 64), n_lights=16, seed=1)
    run_capture(root / "cap", root / "out" / "a", RunOptions(pixel_size=0.05))
    return root / "out"


def _done(name: str, **kw) -> BatchRow:
    figures = dict(seconds=12.5, peak_rss_mb=1830.0, photographs=48, width=6000, height=4000,
                   normals="robust", height_min=-0.25, height_max=3.5, height_unit="mm",
                   accuracy_mean_deg=2.1, scan_rms_mm=0.04, warnings=1)
    return BatchRow(name, f"/data/drawer_12/{name}", DONE, **{**figures, **kw})


def test_thumbnails_of_a_run(out):
    written = write_thumbnails(out / "a", out / "thumbnails", "a", max_side=40)

    assert written == {"relit": "thumbnails/a_relit.jpg", "height": "thumbnails/a_height.png"}
    for rel, fmt in ((written["relit"], "JPEG"), (written["height"], "PNG")):
        path = out / rel
        assert path.stat().st_size < 20_000
        with Image.open(path) as im:
            assert im.format == fmt
            assert max(im.size) <= 40 and min(im.size) > 0
            assert im.convert("RGB").getextrema() != ((0, 0),) * 3  # not black


def test_thumbnails_without_ptm_use_the_albedo(out, tmp_path):
    folder = tmp_path / "from_normals"
    folder.mkdir()
    shutil.copy(out / "a" / "albedo.png", folder)

    written = write_thumbnails(folder, tmp_path / "thumbnails", "n", max_side=30)

    assert written == {"relit": "thumbnails/n_relit.jpg"}
    with Image.open(tmp_path / written["relit"]) as im:
        assert max(im.size) <= 30


def test_thumbnails_never_raise(tmp_path):
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "coefficients.ptm").write_bytes(b"not a ptm")
    (folder / "height.tif").write_bytes(b"not a tiff")
    (folder / "report.json").write_text("{truncated")

    assert write_thumbnails(folder, tmp_path / "thumbnails", "x") == {}
    assert write_thumbnails(tmp_path / "missing", tmp_path / "thumbnails", "y") == {}


def test_index_failures_first_escaped_and_linked(out):
    write_thumbnails(out / "a", out / "thumbnails", "a")
    odd = '<script>alert("&")</script>'
    rows = [
        _done("a"),
        BatchRow("c", "/data/drawer_12/c", SKIPPED, photographs=48, warnings=0),
        BatchRow(odd, "/data/<b>", FAILED, error="InputError: no .lp file\n  in /data/<b> & elsewhere"),
        _done("b#1", accuracy_mean_deg=None, scan_rms_mm=None),
    ]

    page = write_index(out, rows, title="Drawer <12>").read_text(encoding="utf-8")

    assert "<script" not in page and "<b>" not in page
    assert "&lt;script&gt;alert(&quot;&amp;&quot;)&lt;/script&gt;" in page
    assert "InputError: no .lp file\n  in /data/&lt;b&gt; &amp; elsewhere" in page  # in full
    assert "<title>Drawer &lt;12&gt;</title>" in page
    assert "1 failed" in page and "2 done" in page and "1 skipped" in page
    assert page.index("InputError") < page.index("<article")
    assert 'href="a/report.html"' in page and 'href="c/report.html"' in page
    assert 'href="b%231/report.html"' in page
    assert f'href="{quote(odd)}/report.html"' not in page  # failed: no card, no link
    assert re.search(r'<img loading="lazy" src="thumbnails/a_relit.jpg" width="64" height="48"', page)
    assert 'src="thumbnails/a_height.png"' in page
    assert "skipped: unchanged" in page
    assert "-0.25 to 3.5 mm" in page and "2.1° mean" in page and "0.04 mm" in page
    assert "1.8 GB" in page and "12.5 s" in page
    assert "data:" not in page and "<script" not in page and "http" not in page


def test_index_takes_given_thumbnail_paths(out):
    write_thumbnails(out / "a", out / "pictures", "z")
    rows = [_done("z"), _done("q")]

    page = write_index(out, rows, thumbs={"z": {"relit": "pictures/z_relit.jpg"}}).read_text()

    assert 'src="pictures/z_relit.jpg"' in page
    assert "z_height.png" not in page  # not given, and the convention is not consulted for z
    assert page.count("no picture") == 3  # z's height, both of q's


def test_index_of_a_thousand_objects_is_light(tmp_path):
    rows = [
        _done(f"drawer_12_object_{k:04d}") if k % 20 else
        BatchRow(f"drawer_12_object_{k:04d}", f"/data/drawer_12/object_{k:04d}", FAILED,
                 error="InputError: " + "a long reason " * 20, seconds=3.0)
        for k in range(1000)
    ]

    # Every card shows real thumbnails: their sizes are read from the files.
    (tmp_path / "thumbnails").mkdir()
    Image.new("RGB", (240, 160)).save(tmp_path / "thumbnails" / "t.jpg")
    Image.new("RGB", (240, 160)).save(tmp_path / "thumbnails" / "t.png")
    thumbs = {r.name: {"relit": "thumbnails/t.jpg", "height": "thumbnails/t.png"} for r in rows}

    start = time.perf_counter()
    page = write_index(tmp_path, rows, thumbs=thumbs)
    elapsed = time.perf_counter() - start

    assert page.stat().st_size < 1_500_000
    assert elapsed < 3.0
    text = page.read_text(encoding="utf-8")
    assert text.count("<article") == 950 and "50 failed" in text
    assert text.count('width="240" height="160"') == 1900
