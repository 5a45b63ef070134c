"""Reading a ``web/`` folder back (reconstruct.report.webread): every basis, whole and tiled,
sRGB and linear, renders as the basis it was written from, within the 8-bit quantisation and
the JPEG error; a preview reads only what it needs; bad folders are one-line InputErrors."""

import json
import shutil

import numpy as np
import pytest
from helpers import dome
from PIL import Image

from ptmcore.errors import InputError
from ptmcore.published import PublishedBasis
from ptmcore.relight import light_direction
from reconstruct.report import webread
from reconstruct.report.web import export_openlime, export_relightable, pyramid_levels
from reconstruct.report.webread import READERS, published_folder, read_relightable, relightable_shape

KINDS = ["ptm", "hsh2", "hsh3", "hsh4", "rbf", "bln"]
LIGHTS = [light_direction(azimuth_deg=a, elevation_deg=e) for a, e in [(0, 30), (90, 60), (200, 45), (0, 90),
                                                                        (315, 15), (135, 75)]]
#: JPEG error in levels at quality 100 against the exact bytes (measured in test_web: RGB
#: whole planes ≤ 2, libvips' YCbCr tiles ≤ 4).
JPEG_LEVELS = {False: 2, True: 4}


def _smooth(h, w, k, rng):
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.zeros((h, w, k))
    for i in range(k):
        fx, fy = rng.uniform(0.5, 3, 2) * 2 * np.pi / np.array([w, h])
        out[..., i] = np.sin(fx * cols + fy * rows + rng.uniform(0, 2 * np.pi))
    return out


def make_basis(kind, h=40, w=60, seed=0, encoding="srgb"):
    """A small synthetic basis of each kind, relit mostly within 0–1."""
    rng = np.random.default_rng(seed)
    colour = np.clip(128 + 100 * _smooth(h, w, 3, rng), 0, 255).astype(np.uint8)
    if kind == "ptm":
        planes = 0.15 * _smooth(h, w, 6, rng)
        planes[..., 0] += 0.6
        return PublishedBasis("ptm", "lrgb", planes.astype(np.float32), encoding, colour=colour, name="ptm")
    if kind.startswith("hsh"):
        order = int(kind[3:])
        planes = 0.2 * _smooth(h, w, order * order, rng)
        planes[..., 0] += 1.5
        return PublishedBasis("hsh", "lrgb", planes.astype(np.float32), encoding, colour=colour, order=order,
                              name=kind)
    d, k = (24, 5) if kind == "rbf" else (25, 7)
    q, _ = np.linalg.qr(rng.normal(size=(3 * d, k)))
    basis = np.concatenate([rng.uniform(0.3, 0.6, (1, d, 3)), q.T.reshape(k, d, 3)]).astype(np.float32)
    planes = (0.8 * _smooth(h, w, k, rng)).astype(np.float32)
    if kind == "rbf":
        return PublishedBasis("rbf", "mrgb", planes, encoding, lights=dome(d, seed=seed), sigma=0.35, basis=basis,
                              name="rbf")
    return PublishedBasis("bln", "mrgb", planes, encoding, resolution=5, basis=basis, name="bilinear")


def _one_line_error(call, *needles):
    with pytest.raises(InputError) as err:
        call()
    message = str(err.value)
    assert "\n" not in message, message
    for needle in needles:
        assert needle in message, (needle, message)
    return message


# --- round trips --------------------------------------------------------------------------


