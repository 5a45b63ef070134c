"""Hostile input to the readers of files other than photographs: HP ``.ptm``, RTIViewer ``.rti``,
laser scans, ``.npy`` arrays, transform matrices.

Every case is refused with an :class:`InputError` naming the file (one line and exit status 2
from the command line), without blocking on a special file, without allocating from a lying
header, and without accepting a file whose header does not describe its payload.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import threading
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ptm_samples import jpeg_ptm, lrgb_bytes, rgb_bytes, sample_files, smooth_codes
from ptmcore.errors import InputError
from ptmcore.ptmfile import read_ptm
from ptmcore.ptmheader import HeaderCursor
from ptmcore.rtifile import read_rti_hsh

from test_fuzz_readers import mutated

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SCALE = [0.5, 0.5, 0.25, 0.5, 0.25, 1.0]
BIAS = [167, 97, 0, 0, 0, 0]
#: What reading one of the small files here may allocate: their decoded arrays, and the planes a
#: JPEG PTM's table claims (512 pixels a compressed byte, ptmcore.decoders) before its streams
#: are decoded.
ALLOCATION_BOUND = 16 << 20


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    # Module-scoped: hypothesis runs many examples in one call of the test function.
    return tmp_path_factory.mktemp("hostile")


def _outcome(read, path):
    """``read(path)``, or None when it raised an InputError naming ``path``; any other
    exception fails the test, and so does allocating more than :data:`ALLOCATION_BOUND`."""
    tracemalloc.start()
    try:
        return read(path)
    except InputError as exc:
        assert str(exc).startswith(str(path)), str(exc)
        assert "\n" not in str(exc)
        return None
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak <= ALLOCATION_BOUND, f"reading {path.name} allocated {peak:,} bytes"


def _cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "reconstruct", *args], capture_output=True, text=True,
                          timeout=120, cwd=cwd)


def _one_line(proc: subprocess.CompletedProcess, *names: str) -> str:
    """The stderr of a refused command: exit 2, one line, no traceback, naming ``names``."""
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for name in names:
        assert name in lines[0], lines[0]
    return lines[0]


# --- .ptm: payloads with no information, payloads larger than the header says ----------------


def _codes(h=5, w=8, seed=3):
    planes = smooth_codes(np.random.default_rng(seed), h, w, 9)
    return np.moveaxis(planes[:6], 0, -1), np.moveaxis(planes[6:9], 0, -1)


@pytest.mark.parametrize("value", [0, 128])
def test_a_constant_ptm_payload_is_refused(tmp_path, value):
    codes, rgb = _codes()
    path = tmp_path / "flat.ptm"
    path.write_bytes(lrgb_bytes(np.full_like(codes, value), np.full_like(rgb, value), SCALE, BIAS))
    with pytest.raises(InputError, match="every pixel holds the same polynomial"):
        read_ptm(path)


@pytest.mark.parametrize("layout", ["lrgb", "lrgb_1.1", "rgb", "jpeg_lrgb", "jpeg_rgb"])
def test_every_layout_refuses_the_same_polynomial_at_every_pixel(tmp_path, layout):
    """Each pixel's six bytes differ from one another but are the same at every pixel: one
    polynomial for the whole image, in every layout."""
    h, w = 4, 6
    pixel = np.array([10, 200, 30, 140, 50, 160], np.uint8)
    planes = np.broadcast_to(np.resize(pixel, 18)[:, None, None], (18, h, w)).copy()
    if layout.startswith("jpeg"):
        fmt = "PTM_FORMAT_JPEG_LRGB" if layout == "jpeg_lrgb" else "PTM_FORMAT_JPEG_RGB"
        data = jpeg_ptm(fmt, planes[:9] if layout == "jpeg_lrgb" else planes, SCALE, BIAS)[0]
    elif layout == "rgb":
        data = rgb_bytes(np.moveaxis(planes.reshape(3, 6, h, w), (0, 1), (2, 3)), SCALE, BIAS)
    else:
        version = "PTM_1.1" if layout == "lrgb_1.1" else "PTM_1.2"
        data = lrgb_bytes(np.moveaxis(planes[:6], 0, -1), np.moveaxis(planes[6:9], 0, -1), SCALE, BIAS, version)
    path = tmp_path / "one.ptm"
    path.write_bytes(data)
    with pytest.raises(InputError, match="every pixel holds the same polynomial"):
        read_ptm(path)


def test_varying_bytes_under_zero_scales_are_refused(tmp_path):
    codes, rgb = _codes()
    path = tmp_path / "zero.ptm"
    path.write_bytes(lrgb_bytes(codes, rgb, [0.0] * 6, BIAS))
    with pytest.raises(InputError, match="all six scales are 0"):
        read_ptm(path)


def test_a_constant_ptm_is_refused_by_the_command_line(tmp_path):
    codes, rgb = _codes()
    path = tmp_path / "flat.ptm"
    path.write_bytes(lrgb_bytes(np.zeros_like(codes), np.zeros_like(rgb), SCALE, BIAS))
    _one_line(_cli("run", str(path), "-o", str(tmp_path / "out")), str(path), "same polynomial")
    assert not (tmp_path / "out").exists()


def test_little_information_is_warned_of_naming_the_file(tmp_path):
    """Light-dependent coefficients equal everywhere (one normal everywhere) and a black colour
    block are read, with one warning line each that names the file."""
    codes, rgb = _codes()
    codes[..., :5] = 77
    path = tmp_path / "dull.ptm"
    path.write_bytes(lrgb_bytes(codes, np.zeros_like(rgb), SCALE, BIAS))
    ptm = read_ptm(path, max_side=4)
    assert len(ptm.warnings) == 2
    assert all(w.startswith(str(path)) and "\n" not in w for w in ptm.warnings)
    assert "a0–a4" in ptm.warnings[0] and "black" in ptm.warnings[1]
    codes, rgb = _codes()
    path.write_bytes(lrgb_bytes(codes, rgb, SCALE, BIAS))
    assert read_ptm(path).warnings == []


def test_a_varying_pixel_far_from_the_sample_counts(tmp_path):
    """The payload is first judged on a sample of its pixels; a constant sample is not enough to
    refuse a file whose pixels differ elsewhere."""
    codes = np.full((300, 200, 6), 9, np.uint8)
    codes[151, 101, 2] = 10  # between the sample's rows and columns
    path = tmp_path / "sparse.ptm"
    path.write_bytes(lrgb_bytes(codes, np.full((300, 200, 3), 90, np.uint8), SCALE, BIAS))
    assert read_ptm(path, max_side=50).warnings == []


def test_ptmfitter_files_end_with_their_payload(tmp_path):
    """HP's PTMfitter writes nothing after the payload (the shared fixture): that is what the
    reader accepts, and one byte more is refused."""
    fixture = Path(__file__).parents[2] / "shared" / "fixtures" / "ptmfitter_8x5" / "reference_8x5.ptm"
    if not fixture.exists():
        pytest.skip("the shared PTMfitter fixture is not here")
    assert (read_ptm(fixture).width, read_ptm(fixture).height) == (8, 5)
    longer = tmp_path / "longer.ptm"
    longer.write_bytes(fixture.read_bytes() + b"\n")
    with pytest.raises(InputError, match="1 bytes follow the 360"):
        read_ptm(longer)


@pytest.mark.parametrize("layout", ["lrgb", "lrgb_1.1", "rgb"])
def test_a_header_smaller_than_its_payload_is_refused(tmp_path, layout):
    """A 6×4 header before the payload of a 9×6 image (or any bytes after the payload) would be
    read as a scrambled 6×4 image."""
    big = sample_files(np.random.default_rng(5), h=6, w=9)[layout]
    small = sample_files(np.random.default_rng(5), h=4, w=6)[layout]
    head = small[: len(small) - 4 * 6 * (18 if layout == "rgb" else 9)]
    payload = big[len(big) - 6 * 9 * (18 if layout == "rgb" else 9):]
    path = tmp_path / "lying.ptm"
    for data in (head + payload, small + b"\n"):
        path.write_bytes(data)
        with pytest.raises(InputError, match="does not match the payload"):
            read_ptm(path)


def test_a_header_smaller_than_its_payload_is_refused_in_rti(tmp_path):
    head = b"#HSH1.2\n3\n3 2 3\n4 2 1\n" + np.ones(4, "<f4").tobytes() + np.zeros(4, "<f4").tobytes()
    path = tmp_path / "lying.rti"
    path.write_bytes(head + bytes(range(6 * 4 * 3 * 4 // 2)) * 2)  # the payload of 6×4 pixels
    with pytest.raises(InputError, match="does not match the payload"):
        read_rti_hsh(path)


# --- absurd sizes and special files -------------------------------------------------------------


def _at_once(call, fifos=()):
    """``call()``'s result, or its exception raised, within seconds. A reader blocked on one of
    ``fifos`` is released by opening its other end, so the test fails rather than hangs."""
    outcome = []

    def attempt():
        try:
            outcome.append(call())
        except Exception as exc:  # noqa: BLE001 - raised below
            outcome.append(exc)

    worker = threading.Thread(target=attempt, daemon=True)
    worker.start()
    worker.join(10)
    if worker.is_alive():
        for fifo in fifos:
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        pytest.fail("reading a special file blocked")
    if isinstance(outcome[0], Exception):
        raise outcome[0]
    return outcome[0]


def test_a_ptm_or_rti_larger_than_the_memory_left_is_refused_before_allocating(tmp_path, monkeypatch):
    """As a photograph's decoding does: the decoded arrays are weighed against the memory left
    (every read asks, here, and one byte is left)."""
    import ptmcore.ptmfile
    import ptmcore.resources

    monkeypatch.setattr(ptmcore.ptmfile, "ASK_MEMORY_BYTES", 0, raising=False)
    monkeypatch.setattr(ptmcore.resources, "available_memory_mb", lambda: 2.0**-20)
    for name, data in (("a.ptm", _PTM_SEEDS["lrgb"]), ("b.ptm", _PTM_SEEDS["jpeg_rgb"]), ("c.rti", _RTI_SEED)):
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(InputError, match=r"takes 0 MiB, more than the 0 MiB of memory available"):
            (read_rti_hsh if name.endswith(".rti") else read_ptm)(path)


def _refused_at_once(read, path, match: str) -> None:
    """``read(path)`` raises an InputError naming ``path`` and matching ``match``, at once."""
    with pytest.raises(InputError, match=match) as info:
        _at_once(lambda: read(path), [path] if path.is_fifo() else [])
    assert str(info.value).startswith(str(path))


def test_special_files_are_refused_without_blocking(tmp_path):
    for read, name in ((read_ptm, "f.ptm"), (read_rti_hsh, "f.rti")):
        fifo = tmp_path / name
        os.mkfifo(fifo)
        _refused_at_once(read, fifo, "named pipe")
        link = tmp_path / ("zero_" + name)
        link.symlink_to("/dev/zero")
        _refused_at_once(read, link, "a device")


def test_a_ptm_plane_is_decoded_as_jpeg_only(tmp_path, monkeypatch):
    """Without simplejpeg the planes go to Pillow, which must not take a PostScript plane for an
    image (its EPS plugin runs Ghostscript)."""
    monkeypatch.setitem(sys.modules, "simplejpeg", None)
    eps = (b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 6 4\n"
           b"/f (PWNED) (w) file def f (x) writestring f closefile\n0 0 6 4 rectfill showpage\n")
    n = 9
    text = f"PTM_1.2\nPTM_FORMAT_JPEG_LRGB\n6\n4\n" + "0.5 " * 6 + "\n" + "0 " * 6 + "\n75\n"
    text += ("0 " * n + "\n") * 3 + " ".join(map(str, range(n))) + "\n" + "-1 " * n + "\n"
    text += f"{len(eps)} " * n + "\n" + "0 " * n + "\n"
    path = tmp_path / "eps.ptm"
    path.write_bytes(text.encode() + eps * n)
    with pytest.raises(InputError, match="JPEG plane 0 is not a readable JPEG stream"):
        read_ptm(path)
    assert not (tmp_path / "PWNED").exists()


# --- property: the .ptm and .rti readers under arbitrary and damaged bytes -------------------


_PTM_SEEDS = sample_files(np.random.default_rng(11), h=5, w=7)


def _rti_seed() -> bytes:
    codes = smooth_codes(np.random.default_rng(12), 4, 5, 27)
    payload = np.moveaxis(codes.reshape(3, 9, 4, 5), (0, 1), (2, 3))[::-1].tobytes()
    scale, bias = np.full(9, 2.0, "<f4"), np.full(9, -1.0, "<f4")
    return b"#HSH1.2\n3\n5 4 3\n9 2 1\n" + scale.tobytes() + bias.tobytes() + payload


_RTI_SEED = _rti_seed()


def damaged(good: bytes, header: int = 200) -> st.SearchStrategy[bytes]:
    """A valid file truncated, with single bytes changed (mostly in its header), with bytes
    inserted (test_fuzz_readers.mutated), or with bytes appended."""
    return st.one_of(mutated(good, header), st.binary(min_size=1, max_size=64).map(lambda tail: good + tail))


@st.composite
def forged_ptm(draw) -> bytes:
    """A PTM header of any format claiming any size, up to 10^12 pixels a side, over a short
    payload: the reader must refuse it from the file's length, before allocating."""
    fmt = draw(st.sampled_from(["PTM_FORMAT_LRGB", "PTM_FORMAT_RGB", "PTM_FORMAT_JPEG_LRGB",
                                "PTM_FORMAT_JPEG_RGB"]))
    side = st.one_of(st.integers(1, 3000), st.integers(1, 10**12))
    width, height = draw(side), draw(side)
    text = f"PTM_1.2\n{fmt}\n{width}\n{height}\n" + "0.5 " * 6 + "\n" + "0 " * 6 + "\n"
    if "JPEG" in fmt:
        n = 9 if fmt.endswith("LRGB") else 18
        size = draw(st.integers(1, 10**6))
        text += "75\n" + ("0 " * n + "\n") * 3 + " ".join(map(str, range(n))) + "\n" + "-1 " * n + "\n"
        text += f"{size} " * n + "\n" + "0 " * n + "\n"
    return text.encode() + draw(st.binary(max_size=2000))


