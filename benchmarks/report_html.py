"""Time and memory of ``report.html`` for a large output folder (24 megapixels by default).

An output folder is made as ``reconstruct run`` writes it (normals.npy, normals.png, albedo.png,
height.tif, mesh.ply with the automatic mesh step, report.json) from a synthetic relief, with 8
full-size JPEG photographs for the contact sheet; then :func:`reconstruct.report.html.write_report_html`
runs in a fresh process, which reports its wall time and the peak RSS above what the imports
take. The folder has no ``coefficients.ptm``: relighting uses the normals and albedo (a PTM
would be relit from a subsample decoded by ``read_ptm(path, max_side=480)``).

Two ways of calling it are measured: ``files``, the page made from the folder alone (the maps
read through memory maps, albedo.png decoded whole for the albedo picture and the mesh's colours,
the photographs decoded for the contact sheet and read for the lights' plot), and ``arrays``, as a
pipeline that holds the maps and the decoded photographs can call it: ``previews`` of the maps
and ``thumbnails`` from the stack (``figures.stack_thumbnail``), both made inside the timing.
Each is also timed with the import of matplotlib and the loading of the compiled mesh
rasteriser (:mod:`reconstruct.report.raster`) inside the timing (``seconds_cold``), as the first
page of a process costs.

Run: ``.venv/bin/python benchmarks/report_html.py [--size 6000x4000]``
Prints the numbers and writes ``benchmarks/results/report_html.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ptmcore.png import write_png  # noqa: E402
from reconstruct.report import outputs  # noqa: E402
from reconstruct.mesh.grid import grid_mesh  # noqa: E402
from reconstruct.mesh.ply import write_ply  # noqa: E402
from reconstruct.pipeline.stages import auto_step  # noqa: E402

_MEASURE = """
import json, sys, time
sys.path.insert(0, {root!r})
from pathlib import Path
from reconstruct.pipeline.profiling import StageTimer, current_rss_mb
from reconstruct.report import figures, html as report_html
import numpy as np
if not {cold!r}:
    import matplotlib.figure  # the imports' memory is not the report's
    from reconstruct.report import raster
    raster.render_mesh(np.eye(3), [[0, 1, 2]], size=(8, 8))  # its compiled code loaded
photos = [(p, np.array(d)) for p, d in json.loads({photos!r})]
folder = Path({folder!r})
if {mode!r} == "arrays":  # what the pipeline holds when it writes the page
    import tifffile
    from ptmcore.images import load_stack, read_image
    maps = {{"normals": np.load(folder / "normals.npy"), "height": tifffile.imread(folder / "height.tif"),
             "albedo": read_image(folder / "albedo.png")}}
    stack = load_stack([p for p, _ in photos], min_photographs=1)
base = current_rss_mb()
timer = StageTimer()
t0 = time.perf_counter()
with timer.stage("report"):  # resident memory sampled every 20 ms while the page is made
    kw = {{}}
    if {mode!r} == "arrays":
        kw = {{"previews": figures.previews(**maps),
               "thumbnails": {{k: figures.stack_thumbnail(stack, k) for k in report_html.contact_sheet_picks(len(photos))}}}}
    report_html.write_report_html(folder, photographs=photos, **kw)
print(json.dumps({{"seconds": time.perf_counter() - t0, "peak_rss_mb_above_imports": timer.stages["report"]["peak_rss_mb"] - base}}))
"""


def make_folder(folder: Path, shape: tuple[int, int]) -> list[tuple[str, list[float]]]:
    """A synthetic output folder of ``shape`` pixels; returns the photographs and their lights."""
    import cv2

    h, w = shape
    rows = np.arange(h, dtype=np.float32)[:, None]
    cols = np.arange(w, dtype=np.float32)[None, :]
    height = (np.sin(cols / 90) * np.cos(rows / 70) * 8).astype(np.float32)
    gy, gx = np.gradient(height)
    normals = np.dstack([-gx, gy, np.ones_like(gx)])
    del gx, gy
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    normals = normals.astype(np.float32)
    albedo = np.full((h, w, 3), 180, np.uint8)
    outputs.write_npy(folder / "normals.npy", normals)
    write_png(folder / "normals.png", outputs.normals_to_rgb16(normals))
    write_png(folder / "albedo.png", albedo)
    outputs.write_height_tiff(folder / "height.tif", height, "mm", 0.02)
    step = auto_step(shape)
    write_ply(folder / "mesh.ply", grid_mesh(height, texture=albedo, step=step, pixel_size=0.02))
    outputs.write_json(folder / "report.json", {
        "inputs": {"capture": "synthetic", "width": w, "height": h},
        "parameters": {"pixel_size": 0.02, "step": step}, "height_unit": "mm",
        "mesh": {"step": step, "unit": "mm"}, "stages": {}, "versions": {}, "warnings": [],
    })
    photos = []
    for k, az in enumerate(np.radians(np.arange(8) * 45.0)):
        light = [0.5 * np.cos(az), 0.5 * np.sin(az), np.sqrt(0.75)]
        shade = np.clip(normals @ np.asarray(light, np.float32), 0, 1)
        path = folder / f"photo_{k}.jpg"
        cv2.imwrite(str(path), np.round(shade * 230).astype(np.uint8))
        photos.append((str(path), light))
    return photos


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="6000x4000", help="WxH of the output folder")
    args = parser.parse_args()
    w, h = map(int, args.size.lower().split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        photos = make_folder(folder, (h, w))
        made = time.perf_counter() - t0
        result = {}
        for mode in ("files", "arrays"):
            for cold in (False, True):
                code = _MEASURE.format(root=str(ROOT), folder=str(folder), photos=json.dumps(photos), mode=mode,
                                       cold=cold)
                out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
                measured = json.loads(out.stdout.strip().splitlines()[-1])
                if cold:
                    result[mode]["seconds_cold"] = round(measured["seconds"], 3)
                else:
                    result[mode] = {"seconds": round(measured["seconds"], 3),
                                    "peak_rss_mb_above_imports": round(measured["peak_rss_mb_above_imports"])}
        size_kb = (folder / "report.html").stat().st_size / 1024
        page = (folder / "report.html").read_text()
    result.update({"size": args.size, "mesh_step": auto_step((h, w)), "report_kib": round(size_kb),
                   "mesh_render": "no mesh render" not in page, "folder_made_seconds": round(made, 1),
                   "machine": f"{platform.machine()}, {platform.python_version()}"})
    print(json.dumps(result, indent=2))
    (ROOT / "benchmarks" / "results").mkdir(exist_ok=True)
    (ROOT / "benchmarks" / "results" / "report_html.json").write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
