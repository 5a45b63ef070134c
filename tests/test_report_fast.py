"""report.html of a large run is made from subsamples; the parallel PNG writer writes valid PNGs."""

import base64
import io
import re
import zlib

import cv2
import numpy as np
import pytest
from PIL import Image

from ptmcore import png
from ptmcore.images import load_stack, read_image
from reconstruct.mesh.grid import grid_mesh
from reconstruct.mesh.ply import write_ply
from reconstruct.report import figures, html, outputs, plots
from reconstruct.surface.normalmaps import read_normal_map

SHAPE = (3000, 4000)


def _embedded(page: str) -> dict[str, Image.Image]:
    """The page's pictures by their alt text."""
    found = {}
    for data, alt in re.findall(r'<img src="data:image/\w+;base64,([A-Za-z0-9+/=]+)" alt="([^"]*)"', page):
        found[alt] = Image.open(io.BytesIO(base64.b64decode(data)))
    return found


@pytest.fixture(scope="module")
def large_maps():
    """Normals, heights and albedo of a 12-megapixel relief."""
    h, w = SHAPE
    rows = np.arange(h, dtype=np.float32)[:, None]
    cols = np.arange(w, dtype=np.float32)[None, :]
    height = np.sin(cols / 90) * np.cos(rows / 70) * 8
    height[:40] = np.nan  # outside the object
    gy, gx = np.gradient(np.nan_to_num(height))
    normals = np.dstack([-gx, gy, np.ones_like(gx)])
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    albedo = np.full((h, w, 3), 180, np.uint8)
    return normals.astype(np.float32), height.astype(np.float32), albedo


@pytest.fixture(scope="module")
def large_folder(tmp_path_factory, large_maps):
    """An output folder as a 12-megapixel run writes it (no PTM: relit from the normals)."""
    normals, height, albedo = large_maps
    folder = tmp_path_factory.mktemp("large")
    outputs.write_npy(folder / "normals.npy", normals)
    outputs.write_height_tiff(folder / "height.tif", height, "mm", 0.02)
    png.write_png(folder / "albedo.png", albedo)
    # Step 6: more faces than figures.MAX_RENDER_FACES, so the render is of the heights.
    write_ply(folder / "mesh.ply", grid_mesh(height, step=6, pixel_size=0.02))
    return folder


def _report(h: int, w: int) -> dict:
    return {"inputs": {"capture": "synthetic", "width": w, "height": h}, "parameters": {"pixel_size": 0.02},
            "height_unit": "mm", "mesh": {"step": 6}, "stages": {}, "versions": {}, "warnings": []}


def _spy(monkeypatch) -> dict[str, list[tuple[int, ...]]]:
    """Record the shapes of the arrays that the pictures are made from; the mesh "render"
    is a grey image (no OpenGL needed)."""
    seen: dict[str, list[tuple[int, ...]]] = {}

    def record(module, name):
        original = getattr(module, name)

        def spy(array, *args, **kwargs):
            seen.setdefault(name, []).append(np.shape(array))
            return original(array, *args, **kwargs)
        monkeypatch.setattr(module, name, spy)

    for name in ("height_figure", "normal_colors", "relit_lambertian", "surface_from_height"):
        record(figures, name)
    record(plots, "profile_figure")

    def render(mesh, size=(900, 600), *, exaggeration=1.0):
        seen.setdefault("mesh_render", []).append(np.shape(mesh[0]) if isinstance(mesh, tuple) else ("file",))
        if isinstance(mesh, tuple):  # coloured by the albedo's samples at the vertices
            seen.setdefault("mesh_colours", []).append(None if mesh[2] is None else mesh[2].shape)
        return np.full((size[1], size[0], 3), 128, np.uint8)

    monkeypatch.setattr(figures, "mesh_render", render)
    return seen