@st.composite
def forged_rti(draw) -> bytes:
    """An HSH header claiming any size over a short payload."""
    width, height = draw(st.integers(1, 10**12)), draw(st.integers(1, 10**12))
    terms = draw(st.sampled_from([4, 9]))
    return f"#HSH1.2\n3\n{width} {height} 3\n{terms} 2 1\n".encode() + draw(st.binary(max_size=2000))


def _ptm_payload_start(data: bytes) -> int:
    """Where a raw PTM's payload starts, its header read as the reader reads it (its numbers
    may be spread over lines)."""
    cur = HeaderCursor(data, Path("x.ptm"))
    cur.line("version"), cur.line("format"), cur.ints(2, "size"), cur.floats(12, "scales and biases")
    return cur.end_header()


def _rti_payload_start(data: bytes) -> int:
    """Where an RTI's scales start: after its comment lines and three lines of numbers."""
    lines = data.split(b"\n")
    comments = next(i for i, line in enumerate(lines) if not line.startswith(b"#"))
    return sum(len(line) + 1 for line in lines[: comments + 3])


def _check_ptm(ptm, data: bytes) -> None:
    """A PTM read from ``data`` is what its header says, and a raw layout's header accounts for
    every byte of the file."""
    h, w = ptm.height, ptm.width
    assert ptm.coefficients.shape[:2] == (h, w) and ptm.coefficients.shape[-1] == 6
    assert (ptm.rgb is None) == (ptm.coefficients.ndim == 4)
    assert ptm.coefficients.dtype == np.float32
    if "JPEG" not in ptm.format:
        assert len(data) == _ptm_payload_start(data) + h * w * (18 if ptm.format == "PTM_FORMAT_RGB" else 9)