@pytest.mark.parametrize("tiles", [False, True])
@pytest.mark.parametrize("encoding", ["srgb", "linear"])
@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_renders_as_the_basis(tmp_path, kind, encoding, tiles):
    """Every attribute comes back; each plane within half a quantisation step plus the JPEG's
    error of the original, the colour within the JPEG's error, the MRGB basis within half a step
    of its bytes; so each rendering within the bound those give, per pixel."""
    basis = make_basis(kind, w=300 if tiles else 60, encoding=encoding)
    folder = tmp_path / "web"
    export_relightable(folder, basis, quality=100, tiles=tiles)
    assert (folder / "plane_0.dzi").is_file() == tiles
    read = read_relightable(folder)
    assert (read.type, read.colorspace, read.encoding, read.name, read.order, read.resolution) == (
        basis.type, basis.colorspace, encoding, basis.name, basis.order, basis.resolution)
    assert read.planes.shape == basis.planes.shape and read.planes.dtype == np.float32
    assert relightable_shape(folder) == basis.shape
    material = json.loads((folder / "info.json").read_text())["materials"][0]
    j = JPEG_LEVELS[tiles]
    k = basis.planes.shape[2]
    first = 3 if basis.colorspace == "lrgb" else 0
    eps = np.array(material["scale"][first:first + k]) * (0.5 + j) / 255
    assert np.all(np.abs(read.planes - basis.planes) <= eps + 1e-6)
    if basis.colorspace == "lrgb":
        assert read.colour.dtype == np.uint8 and np.abs(read.colour.astype(int) - basis.colour).max() <= j
    else:
        ranges = np.array(material["range"][:k])
        assert read.basis.shape == basis.basis.shape
        assert np.abs(read.basis[0] - basis.basis[0]).max() <= 0.5 / 255 + 1e-6
        assert np.all(np.abs(read.basis[1:] - basis.basis[1:]) <= 0.5 / ranges[:, None, None] + 1e-6)
        if kind == "rbf":
            np.testing.assert_array_equal(read.lights, basis.lights)
            assert read.sigma == basis.sigma
    for light in LIGHTS:
        err = np.abs(read.render(light) - basis.render(light))
        if basis.colorspace == "lrgb":
            w = np.abs(basis.weights(light))
            luminance = np.abs(read.planes @ basis.weights(light).astype(np.float32))
            bound = j / 255 * luminance[..., None] + (basis.colour / 255.0) * float(w @ eps)
        else:
            b = np.abs(read.weights(light))
            bound = 0.5 / 255 + (b[1:].T @ eps) + (np.abs(basis.planes) @ (0.5 / ranges))[..., None]
        assert np.all(err <= bound + 1e-5), (light, (err - bound).max())
        assert bound.max() < 0.06  # a few levels: the bound says something
        shown = np.abs(read.display(light).astype(int) - basis.display(light))
        assert shown.mean() < 1.5, shown.mean()


def test_the_colour_takes_its_scale_and_bias(tmp_path):
    """OpenLIME dequantises the colour plane as every plane: a folder whose colour has a scale
    and bias (not ours: 1 and 0) is read as it shows it."""
    basis = make_basis("ptm")
    export_relightable(tmp_path, basis, quality=100, tiles=False)
    info = json.loads((tmp_path / "info.json").read_text())
    info["materials"][0]["scale"][:3] = [0.5, 0.5, 0.5]
    (tmp_path / "info.json").write_text(json.dumps(info))
    read = read_relightable(tmp_path)
    assert np.abs(read.colour.astype(int) - np.rint(basis.colour / 2)).max() <= 2


@pytest.mark.parametrize("kind", ["hsh2", "hsh3", "hsh4", "rbf"])
def test_a_folder_relight_wrote_without_viewer_json(tmp_path, kind):
    """Relight writes no viewer.json: sRGB values, the type's name, the HSH order that fits."""
    basis = make_basis(kind, encoding="linear")
    export_relightable(tmp_path, basis, tiles=False)
    (tmp_path / "viewer.json").unlink()
    read = read_relightable(tmp_path / "info.json")
    assert read.encoding == "srgb" and read.name == basis.name and read.order == basis.order
    assert read.planes.shape == basis.planes.shape


def test_a_pyramid_without_viewer_json_is_found(tmp_path):
    export_relightable(tmp_path, make_basis("bln", w=300), tiles=True)
    (tmp_path / "viewer.json").unlink()
    assert read_relightable(tmp_path).planes.shape == (40, 300, 7)