def _check_small(seen: dict, page: str) -> None:
    side = figures.PREVIEW_SIDE
    for name in ("height_figure", "normal_colors", "relit_lambertian", "surface_from_height", "profile_figure"):
        assert seen.get(name), f"{name} was not called"
        for shape in seen[name]:
            assert max(shape[:2]) <= side, (name, shape)
    # The mesh is rendered from a grid of heights of at most MESH_RENDER_SIDE samples a side.
    (vertices,) = seen["mesh_render"]
    assert vertices[0] <= figures.MESH_RENDER_SIDE**2
    assert seen["mesh_colours"] == [vertices], "the mesh is rendered with the albedo's colours"
    stride = int(re.search(r"sampled every (\d+) pixels", page).group(1))
    assert stride >= max(SHAPE) / figures.MESH_RENDER_SIDE
    pictures = _embedded(page)
    assert len(pictures) >= 11  # six relit, albedo, normal map, height map, profile, mesh
    for alt, image in pictures.items():
        assert image.width <= figures.MAX_WIDTH and image.height <= figures.MAX_WIDTH, (alt, image.size)


def test_large_report_from_files_uses_subsamples(large_folder, monkeypatch):
    seen = _spy(monkeypatch)
    page = html.report_html(large_folder, report=_report(*SHAPE))
    _check_small(seen, page)
    assert "scale bar in mm" in page and "no mesh render" not in page


def test_large_report_from_arrays_reads_no_map(large_maps, tmp_path, monkeypatch):
    """With previews and thumbnails given, the maps and photographs are not read again."""
    normals, height, albedo = large_maps
    # mesh.ply's header alone says how large the mesh is; the maps are not in the folder.
    (tmp_path / "mesh.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000\n"
                                        b"property float x\nelement face 8000000\n"
                                        b"property list uchar int vertex_indices\nend_header\n")
    photographs = [(tmp_path / f"missing_{k}.jpg", np.array([0.0, 0.0, 1.0])) for k in range(30)]
    picks = html.contact_sheet_picks(len(photographs))
    assert len(picks) == html.CONTACT_SHEET and picks[0] == 0 and picks[-1] == 29
    thumbnails = {k: np.full((160, 240, 3), 5 * k, np.uint8) for k in picks}
    seen = _spy(monkeypatch)
    previews = figures.previews(normals=normals, height=height, albedo=albedo)
    assert previews.stride == 5 and previews.normals.shape == (600, 800, 3)
    assert previews.albedo.dtype == np.uint8 and previews.height.dtype == np.float32
    page = html.report_html(tmp_path, report=_report(*SHAPE), photographs=photographs,
                            previews=previews, thumbnails=thumbnails)
    _check_small(seen, page)
    assert "Lambertian shading of the normals and albedo" in page
    sheet = [image for alt, image in _embedded(page).items() if "light az" in alt]
    assert len(sheet) == html.CONTACT_SHEET and "no contact sheet" not in page
    assert all(image.size == (240, 160) for image in sheet)


def test_previews_of_memory_maps_read_only_the_rows_taken(large_folder):
    maps = {"normals": figures.map_array(large_folder / "normals.npy"),
            "height": figures.map_array(large_folder / "height.tif")}
    assert all(isinstance(m, np.memmap) for m in maps.values())
    small = figures.previews(**maps, max_side=400)
    assert small.stride == 10 and small.height.shape == (300, 400) and small.albedo is None
    np.testing.assert_array_equal(small.normals, np.load(large_folder / "normals.npy")[::10, ::10])
    assert not isinstance(small.height, np.memmap)


def test_stack_thumbnail_matches_the_photograph(tmp_path):
    rng = np.random.default_rng(3)
    base = cv2.resize(rng.integers(30, 220, (30, 40, 3)).astype(np.uint8), (400, 300), interpolation=cv2.INTER_CUBIC)
    paths = []
    for k, gain in enumerate((0.6, 0.8, 1.0)):
        paths.append(tmp_path / f"p{k}.png")
        png.write_png(paths[-1], np.round(base * gain).astype(np.uint8))
    stack = load_stack(paths)
    for k, path in enumerate(paths):
        thumb = figures.stack_thumbnail(stack, k, max_side=120)
        expected = figures.photograph_thumbnail(path, max_side=120)
        assert thumb.shape == expected.shape == (90, 120, 3) and thumb.dtype == np.uint8
        # The stack's colour is the capture's mean: each photograph's own differs a little.
        assert np.abs(thumb.astype(int) - expected).mean() < 4


@pytest.mark.parametrize("shape, dtype", [((37, 53, 3), np.uint16), ((37, 53, 3), np.uint8), ((37, 53), np.uint8),
                                          ((41, 7), np.uint16), ((1, 1), np.uint8)])