def _check_rti(rti, data: bytes) -> None:
    k = rti.order ** 2
    assert rti.coefficients.shape == (rti.height, rti.width, 3, k)
    assert len(data) == _rti_payload_start(data) + 8 * k + rti.width * rti.height * 3 * k


@FUZZ
@given(data=st.one_of(st.binary(max_size=400), forged_ptm(), *(damaged(seed) for seed in _PTM_SEEDS.values())))
def test_ptm_reader_gives_a_ptm_or_one_input_error(folder, data):
    path = folder / "fuzz.ptm"
    path.write_bytes(data)
    ptm = _outcome(read_ptm, path)
    if ptm is not None:
        _check_ptm(ptm, data)


@FUZZ
@given(data=st.one_of(st.binary(max_size=400), forged_rti(), damaged(_RTI_SEED, header=40)))
def test_rti_reader_gives_an_rti_or_one_input_error(folder, data):
    path = folder / "fuzz.rti"
    path.write_bytes(data)
    rti = _outcome(read_rti_hsh, path)
    if rti is not None:
        _check_rti(rti, data)


def test_the_seeds_are_read(tmp_path):
    """The damaged files start from valid ones: each seed reads, without a warning."""
    for name, data in _PTM_SEEDS.items():
        path = tmp_path / f"{name}.ptm"
        path.write_bytes(data)
        ptm = read_ptm(path)
        assert ptm.warnings == []
        _check_ptm(ptm, data)
    path = tmp_path / "seed.rti"
    path.write_bytes(_RTI_SEED)
    _check_rti(read_rti_hsh(path), _RTI_SEED)