def test_an_output_folder_reads_its_web(tmp_path):
    basis = make_basis("hsh3")
    export_relightable(tmp_path / "out" / "web", basis, tiles=False)
    assert read_relightable(tmp_path / "out").name == "hsh3"
    assert published_folder(tmp_path / "out") == tmp_path / "out" / "web"
    # A web/ of the PTM itself (a run from a .ptm, older runs) is not a chosen basis.
    export_openlime(tmp_path / "old" / "web", np.ones((8, 9, 6), np.float32), np.zeros((8, 9, 3), np.uint8))
    assert published_folder(tmp_path / "old") is None
    assert read_relightable(tmp_path / "old").type == "ptm"
    assert published_folder(tmp_path / "none") is None


# --- previews read little -------------------------------------------------------------------


def _decoded_sides(monkeypatch):
    """Record the size of every JPEG decoded."""
    import simplejpeg

    sides = []
    real = simplejpeg.decode_jpeg

    def spy(*args, **kwargs):
        image = real(*args, **kwargs)
        sides.append(image.shape[:2])
        return image

    monkeypatch.setattr(simplejpeg, "decode_jpeg", spy)
    return sides


@pytest.mark.parametrize("max_side", [40, 100, 170, 260])
def test_max_side_decodes_whole_planes_scaled(tmp_path, monkeypatch, max_side):
    basis = make_basis("rbf", h=200, w=300)
    export_relightable(tmp_path, basis, quality=100, tiles=False)
    full = read_relightable(tmp_path)
    sides = _decoded_sides(monkeypatch)
    small = read_relightable(tmp_path, max_side=max_side)
    h, w = small.shape
    assert max_side <= w < 2 * max_side and abs(h / w - 2 / 3) < 0.02, (h, w)
    # libjpeg decoded each plane at a DCT scale: at least max_side, below 8·max_side, never
    # the full 300 pixels.
    assert len(sides) == 2 and all(max_side <= max(s) < min(300, 8 * max_side) for s in sides), sides
    # The planes are the full ones averaged (the DCT scaling's own filter, then the box).
    import cv2

    expected = np.stack([cv2.resize(full.planes[..., c], (w, h), interpolation=cv2.INTER_AREA)
                         for c in range(full.planes.shape[2])], axis=-1)
    span = full.planes.max(axis=(0, 1)) - full.planes.min(axis=(0, 1))
    assert (np.abs(small.planes - expected).mean(axis=(0, 1)) < 0.02 * span).all()


def test_max_side_reads_only_its_pyramid_level(tmp_path):
    basis = make_basis("ptm", h=100, w=600)
    export_relightable(tmp_path, basis, tiles=True)
    assert pyramid_levels(600, 100) == [(150, 25), (300, 50), (600, 100)]
    for j in range(3):
        shutil.rmtree(tmp_path / f"plane_{j}_files" / "2")  # the full level is gone
    small = read_relightable(tmp_path, max_side=200)
    assert small.shape == (50, 300)
    assert read_relightable(tmp_path, max_side=150).shape == (25, 150)
    assert read_relightable(tmp_path, max_side=1).shape == (25, 150)
    # The level is the whole image halved: its rendering is the full one's average.
    image = basis.display(LIGHTS[1]).astype(np.float32)
    halved = image.reshape(50, 2, 300, 2, 3).mean(axis=(1, 3))
    assert np.abs(small.display(LIGHTS[1]) - halved).mean() < 3
    _one_line_error(lambda: read_relightable(tmp_path, max_side=400), "plane_0_files/2/0_0.jpg", "missing tile")


def test_max_side_must_be_positive(tmp_path):
    export_relightable(tmp_path, make_basis("ptm"), tiles=False)
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="max_side"):
            read_relightable(tmp_path, max_side=bad)


# --- the types' table ---------------------------------------------------------------------------


def _neural_basis(h=40, w=60, seed=0):
    """A NeuralRTI basis of random smooth codes and a random decoder of hidden width 10 (padded
    to 12 in info.json, so the unpadding is tested)."""
    rng = np.random.default_rng(seed)
    codes = (2 * _smooth(h, w, 9, rng)).astype(np.float32)
    codes[..., 4] = 0.7  # a constant code number: bytes 0 and min = max
    sizes = [(11, 10), (10, 10), (10, 3)]
    network = [((rng.normal(size=s) / np.sqrt(s[0])).astype(np.float32), rng.normal(0, 0.1, s[1]).astype(np.float32))
               for s in sizes]
    network[2] = (network[2][0] * 0.2, network[2][1] + 0.5)
    return PublishedBasis("neural", "rgb", codes, network=network, name="neural")