@pytest.mark.parametrize("compress", [True, False])
def test_write_png_round_trip(tmp_path, monkeypatch, shape, dtype, compress):
    monkeypatch.setattr(png, "_PNG_BAND_BYTES", 300)  # many bands, each its own deflate stream
    rng = np.random.default_rng(1)
    image = rng.integers(0, np.iinfo(dtype).max + 1, shape).astype(dtype)
    image[shape[0] // 3 :] = 7  # runs, for the run-length matching
    path = tmp_path / "image.png"
    png.write_png(path, image, compress=compress)
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    back = back[..., ::-1] if back.ndim == 3 else back
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, image)
    np.testing.assert_array_equal(read_image(path), image)
    with Image.open(path) as im:
        im.verify()  # every chunk's CRC
    data = path.read_bytes()
    # One zlib stream over the IDAT chunks, with its Adler-32.
    stream, pos = b"", 8
    while pos < len(data):
        (length,) = np.frombuffer(data[pos : pos + 4], ">u4")
        if data[pos + 4 : pos + 8] == b"IDAT":
            stream += data[pos + 8 : pos + 8 + length]
        pos += 12 + int(length)
    assert len(zlib.decompress(stream)) == shape[0] * (1 + shape[1] * image.itemsize * (3 if len(shape) == 3 else 1))


def test_write_png_rejects_what_png_cannot_hold(tmp_path):
    with pytest.raises(TypeError):
        png.write_png(tmp_path / "x.png", np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError):
        png.write_png(tmp_path / "x.png", np.zeros((4, 4, 4), np.uint8))
    assert not (tmp_path / "x.png").exists()


def test_adler32_combine():
    rng = np.random.default_rng(2)
    for _ in range(50):
        a, b = rng.bytes(int(rng.integers(0, 100_000))), rng.bytes(int(rng.integers(0, 100_000)))
        assert png._adler32_combine(zlib.adler32(a), zlib.adler32(b), len(b)) == zlib.adler32(a + b)


def test_normals_png_reads_back(tmp_path, large_maps):
    normals = large_maps[0][:200, :300]
    outputs.write_normals_png(tmp_path / "normals.png", normals)
    back = read_normal_map(tmp_path / "normals.png")
    assert np.abs(back - normals).max() < 1e-4
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "normals.png"), cv2.IMREAD_UNCHANGED)[..., ::-1],
                                  outputs.normals_to_rgb16(normals))


def _old_albedo_to_srgb8(albedo_rgb):
    """The whole-image encoding albedo_to_srgb8 made before it went in bands."""
    from ptmcore.images import linear_to_srgb

    flat = albedo_rgb.reshape(-1)
    sample = flat[:: max(1, flat.size // 1_000_000)]
    sample = sample[np.isfinite(sample)]
    top = float(np.percentile(sample, 99.9)) if sample.size else 1.0
    scale = top if top > 1.0 else 1.0
    a = np.ascontiguousarray(albedo_rgb, dtype=np.float32)
    index = cv2.addWeighted(a, 65535.0 / scale, a, 0.0, 0.0, dtype=cv2.CV_16U)
    table = np.round(linear_to_srgb(np.arange(65536, dtype=np.float64) / 65535.0) * 255).astype(np.uint8)
    return table[index], scale


@pytest.mark.parametrize("peak", [0.5, 3.0])
def test_albedo_texture_is_the_product_encoded_in_bands(peak):
    rng = np.random.default_rng(7)
    h, w = 1100, 1500  # several bands, and more than a million values: a strided sample
    chroma = rng.uniform(0.2, 1.6, (h, w, 3)).astype(np.float32)
    albedo = rng.uniform(0, peak, (h, w)).astype(np.float32)
    albedo[5, :7] = np.nan
    albedo[6, :3] = np.inf
    product = chroma * albedo[..., None]
    old, old_scale = _old_albedo_to_srgb8(product)
    for threads in (1, 2):
        texture, scale = outputs.albedo_texture(chroma, albedo, threads=threads)
        assert scale == old_scale and (scale > 1) == (peak > 1)
        np.testing.assert_array_equal(texture, old)
        again, scale = outputs.albedo_to_srgb8(product, threads=threads)
        assert scale == old_scale
        np.testing.assert_array_equal(again, old)