# --- laser scans --------------------------------------------------------------------------------


def _scan_points() -> np.ndarray:
    rng = np.random.default_rng(4)
    return np.column_stack([rng.uniform(0, 20, 50), rng.uniform(0, 30, 50), rng.uniform(0, 2, 50)])


def _ply(points: np.ndarray, count: int | None = None, binary: bool = False) -> bytes:
    head = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\n"
            f"element vertex {len(points) if count is None else count}\n"
            "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    if binary:
        return head + points.astype("<f4").tobytes()
    return head + "".join(f"{x} {y} {z}\n" for x, y, z in points).encode()


def _pcd(points: np.ndarray, count: int, data: str) -> bytes:
    head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            f"WIDTH {count}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\nDATA {data}\n").encode()
    if data == "ascii":
        return head + "".join(f"{x} {y} {z}\n" for x, y, z in points).encode()
    if data == "binary":
        return head + points.astype("<f4").tobytes()
    return head + struct.pack("<II", 10, 4_000_000_000) + bytes(10)


def _lying_scans() -> dict[str, bytes]:
    """Scans of 50 points whose headers claim a billion."""
    p = _scan_points()
    return {
        "text.ply": _ply(p, 10**9),
        "binary.ply": _ply(p, 10**9, binary=True),
        "binary.stl": bytes(80) + struct.pack("<I", 10**9) + bytes(50 * 3),
        "counts.off": b"OFF\n1000000000 1000000000 0\n" + b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
        "text.pcd": _pcd(p, 10**9, "ascii"),
        "binary.pcd": _pcd(p, 10**9, "binary"),
        "compressed.pcd": _pcd(p, 10**9, "binary_compressed"),
    }