@pytest.mark.parametrize("tiles", [False, True])
def test_neural_round_trip(tmp_path, tiles):
    basis = _neural_basis(w=300 if tiles else 60)
    folder = tmp_path / "web"
    export_relightable(folder, basis, quality=100, tiles=tiles)
    assert (folder / "plane_1.dzi").is_file() == tiles and not (folder / "plane_0.jpg").exists()
    read = read_relightable(folder)
    assert (read.type, read.colorspace, read.name, read.planes.shape) == ("neural", "rgb", "neural", (40, basis.shape[1], 9))
    for (w0, b0), (w1, b1) in zip(basis.network, read.network):
        np.testing.assert_array_equal(w1, w0)
        np.testing.assert_array_equal(b1, b0)
    info = json.loads((folder / "info.json").read_text())
    step = (np.array(info["max"]) - np.array(info["min"])) / 255
    assert np.all(np.abs(read.planes - basis.planes) <= step * (0.5 + JPEG_LEVELS[tiles]) + 1e-5)
    np.testing.assert_allclose(read.planes[..., 4], 0.7, atol=1e-6)
    for light in LIGHTS[:3]:
        assert np.abs(read.display(light).astype(int) - basis.display(light)).mean() < 1.5
    if not tiles:  # (a pyramid's smallest level is its one-tile level, 150 pixels here)
        small = read_relightable(folder, max_side=20)
        assert 20 <= max(small.shape) < 40 and small.network is not None


def test_neural_bgr_folder_is_read_in_its_order(tmp_path):
    """NeuralRTI's own folders say "bgr": OpenLIME swizzles the planes' texels and the output
    alike, so relabelled planes and output give the same image."""
    basis = _neural_basis()
    export_relightable(tmp_path / "rgb", basis, quality=100, tiles=False)
    codes = basis.planes.reshape(40, 60, 3, 3)[..., ::-1].reshape(40, 60, 9)
    (w3, b3) = basis.network[2]
    swapped = PublishedBasis("neural", "rgb", codes, network=[*basis.network[:2], (w3[:, ::-1].copy(), b3[::-1].copy())])
    export_relightable(tmp_path / "bgr", swapped, quality=100, tiles=False)
    info = json.loads((tmp_path / "bgr" / "info.json").read_text())
    info["colorspace"] = "bgr"
    (tmp_path / "bgr" / "info.json").write_text(json.dumps(info))
    a, b = read_relightable(tmp_path / "rgb"), read_relightable(tmp_path / "bgr")
    np.testing.assert_allclose(b.render(LIGHTS[0]), a.render(LIGHTS[0]), atol=2e-3)


@pytest.mark.parametrize("change, needles", [
    (lambda i: i.pop("min"), ["info.json", "'min'"]),
    (lambda i: i.update(planes=6), ["planes"]),
    (lambda i: i["weights"].pop(), ["weights and biases"]),
    (lambda i: i["weights"][1].pop(), ["weights[1]"]),
    (lambda i: i.update(samples=0), ["samples"]),
    (lambda i: i.update(colorspace="rgba"), ["colorspace"]),
])
def test_bad_neural_info(tmp_path, change, needles):
    export_relightable(tmp_path, _neural_basis(), tiles=False)
    info = json.loads((tmp_path / "info.json").read_text())
    change(info)
    (tmp_path / "info.json").write_text(json.dumps(info))
    _one_line_error(lambda: read_relightable(tmp_path), *needles)