def test_scan_headers_claiming_more_than_the_file_holds_are_refused(tmp_path):
    from reconstruct.compare import load_geometry

    for name, data in _lying_scans().items():
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(InputError, match="its header claims .* but the file holds") as info:
            load_geometry(path)
        assert info.value.path == str(path), name
    # Files at the edge of what their headers need are read: one-digit values without a last
    # line end, a text STL after white space (no binary triangle count).
    (tmp_path / "edge.ply").write_bytes(_ply(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 1]]))[:-1])
    (tmp_path / "edge.stl").write_bytes(b"  solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\n"
                                        b"vertex 1 0 0\nvertex 0 1 1\nendloop\nendfacet\nendsolid t\n" + b" " * 40)
    for name in ("edge.ply", "edge.stl"):
        assert len(load_geometry(tmp_path / name).points) == 3, name


def test_special_scan_files_are_refused_without_blocking(tmp_path):
    from reconstruct.compare import load_geometry

    for name in ("scan.ply", "scan.pcd", "scan.xyz"):
        fifo = tmp_path / name
        os.mkfifo(fifo)
        _refused_at_once(load_geometry, fifo, "named pipe")
    for name in ("zero.stl", "zero.csv"):
        (tmp_path / name).symlink_to("/dev/zero")
        _refused_at_once(load_geometry, tmp_path / name, "a device")


def test_a_scan_names_no_file_that_is_opened(tmp_path):
    """A mesh's materials and textures are not read for a comparison: a FIFO named as its
    material file would block the read, an EPS texture would run Ghostscript."""
    from reconstruct.compare import load_geometry

    os.mkfifo(tmp_path / "scan.mtl")
    (tmp_path / "scan.obj").write_text("mtllib scan.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 1\nf 1 2 3\n")
    geometry = _at_once(lambda: load_geometry(tmp_path / "scan.obj"), [tmp_path / "scan.mtl"])
    assert geometry.is_mesh and len(geometry.points) == 3


def test_a_text_scan_is_read_within_a_few_times_its_size(tmp_path):
    """x y z text is parsed into one array, not a Python object per number (ten times the
    file's size): what reading allocates stays within four times the file."""
    from reconstruct.compare import load_geometry

    points = np.random.default_rng(6).uniform(0, 50, (40000, 3))
    path = tmp_path / "scan.csv"
    path.write_text("x,y,z,intensity\r\n" + "".join(f"{x:.4f},{y:.4f},{z:.4f},7\r\n" for x, y, z in points))
    tracemalloc.start()
    try:
        geometry = load_geometry(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_allclose(geometry.points, points, atol=1e-4)
    assert peak <= 4 * path.stat().st_size, peak / path.stat().st_size


def _reconstruction_mesh(tmp_path) -> Path:
    import trimesh

    path = tmp_path / "rec.ply"
    trimesh.creation.box((20.0, 30.0, 4.0)).export(path)
    return path


def test_hostile_scans_are_one_line_and_exit_2_through_compare(tmp_path, capsys):
    from helpers import run_cli

    rec = _reconstruction_mesh(tmp_path)
    nan = _scan_points().astype(np.float32)
    nan[7, 2] = np.nan
    cases = {"empty.ply": (b"", "no points"), "blank.pcd": (b"\n\n", "no points"),
             "nan.ply": (_ply(nan, binary=True), "NaN"),
             "lying.ply": (_lying_scans()["binary.ply"], "claims")}
    for name, (data, problem) in cases.items():
        (tmp_path / name).write_bytes(data)
        code, _, err = run_cli(["compare", rec, tmp_path / name, "-o", tmp_path / "out"], capsys)
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert str(tmp_path / name) in err and problem in err, err
        assert not (tmp_path / "out").exists()
    os.mkfifo(tmp_path / "fifo.ply")
    _one_line(_cli("compare", str(rec), str(tmp_path / "fifo.ply"), "-o", str(tmp_path / "out")),
              str(tmp_path / "fifo.ply"), "named pipe")
    assert not (tmp_path / "out").exists()


def test_a_hostile_scan_stops_run_before_any_output(tmp_path):
    from data_synthetic import write_capture

    info = write_capture(tmp_path / "cap", "tablet", shape=(32, 40), n_lights=8, seed=2)
    (tmp_path / "zero.ply").symlink_to("/dev/zero")
    _one_line(_cli("run", str(info.folder), "-o", str(tmp_path / "out"), "--pixel-size", "0.1",
                   "--scan", str(tmp_path / "zero.ply")), str(tmp_path / "zero.ply"), "a device")
    assert not (tmp_path / "out").exists()


@st.composite
def forged_scan(draw) -> tuple[str, bytes]:
    """A PLY, STL, OFF or PCD whose header claims any count over a few points."""
    p = _scan_points()[: draw(st.integers(0, 50))]
    count = draw(st.one_of(st.integers(0, 60), st.integers(0, 10**12)))
    kind = draw(st.sampled_from(["ply", "ply_binary", "stl", "off", "pcd", "pcd_binary", "pcd_compressed"]))
    if kind.startswith("ply"):
        return "f.ply", _ply(p, count, binary=kind.endswith("binary"))
    if kind == "stl":
        return "f.stl", bytes(80) + struct.pack("<I", count % 2**32) + draw(st.binary(max_size=600))
    if kind == "off":
        return "f.off", f"OFF\n{len(p)} {count} 0\n".encode() + "".join(f"{x} {y} {z}\n" for x, y, z in p).encode()
    return "f.pcd", _pcd(p, count, {"pcd": "ascii", "pcd_binary": "binary", "pcd_compressed": "x"}[kind].replace(
        "x", "binary_compressed"))


@FUZZ
@given(case=forged_scan())
def test_scan_reader_gives_a_geometry_or_one_input_error(folder, case):
    import open3d  # noqa: F401 - imported before the reading's memory is traced
    import trimesh  # noqa: F401

    from reconstruct.compare import load_geometry

    name, data = case
    path = folder / name
    path.write_bytes(data)
    geometry = _outcome(load_geometry, path)
    if geometry is not None:
        assert geometry.points.shape[1] == 3 and np.all(np.isfinite(geometry.points))
        assert len(geometry.points) * 6 <= len(data)


# --- .npy arrays and transform matrices --------------------------------------------------------


def _npy_header(shape, descr="<f4") -> bytes:
    text = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode()
    text += b" " * (63 - (len(text) + 10) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text


def _write_run_folder(tmp_path, normals: bytes) -> Path:
    """An output folder as the viewer reads it: a height map and ``normals``."""
    import tifffile

    out = tmp_path / "out"
    out.mkdir()
    yy, xx = np.mgrid[0:12, 0:16]
    tifffile.imwrite(out / "height.tif", (0.1 * xx + 0.05 * yy).astype(np.float32))
    (out / "normals.npy").write_bytes(normals)
    return out


def test_the_viewer_checks_normals_npy_before_mapping_it(tmp_path):
    """A lying header (a billion rows in 200 bytes), pickled objects and a FIFO are refused with
    one line naming normals.npy."""
    from reconstruct.viewer.scene import load_scene

    out = _write_run_folder(tmp_path, _npy_header((10**9, 16, 3)) + bytes(200))
    with pytest.raises(InputError, match="truncated") as info:
        load_scene(out)
    assert info.value.path == str(out / "normals.npy")
    (out / "normals.npy").write_bytes(_npy_header((12, 16, 3), "|O") + bytes(64))
    with pytest.raises(InputError, match="Python objects"):
        load_scene(out)
    (out / "normals.npy").unlink()
    os.mkfifo(out / "normals.npy")
    assert _at_once(lambda: load_scene(out), [out / "normals.npy"]).normals is None


def test_report_maps_are_checked_before_mapping(tmp_path):
    """report.html's subsamples of normals.npy and height.tif: a lying .npy header, a TIFF
    whose header claims far more than the file holds, and special files are refused."""
    import tifffile

    from reconstruct.report.figures import map_array

    lying = tmp_path / "normals.npy"
    lying.write_bytes(_npy_header((10**6, 10**6, 3)) + bytes(100))
    with pytest.raises(InputError, match="truncated"):
        map_array(lying)
    # A compressed 64×64 TIFF whose width, height and rows per strip say 100,000.
    tiff = tmp_path / "height.tif"
    tifffile.imwrite(tiff, np.zeros((64, 64), np.float32), compression="zlib", metadata=None)
    data = bytearray(tiff.read_bytes())
    with tifffile.TiffFile(tiff) as tif:
        at = [tif.pages[0].tags[name].valueoffset for name in ("ImageWidth", "ImageLength", "RowsPerStrip")]
    for offset in at:
        struct.pack_into("<I", data, offset, 100_000)
    tiff.write_bytes(bytes(data))
    with pytest.raises(InputError, match="100000×100000 image of float32 .* cannot hold"):
        map_array(tiff)
    os.mkfifo(tmp_path / "fifo.tif")
    _refused_at_once(map_array, tmp_path / "fifo.tif", "named pipe")


def test_the_initial_transform_is_read_from_a_regular_text_file(tmp_path):
    from reconstruct.pipeline.compare_run import _read_initial

    os.mkfifo(tmp_path / "t.txt")
    _refused_at_once(_read_initial, tmp_path / "t.txt", "named pipe")
    (tmp_path / "zero.txt").symlink_to("/dev/zero")
    _refused_at_once(_read_initial, tmp_path / "zero.txt", "a device")
    utf16 = tmp_path / "utf16.txt"
    utf16.write_text("# from Windows\n" + "1 0 0 0\n0 1 0 0\n0 0 1 5\n0 0 0 1\n", encoding="utf-16")
    np.testing.assert_array_equal(_read_initial(utf16)[:, 3], [0, 0, 5, 1])
    for text, problem in (("# nothing\n", "holds no numbers"), ("1 2 3\n", "4×4")):
        (tmp_path / "bad.txt").write_text(text)
        with pytest.raises(InputError, match=problem):
            _read_initial(tmp_path / "bad.txt")


def test_the_viewer_reads_a_meshs_textures_only_as_png_or_jpeg(tmp_path, monkeypatch):
    """An OBJ's texture that is PostScript is not handed to Pillow (whose EPS plugin runs
    Ghostscript), one that is a FIFO does not block; the mesh is shown without its colours, and
    with them when the texture is a JPEG."""
    from PIL import EpsImagePlugin, Image

    from reconstruct.viewer.scene import load_scene

    decoded = []
    monkeypatch.setattr(EpsImagePlugin.EpsImageFile, "load", lambda self, *a, **k: decoded.append(self))
    (tmp_path / "m.obj").write_text("mtllib m.mtl\nusemtl a\nv 0 0 0\nv 1 0 0\nv 0 1 1\n"
                                    "vt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    (tmp_path / "m.mtl").write_text("newmtl a\nmap_Kd tex.jpg\n")
    texture = tmp_path / "tex.jpg"
    texture.write_bytes(b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 4 4\n0 0 4 4 rectfill showpage\n")
    assert len(load_scene(tmp_path / "m.obj").vertices) == 3 and decoded == []
    texture.unlink()
    os.mkfifo(texture)
    assert len(_at_once(lambda: load_scene(tmp_path / "m.obj"), [texture]).vertices) == 3
    texture.unlink()
    Image.fromarray(np.full((4, 4, 3), 200, np.uint8)).save(texture)
    assert np.all(load_scene(tmp_path / "m.obj").albedo == 200)


def test_a_dull_ptms_warnings_reach_the_run_and_relight(tmp_path):
    """PTMFile.warnings are shown where a person reads a .ptm: run's report and relight's stderr."""
    import json

    from reconstruct.pipeline.run import run_ptm

    codes, rgb = _codes()
    codes[..., :5] = 77
    path = tmp_path / "dull.ptm"
    path.write_bytes(lrgb_bytes(codes, rgb, SCALE, BIAS))
    run_ptm(path, tmp_path / "out")
    warnings = json.loads((tmp_path / "out" / "report.json").read_text())["warnings"]
    assert any("a0–a4" in w and str(path) in w for w in warnings)
    proc = _cli("relight", str(path), "-o", str(tmp_path / "r.png"), "--light", "0.3,0.2,0.93")
    assert proc.returncode == 0, proc.stderr
    assert "warning:" in proc.stderr and "a0–a4" in proc.stderr