def test_a_new_type_is_one_function(tmp_path, monkeypatch):
    export_relightable(tmp_path, make_basis("rbf"), tiles=False)
    info = json.loads((tmp_path / "info.json").read_text())
    info["type"] = "learned"
    (tmp_path / "info.json").write_text(json.dumps(info))
    _one_line_error(lambda: read_relightable(tmp_path), "info.json", "unknown type 'learned'")

    def read_learned(web):
        return PublishedBasis("rbf", "mrgb", web.values(0, web.nplanes), name="learned")

    # Until then, an output folder's viewers show its PTM (published_folder: none readable).
    (tmp_path / "out").mkdir()
    shutil.copytree(tmp_path, tmp_path / "out" / "web", ignore=lambda d, names: ["out"] if "out" in names else [])
    assert published_folder(tmp_path / "out") is None
    monkeypatch.setitem(READERS, "learned", read_learned)
    assert published_folder(tmp_path / "out") == tmp_path / "out" / "web"
    read = read_relightable(tmp_path, max_side=20)
    assert read.name == "learned" and read.planes.shape[2] == 6 and 20 <= read.planes.shape[1] < 40


# --- bad folders ---------------------------------------------------------------------------


@pytest.fixture
def web(tmp_path):
    folder = tmp_path / "web"
    export_relightable(folder, make_basis("hsh3"), tiles=False)
    return folder


def _edit_info(folder, change):
    info = json.loads((folder / "info.json").read_text())
    change(info)
    (folder / "info.json").write_text(json.dumps(info))


@pytest.mark.parametrize(
    ("change", "needles"),
    [
        (lambda i: i.update(type="cubic"), ["unknown type 'cubic'"]),
        (lambda i: i.update(type=["hsh"]), ["unknown type"]),
        (lambda i: i.update(colorspace="rgb"), ["colour space 'rgb'"]),
        (lambda i: i.update(width=10**9), ["width must be"]),
        (lambda i: i.update(width=0), ["width must be"]),
        (lambda i: i.update(height="40"), ["height must be"]),
        (lambda i: i.update(width=40000, height=30000), ["more than the"]),
        (lambda i: i.update(nplanes=15), ["materials[0].scale must be a list of 15"]),
        (lambda i: i.update(nplanes=0), ["nplanes must be"]),
        (lambda i: i["materials"][0].update(bias=[0.0] * 11 + [None]), ["not a number"]),
        (lambda i: i.pop("materials"), ["no 'materials'"]),
        (lambda i: i.update(format="png"), ["format 'png'"]),
    ],
)
def test_bad_info_json(web, change, needles):
    _edit_info(web, change)
    _one_line_error(lambda: read_relightable(web), str(web / "info.json"), *needles)


def test_inconsistent_plane_counts(tmp_path):
    folder = tmp_path / "ptm"
    export_relightable(folder, make_basis("ptm"), tiles=False)

    def twelve(i):
        i["nplanes"] = 12
        i["materials"][0]["scale"] += [1.0] * 3
        i["materials"][0]["bias"] += [0.0] * 3
    _edit_info(folder, twelve)
    _one_line_error(lambda: read_relightable(folder), "info.json", "nplanes 9")
    folder = tmp_path / "hsh"
    export_relightable(folder, make_basis("hsh2"), tiles=False)
    (folder / "viewer.json").write_text(json.dumps({"order": 3, "encoding": "srgb"}))
    _one_line_error(lambda: read_relightable(folder), "info.json", "order 3 has 9 terms")
    folder = tmp_path / "rbf"
    export_relightable(folder, make_basis("rbf"), tiles=False)
    _edit_info(folder, lambda i: i.update(lights=i["lights"][:-3]))
    _one_line_error(lambda: read_relightable(folder), "info.json", "basis must be a list of")
    _edit_info(folder, lambda i: i.update(sigma=-1))
    _one_line_error(lambda: read_relightable(folder), "sigma")


@pytest.mark.parametrize("text", ["", '{"width": 60, "height"', "[1, 2]", '{"width": NaN}'])
def test_malformed_json(web, text):
    (web / "info.json").write_text(text)
    _one_line_error(lambda: read_relightable(web), str(web / "info.json"), "info.json")


def test_non_finite_numbers(web):
    text = (web / "info.json").read_text()
    (web / "info.json").write_text(text.replace('"scale": [', '"scale": [1e999, ', 1).replace(
        '"bias": [', '"bias": [0.0, ', 1).replace('"nplanes": 12', '"nplanes": 13'))
    _one_line_error(lambda: read_relightable(web), "info.json", "not finite")


def test_bad_viewer_json(web):
    (web / "viewer.json").write_text('{"encoding": "gamma"}')
    _one_line_error(lambda: read_relightable(web), str(web / "viewer.json"), "encoding")
    (web / "viewer.json").write_text('{"encoding": ')
    _one_line_error(lambda: read_relightable(web), str(web / "viewer.json"), "malformed")
    _one_line_error(lambda: published_folder(web.parent), "viewer.json")


def test_missing_files(web, tmp_path):
    _one_line_error(lambda: read_relightable(tmp_path / "nowhere"), "not found")
    (tmp_path / "empty").mkdir()
    _one_line_error(lambda: read_relightable(tmp_path / "empty"), "no info.json")
    (web / "plane_2.jpg").unlink()
    _one_line_error(lambda: read_relightable(web), str(web / "plane_2.jpg"), "missing")


def test_wrong_sizes_are_refused_before_decoding(web, monkeypatch):
    sides = _decoded_sides(monkeypatch)
    _edit_info(web, lambda i: i.update(width=61))
    _one_line_error(lambda: read_relightable(web), str(web / "plane_0.jpg"), "60 × 40", "61 × 40")
    # A large declared size: refused at the first plane's header, nothing decoded or allocated.
    _edit_info(web, lambda i: i.update(width=20000, height=20000))
    _one_line_error(lambda: read_relightable(web), "plane_0.jpg", "20000 × 20000")
    assert sides == []
    # One plane of another size among right ones.
    _edit_info(web, lambda i: i.update(width=60, height=40))
    Image.new("RGB", (60, 41)).save(web / "plane_3.jpg")
    _one_line_error(lambda: read_relightable(web), str(web / "plane_3.jpg"), "60 × 41")
    assert sides == []


def test_a_truncated_or_foreign_plane(web):
    data = (web / "plane_1.jpg").read_bytes()
    (web / "plane_1.jpg").write_bytes(data[: len(data) // 2])
    _one_line_error(lambda: read_relightable(web), str(web / "plane_1.jpg"))
    (web / "plane_1.jpg").write_bytes(b"GIF89a" + bytes(100))
    _one_line_error(lambda: read_relightable(web), str(web / "plane_1.jpg"), "not a JPEG")


def test_bad_pyramids(tmp_path):
    folder = tmp_path / "web"
    export_relightable(folder, make_basis("rbf", w=300), tiles=True)
    (folder / "plane_1_files" / "1" / "1_0.jpg").unlink()
    _one_line_error(lambda: read_relightable(folder), str(folder / "plane_1_files" / "1" / "1_0.jpg"), "missing tile")
    shutil.copy(folder / "plane_0_files" / "1" / "0_0.jpg", folder / "plane_1_files" / "1" / "1_0.jpg")
    _one_line_error(lambda: read_relightable(folder), "1_0.jpg", "declares 47 × 40")
    text = (folder / "plane_0.dzi").read_text()
    (folder / "plane_0.dzi").write_text(text.replace('Width="300"', 'Width="301"'))
    _one_line_error(lambda: read_relightable(folder), str(folder / "plane_0.dzi"), "301 × 40")
    (folder / "plane_0.dzi").write_text(text[:40])
    _one_line_error(lambda: read_relightable(folder), str(folder / "plane_0.dzi"), "malformed")
    (folder / "plane_0.dzi").write_text(text.replace('TileSize="254"', 'TileSize="-1"'))
    _one_line_error(lambda: read_relightable(folder), "plane_0.dzi", "TileSize")


def test_memory_is_asked_before_large_planes(web, monkeypatch):
    import ptmcore.resources

    monkeypatch.setattr(webread, "_ASK_MEMORY_BYTES", 0)
    monkeypatch.setattr(ptmcore.resources, "available_memory_mb", lambda: 0.01)
    _one_line_error(lambda: read_relightable(web), "info.json", "memory")
    assert read_relightable(web, max_side=8).planes.shape == (5, 8, 9)  # a preview fits
