"""Reading back a relightable image in Relight's web format: a ``web/`` folder as a basis.

:func:`read_relightable` is the reverse of :func:`reconstruct.report.web.export_relightable`
(see that module's docstring for the format): ``info.json``, the planes — whole JPEGs
``plane_i.jpg`` or DeepZoom pyramids ``plane_i.dzi`` + ``plane_i_files/`` — and, when present,
this project's ``viewer.json`` become a :class:`ptmcore.published.PublishedBasis` that renders
as the page and OpenLIME render the folder. A folder written by Relight itself (no
``viewer.json``) is read too: its values are taken as display-encoded (sRGB), as OpenLIME shows
them, and an HSH's order is the largest whose terms fit its planes, as the page infers it.

Each channel's byte ``b`` is dequantised as OpenLIME's shader does it, ``(b/255 − bias) ·
scale``, and an MRGB basis row as its ``loadBasis`` does (row 0 ``byte/255``, row p ≥ 1
``(byte − 127) / range[p − 1]``).

Size. Everything is checked before it is decoded: ``info.json``'s numbers (finite, sizes within
:data:`ptmcore.decoders.MAX_PIXELS`, the plane count consistent with the type), each JPEG's
header against the size ``info.json`` declares for it (a whole plane, or a tile at its place in
the pyramid), and the memory the planes will take. With ``max_side``, only what a preview needs
is decoded: the smallest pyramid level whose longer side is at least ``max_side``, or a whole
plane decoded at libjpeg's DCT scale (1/8 to 1) and then area-averaged by a whole factor, so a
preview of a 50-megapixel RTI never holds it at full size. The JPEGs are decoded by simplejpeg
(libjpeg-turbo), never by Pillow, so Pillow's decompression-bomb limit is neither needed nor
touched.

Types. Each Relight ``type`` has a reader in :data:`READERS`, a function of the checked
:class:`WebFolder` returning the basis; another type is one function and one entry there.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree import ElementTree

import numpy as np

from ptmcore.decoders import JPEG_PIXELS_PER_BYTE, MAX_PIXELS
from ptmcore.errors import InputError, open_input_file, read_input_file, read_input_text
from ptmcore.published import PublishedBasis
from reconstruct.report.web import NEURAL_PLANES, pyramid_levels

__all__ = ["READERS", "WebFolder", "find_web_folder", "published_folder", "read_relightable", "relightable_shape"]

#: The largest ``info.json`` and ``viewer.json`` read, bytes: an RBF basis of 200 lights and 18
#: planes is 11,400 numbers, well under a megabyte; a larger file is not one of these.
MAX_JSON_BYTES = 16 << 20
#: The largest ``.dzi`` read, bytes (ours are about 200).
MAX_DZI_BYTES = 64 << 10
#: The most coefficient channels read (Relight writes up to 27; 3 · 32 leaves room).
MAX_CHANNELS = 96
#: The largest side of a plane, pixels: within :data:`MAX_PIXELS` and far beyond any capture.
MAX_SIDE = 1 << 20
#: A JPEG plane or tile is at most this many bytes per pixel (quality 100, 4:4:4, noise: ~2.5).
_MAX_JPEG_BYTES_PER_PIXEL = 8
#: The first bytes of a JPEG read for its frame header before the planes are decoded.
_HEADER_BYTES = 64 << 10
#: Decodes larger than this ask how much memory is left (as ptmcore.decoders does).
_ASK_MEMORY_BYTES = 256 << 20
# Relight's type names → PublishedBasis.type.
_TYPE_NAMES = {"ptm": "ptm", "hsh": "hsh", "rbf": "rbf", "bilinear": "bln"}


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number JSON allows")


def _load_json(path: Path, what: str) -> dict:
    """A JSON object from a file, or an :class:`InputError` naming it (NaN and Infinity, which
    Python's json accepts, are refused: no viewer reads them)."""
    text = read_input_text(path, what, MAX_JSON_BYTES)
    try:
        data = json.loads(text, parse_constant=_reject_constant)
    except ValueError as exc:
        raise InputError(f"malformed {what} ({exc})", path) from None
    if not isinstance(data, dict):
        raise InputError(f"malformed {what}: not a JSON object", path)
    return data


def _whole(value: object, what: str, path: Path, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise InputError(f"{what} must be a whole number from {low} to {high:,}, not {value!r}", path)
    return value


def _numbers(value: object, what: str, path: Path, count: int | None = None) -> np.ndarray:
    """A JSON list of finite numbers (``count`` of them when given) as float64."""
    if not isinstance(value, list) or (count is not None and len(value) != count):
        want = f"a list of {count} numbers" if count is not None else "a list of numbers"
        got = f"{len(value)} entries" if isinstance(value, list) else type(value).__name__
        raise InputError(f"{what} must be {want}, not {got}", path)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise InputError(f"{what} holds something that is not a number", path)
    out = np.array(value, dtype=np.float64)
    if not np.isfinite(out).all():  # 1e999 parses as infinity
        raise InputError(f"{what} holds a number that is not finite", path)
    return out


def _check_memory(nbytes: int, path: Path) -> None:
    if nbytes > _ASK_MEMORY_BYTES:
        from ptmcore.resources import available_memory_mb

        free = available_memory_mb()
        if nbytes > free * 2**20:
            raise InputError(f"reading its planes takes {nbytes / 2**20:,.0f} MiB, more than the "
                             f"{free:,.0f} MiB of memory available (give a smaller max_side)", path)


def _size_mismatch(path: Path, found: tuple[int, int], declared: tuple[int, int]) -> InputError:
    return InputError(f"the JPEG is {found[0]} × {found[1]} pixels where info.json declares "
                      f"{declared[0]} × {declared[1]}", path)


def _check_header(path: Path, size: tuple[int, int]) -> None:
    """Check a JPEG's declared size from its first bytes alone (its frame header comes before
    the image data), so a plane of the wrong size is refused before any plane is decoded; a
    header past them is checked when the file is read whole (:func:`_jpeg`)."""
    import simplejpeg

    with open_input_file(path, "JPEG plane") as f:
        head = f.read(_HEADER_BYTES)
    try:
        h, w = simplejpeg.decode_jpeg_header(head)[:2]
    except ValueError:
        return
    if (w, h) != tuple(size):
        raise _size_mismatch(path, (w, h), size)


def _jpeg(path: Path, size: tuple[int, int], scale_to: int | None = None) -> np.ndarray:
    """A plane or tile JPEG ``(h, w, 3)`` uint8, its header checked to declare ``size`` = (width,
    height) before it is decoded; with ``scale_to``, decoded at the smallest DCT scale whose
    longer side is at least that long."""
    import simplejpeg

    width, height = size
    data = read_input_file(path, "JPEG plane", _MAX_JPEG_BYTES_PER_PIXEL * width * height + (1 << 20))
    try:
        h, w, colorspace, _ = simplejpeg.decode_jpeg_header(data)
    except ValueError as exc:
        raise InputError(f"not a JPEG plane ({exc})", path) from None
    if (w, h) != (width, height):
        raise _size_mismatch(path, (w, h), size)
    if colorspace not in ("RGB", "YCbCr", "Gray"):
        raise InputError(f"the JPEG is {colorspace}, not RGB", path)
    if w * h > JPEG_PIXELS_PER_BYTE * len(data):
        raise InputError(f"the JPEG claims {w} × {h} pixels, more than its {len(data):,} bytes can hold "
                         "(a truncated or corrupt file)", path)
    scaled = {}
    if scale_to is not None and scale_to < max(w, h):
        scaled = {"min_width": scale_to} if w >= h else {"min_height": scale_to}
    try:
        image = simplejpeg.decode_jpeg(data, colorspace="RGB", **scaled)
    except ValueError as exc:
        problem = "the file is truncated" if "Premature end" in str(exc) else str(exc)
        raise InputError(f"cannot decode the JPEG plane ({problem})", path) from None
    return image


def _area_reduce(image: np.ndarray, factor: int) -> np.ndarray:
    """``image`` averaged over ``factor`` × ``factor`` blocks (the last ones partial), float32."""
    import cv2

    image = np.asarray(image, dtype=np.float32)
    if factor <= 1:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, (-(-w // factor), -(-h // factor)), interpolation=cv2.INTER_AREA)


@dataclass(frozen=True)
class _Pyramid:
    """A plane's DeepZoom pyramid, as its ``.dzi`` declares it."""

    tile: int
    overlap: int
    suffix: str


def _read_dzi(path: Path, width: int, height: int) -> _Pyramid:
    text = read_input_text(path, "DeepZoom descriptor", MAX_DZI_BYTES)
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as exc:
        raise InputError(f"malformed DeepZoom descriptor ({exc})", path) from None
    size = next((child for child in root if child.tag.rsplit("}", 1)[-1] == "Size"), None)
    if root.tag.rsplit("}", 1)[-1] != "Image" or size is None:
        raise InputError("not a DeepZoom descriptor (no Image with a Size)", path)

    def whole(element: ElementTree.Element, key: str, low: int, high: int) -> int:
        value = element.get(key, "")
        if not (value.isascii() and value.isdigit()) or not low <= int(value) <= high:
            raise InputError(f"{key} must be a whole number from {low} to {high:,}, not {value!r}", path)
        return int(value)

    tile = whole(root, "TileSize", 1, 1 << 14)
    overlap = whole(root, "Overlap", 0, tile - 1)
    suffix = (root.get("Format") or "").lower()
    if suffix not in ("jpg", "jpeg"):
        raise InputError(f"tiles in the format {suffix!r} are not read (only jpg)", path)
    if (whole(size, "Width", 1, MAX_SIDE), whole(size, "Height", 1, MAX_SIDE)) != (width, height):
        raise InputError(f"the pyramid is {size.get('Width')} × {size.get('Height')} pixels where info.json "
                         f"declares {width} × {height}", path)
    return _Pyramid(tile, overlap, suffix)


def _tile_spans(length: int, tile: int, overlap: int) -> list[tuple[int, int, int]]:
    """For each tile along a side of ``length``: the first pixel it holds, its length with the
    overlap, and where its own pixels start in it."""
    spans = []
    for c in range(-(-length // tile)):
        start = max(0, tile * c - overlap)
        spans.append((start, min(length, tile * (c + 1) + overlap) - start, tile * c - start))
    return spans


@dataclass
class WebFolder:
    """A ``web/`` folder whose ``info.json`` (and ``viewer.json``) are read and checked, and which
    decodes its planes on demand, at the size :attr:`shape` (``max_side`` chosen).

    Attributes
    ----------
    folder : Path
        The folder of ``info.json`` and the planes.
    info : dict
        ``info.json``.
    extras : dict
        ``viewer.json``, or ``{}`` for a folder written by Relight.
    width, height : int
        The full image size ``info.json`` declares.
    nplanes : int
        Channels in the planes (``ceil(nplanes / 3)`` JPEGs).
    scale, bias : ndarray, shape (nplanes,)
        Each channel's value is ``(byte/255 − bias) · scale + offset``.
    max_side : int or None
        The longer side wanted (None: full size).
    offset : ndarray, shape (nplanes,), optional
        Added to each channel (NeuralRTI's ``min``; zero for Relight's other types).
    first_plane : int
        The number in the first plane's name (NeuralRTI's planes are named from 1).
    """

    folder: Path
    info: dict
    extras: dict
    width: int
    height: int
    nplanes: int
    scale: np.ndarray
    bias: np.ndarray
    max_side: int | None = None
    offset: np.ndarray | None = None
    first_plane: int = 0
    _laid_out: bool = field(default=False, repr=False)
    _pyramids: list[_Pyramid] = field(default_factory=list, repr=False)
    _level: int | None = field(default=None, repr=False)
    _eighths: int = field(default=8, repr=False)
    _factor: int = field(default=1, repr=False)

    @property
    def info_path(self) -> Path:
        return self.folder / "info.json"

    @property
    def njpegs(self) -> int:
        return -(-self.nplanes // 3)

    def fail(self, problem: str, path: Path | None = None) -> InputError:
        """The error of a problem in ``info.json`` (or in ``path``)."""
        return InputError(problem, path or self.info_path)

    def _plane_path(self, j: int) -> Path:
        return self.folder / f"plane_{j + self.first_plane}.{self.info['format']}"

    def _dzi_path(self, j: int) -> Path:
        return self.folder / f"plane_{j + self.first_plane}.dzi"

    def layout(self) -> None:
        """Find each plane (a whole JPEG or a pyramid, as ``viewer.json``'s ``layout`` says, else
        whichever is there), check that every file the read needs exists (and a whole JPEG's
        header declares the size of ``info.json``) before anything is decoded, and choose the
        level or the DCT scale of ``max_side``. Done once, when the planes' size is first asked
        for: after a type's reader has checked what is its own."""
        if self._laid_out:
            return
        self._laid_out = True
        tiled = self.extras.get("layout") == "deepzoom" or (
            "layout" not in self.extras and not self._plane_path(0).is_file()
            and self._dzi_path(0).is_file())
        for j in range(self.njpegs):
            path = self._dzi_path(j) if tiled else self._plane_path(j)
            if not path.is_file():
                raise InputError(f"missing: the folder's info.json declares {self.nplanes} channels "
                                 f"in {self.njpegs} planes", path)
            if tiled:
                self._pyramids.append(_read_dzi(path, self.width, self.height))
            else:
                _check_header(path, (self.width, self.height))
        longer = max(self.width, self.height)
        if tiled:
            self._choose_level()
        elif self.max_side is not None and longer > self.max_side:
            # libjpeg decodes at n/8 of the size (each side rounded up): the smallest n whose
            # longer side is at least max_side, below 8·max_side; a whole factor then brings
            # it below 2·max_side.
            self._eighths = next(n for n in range(1, 9) if -(-longer * n // 8) >= self.max_side)
            self._factor = max(1, -(-longer * self._eighths // 8) // self.max_side)

    def _choose_level(self) -> None:
        pyramid = self._pyramids[0]
        if any(p.tile != pyramid.tile for p in self._pyramids):
            raise self.fail("the planes' pyramids have different tile sizes", self._dzi_path(1))
        levels = pyramid_levels(self.width, self.height, pyramid.tile)
        top = len(levels) - 1
        wanted = self.max_side or max(self.width, self.height)
        self._level = next((i for i, size in enumerate(levels) if max(size) >= wanted), top)
        lw, lh = levels[self._level]
        for j, p in enumerate(self._pyramids):
            for column in range(-(-lw // p.tile)):
                for row in range(-(-lh // p.tile)):
                    tile = self._tile_path(j, column, row)
                    if not tile.is_file():
                        raise InputError(f"missing tile of level {self._level} ({lw} × {lh} pixels)", tile)

    def _tile_path(self, j: int, column: int, row: int) -> Path:
        return (self.folder / f"plane_{j + self.first_plane}_files" / str(self._level)
                / f"{column}_{row}.{self._pyramids[j].suffix}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(h, w)`` of what the planes decode to."""
        self.layout()
        if self._level is not None:
            lw, lh = pyramid_levels(self.width, self.height, self._pyramids[0].tile)[self._level]
            return lh, lw
        n = self._eighths
        h, w = -(-self.height * n // 8), -(-self.width * n // 8)
        return -(-h // self._factor), -(-w // self._factor)

    def jpeg(self, j: int) -> np.ndarray:
        """JPEG ``j``'s bytes at :attr:`shape`: ``(h, w, 3)``, uint8 at full size or a pyramid
        level, float32 when a whole plane was reduced (the average of its bytes)."""
        self.layout()
        if self._level is not None:
            return self._assemble(j)
        if self._eighths == 8:
            return _jpeg(self._plane_path(j), (self.width, self.height))
        image = _jpeg(self._plane_path(j), (self.width, self.height), self.max_side)
        out = _area_reduce(image, self._factor)
        if out.shape[:2] != self.shape:  # a libjpeg that scales otherwise: the sizes must still agree
            raise InputError(f"decoded to {out.shape[1]} × {out.shape[0]} pixels, not {self.shape[1]} × "
                             f"{self.shape[0]}", self._plane_path(j))
        return out

    def _assemble(self, j: int) -> np.ndarray:
        """A pyramid level stitched from its tiles, each without its overlap."""
        p = self._pyramids[j]
        lh, lw = self.shape
        out = np.empty((lh, lw, 3), np.uint8)
        for row, (y0, th, oy) in enumerate(_tile_spans(lh, p.tile, p.overlap)):
            for column, (x0, tw, ox) in enumerate(_tile_spans(lw, p.tile, p.overlap)):
                tile = _jpeg(self._tile_path(j, column, row), (tw, th))
                y, x = y0 + oy, x0 + ox
                out[y:y + min(p.tile, lh - y), x:x + min(p.tile, lw - x)] = \
                    tile[oy:oy + min(p.tile, lh - y), ox:ox + min(p.tile, lw - x)]
        return out

    def values(self, first: int, count: int) -> np.ndarray:
        """Channels ``first … first + count − 1`` dequantised, ``(h, w, count)`` float32,
        decoding each JPEG they lie in once (one at a time)."""
        h, w = self.shape
        out = np.empty((h, w, count), np.float32)
        for j in range(first // 3, -(-(first + count) // 3)):
            image = self.jpeg(j)
            for c in range(3):
                k = 3 * j + c
                if first <= k < first + count:
                    s, b = np.float32(self.scale[k]), np.float32(self.bias[k])
                    np.multiply(image[..., c], np.float32(1.0 / 255.0), out=out[..., k - first], casting="unsafe")
                    out[..., k - first] -= b
                    out[..., k - first] *= s
                    if self.offset is not None:
                        out[..., k - first] += np.float32(self.offset[k])
        return out

    def colour(self) -> np.ndarray:
        """The LRGB colour, plane 0, as uint8 (its scale and bias applied: 1 and 0 as written)."""
        values = self.values(0, 3)
        return np.rint(np.clip(values * np.float32(255.0), 0.0, 255.0)).astype(np.uint8)


def _open(source: Path, max_side: int | None) -> WebFolder:
    """``info.json`` and ``viewer.json`` read and checked, whatever the type."""
    if not source.exists():
        raise InputError("not found", source)
    if source.is_dir():
        folder = source if (source / "info.json").exists() or not (source / "web" / "info.json").is_file() \
            else source / "web"
        info_path = folder / "info.json"
    else:
        folder, info_path = source.parent, source
    if not info_path.exists():
        raise InputError("no info.json here: not a web/ folder of reconstruct run or of Relight", source)
    info = _load_json(info_path, "info.json")
    extras = _load_json(folder / "viewer.json", "viewer.json") if (folder / "viewer.json").exists() else {}
    neural = info.get("type") == "neural"
    for key in ("width", "height", "type", "colorspace", *(("planes", "min", "max") if neural else ("nplanes", "materials"))):
        if key not in info:
            raise InputError(f"no {key!r} in it", info_path)
    width = _whole(info["width"], "width", info_path, 1, MAX_SIDE)
    height = _whole(info["height"], "height", info_path, 1, MAX_SIDE)
    if width * height > MAX_PIXELS:
        raise InputError(f"width × height = {width} × {height}, more than the {MAX_PIXELS:,} pixels this "
                         "program reads", info_path)
    if str(info.get("format", "jpg")).lower() not in ("jpg", "jpeg"):
        raise InputError(f"planes in the format {info.get('format')!r} are not read (only jpg)", info_path)
    info.setdefault("format", "jpg")
    if not isinstance(info["type"], str) or info["type"] not in READERS:
        raise InputError(f"unknown type {info['type']!r} (reads {', '.join(READERS)})", info_path)
    if not isinstance(info["colorspace"], str):
        raise InputError(f"colorspace must be a name, not {info['colorspace']!r}", info_path)
    offset = None
    if neural:  # code = byte/255 · (max − min) + min, planes named from 1 (OpenLIME's LayerNeuralRTI)
        nplanes = _whole(info["planes"], "planes", info_path, NEURAL_PLANES, NEURAL_PLANES)
        offset = _numbers(_flat(info["min"]), "min", info_path, nplanes)
        scale = _numbers(_flat(info["max"]), "max", info_path, nplanes) - offset
        bias = np.zeros(nplanes)
    else:
        nplanes = _whole(info["nplanes"], "nplanes", info_path, 1, MAX_CHANNELS)
        materials = info["materials"]
        if not isinstance(materials, list) or not materials or not isinstance(materials[0], dict):
            raise InputError("materials must be a list holding one object of scale and bias", info_path)
        scale = _numbers(materials[0].get("scale"), "materials[0].scale", info_path, nplanes)
        bias = _numbers(materials[0].get("bias"), "materials[0].bias", info_path, nplanes)
    encoding = extras.get("encoding", "srgb")
    if encoding not in ("srgb", "linear"):
        raise InputError(f"encoding must be 'srgb' or 'linear', not {encoding!r}", folder / "viewer.json")
    if max_side is not None and (isinstance(max_side, bool) or not isinstance(max_side, (int, np.integer))
                                 or max_side < 1):
        raise ValueError(f"max_side must be a positive whole number of pixels, not {max_side!r}")
    return WebFolder(folder, info, extras, width, height, nplanes, scale, bias,
                     None if max_side is None else int(max_side), offset, 1 if neural else 0)


def _flat(value: object) -> object:
    """OpenLIME's ``min``/``max``: flat, or one list per plane (its ``flat(1)``)."""
    if isinstance(value, list) and value and all(isinstance(v, list) for v in value):
        return [x for v in value for x in v]
    return value


def _terms(web: WebFolder, low: int, high: int) -> int | None:
    """``viewer.json``'s ``terms`` (the planes before padding), checked to lie in [low, high]."""
    if "terms" not in web.extras:
        return None
    return _whole(web.extras["terms"], "terms", web.folder / "viewer.json", low, high)


def _name(web: WebFolder, default: str) -> str:
    name = web.extras.get("basis")
    return name if isinstance(name, str) and 0 < len(name) <= 64 and name.isprintable() else default


def _lrgb_coefficients(web: WebFolder, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The colour and the K luminance coefficients of an LRGB folder, the memory checked first."""
    h, w = web.shape
    _check_memory(h * w * (4 * k + 3 + 12), web.info_path)
    return web.colour(), web.values(3, k)


def _read_lrgb(web: WebFolder) -> PublishedBasis:
    """PTM and HSH: ``plane_0`` the colour, then K luminance coefficients (Relight's ``lrgb``)."""
    kind = _TYPE_NAMES[web.info["type"]]
    if web.info["colorspace"] != "lrgb":
        raise web.fail(f"a {kind} in the colour space {web.info['colorspace']!r} is not read (only lrgb)")
    channels = web.nplanes - 3
    order = None
    if kind == "ptm":
        if web.nplanes != 9:
            raise web.fail(f"an lrgb PTM has nplanes 9 (colour and 6 coefficients), not {web.nplanes}")
        k = 6
        _terms(web, 6, 6)
    else:
        viewer = web.folder / "viewer.json"
        # Without viewer.json (Relight's folders), the largest order whose terms fit, as the page.
        order = web.extras.get("order", math.isqrt(max(channels, 0)))
        order = _whole(order, "order", viewer if "order" in web.extras else web.info_path, 2, 4)
        k = order * order
        if not k <= channels <= 3 * -(-k // 3):
            raise web.fail(f"an HSH of order {order} has {k} terms; nplanes {web.nplanes} holds "
                           f"{channels} coefficient channels")
        _terms(web, k, k)
    colour, planes = _lrgb_coefficients(web, k)
    name = _name(web, "ptm" if kind == "ptm" else f"hsh{order}")
    return PublishedBasis(kind, "lrgb", planes, web.extras.get("encoding", "srgb"), colour=colour, order=order,
                          name=name)


def _read_mrgb(web: WebFolder) -> PublishedBasis:
    """RBF and bilinear: K coefficient planes and an RGB basis shared by every pixel
    (Relight's ``mrgb``)."""
    kind = _TYPE_NAMES[web.info["type"]]
    info, path = web.info, web.info_path
    if info["colorspace"] != "mrgb":
        raise web.fail(f"a {info['type']} basis in the colour space {info['colorspace']!r} is not read (only mrgb)")
    lights = sigma = resolution = None
    if kind == "rbf":
        flat = _numbers(info.get("lights"), "lights", path)
        if len(flat) == 0 or len(flat) % 3:
            raise web.fail(f"lights must hold x, y, z of each light, not {len(flat)} numbers")
        lights = flat.reshape(-1, 3)
        if (np.linalg.norm(lights, axis=1) == 0).any():
            raise web.fail("a light direction is the zero vector")
        sigma = info.get("sigma")
        if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not (math.isfinite(sigma) and sigma > 0):
            raise web.fail(f"sigma must be a positive number, not {sigma!r}")
        sigma = float(sigma)
        d = len(lights)
    else:
        resolution = _whole(info.get("resolution"), "resolution", path, 2, 1 << 10)
        d = resolution * resolution
    rows = web.nplanes + 1
    raw = _numbers(info.get("basis"), "basis", path, rows * d * 3)
    if (raw != np.rint(raw)).any() or raw.min() < 0 or raw.max() > 255:
        raise web.fail("basis must hold bytes, whole numbers from 0 to 255")
    ranges = _numbers(info["materials"][0].get("range"), "materials[0].range", path, web.nplanes)
    if not (ranges > 0).all():
        raise web.fail("materials[0].range must be positive")
    k = _terms(web, 1, web.nplanes)
    if k is None:  # Relight's folders: the channels after the last of nonzero scale are exactly 0
        k = max(1, int(np.flatnonzero(web.scale != 0)[-1]) + 1 if (web.scale != 0).any() else 1)
    raw = raw.reshape(rows, d, 3)[: k + 1]
    basis = np.concatenate([raw[:1] / 255.0, (raw[1:] - 127.0) / ranges[:k, None, None]]).astype(np.float32)
    h, w = web.shape
    _check_memory(h * w * 4 * (k + 3), path)
    planes = web.values(0, k)
    return PublishedBasis(kind, "mrgb", planes, web.extras.get("encoding", "srgb"), lights=lights, sigma=sigma,
                          resolution=resolution, basis=basis, name=_name(web, "rbf" if kind == "rbf" else "bilinear"))


def _read_neural(web: WebFolder) -> PublishedBasis:
    """NeuralRTI: the 9-number codes in three planes and the decoder in ``info.json``, padded
    as OpenLIME's ShaderNeural reads it (:mod:`reconstruct.report.web`)."""
    info, path = web.info, web.info_path
    if not (isinstance(info["colorspace"], str) and sorted(info["colorspace"]) == ["b", "g", "r"]):
        raise web.fail(f"colorspace must order r, g and b, not {info['colorspace']!r}")
    k = web.nplanes
    hidden = _whole(info.get("samples"), "samples", path, 1, 1 << 10)
    n4, c4 = 4 * -(-hidden // 4), 4 * -(-(k + 2) // 4)
    weights, biases = info.get("weights"), info.get("biases")
    if not (isinstance(weights, list) and isinstance(biases, list) and len(weights) == len(biases) == 3):
        raise web.fail("weights and biases must be lists of three layers")
    network = []
    for i, (rows, cols) in enumerate([(n4, c4), (n4, n4), (3, n4)]):
        w = _numbers(weights[i], f"weights[{i}]", path, rows * cols).reshape(rows, cols)
        b = _numbers(biases[i], f"biases[{i}]", path, rows)
        inputs, outputs = (k + 2 if i == 0 else hidden), (3 if i == 2 else hidden)
        network.append((np.ascontiguousarray(w[:outputs, :inputs].T, np.float32), b[:outputs].astype(np.float32)))
    # OpenLIME swizzles the planes' texels and the network's output alike: a "bgr" folder (as
    # NeuralRTI's own) holds each plane's numbers and the output in that order.
    order = ["rgb".index(c) for c in info["colorspace"]]
    h, w = web.shape
    _check_memory(h * w * 4 * (k + 3), path)
    codes = web.values(0, k).reshape(h, w, k // 3, 3)[..., order].reshape(h, w, k)
    last_w, last_b = network[2]  # shown channel i is output order[i]
    network[2] = (np.ascontiguousarray(last_w[:, order]), np.ascontiguousarray(last_b[order]))
    return PublishedBasis("neural", "rgb", codes, web.extras.get("encoding", "srgb"), network=network,
                          name=_name(web, "neural"))


#: Relight's ``type`` → the function reading a folder of it (after :class:`WebFolder` has checked
#: what every type shares). A new type is one function of a ``WebFolder`` and one entry here.
READERS: dict[str, Callable[[WebFolder], PublishedBasis]] = {
    "ptm": _read_lrgb,
    "hsh": _read_lrgb,
    "rbf": _read_mrgb,
    "bilinear": _read_mrgb,
    "neural": _read_neural,
}


def read_relightable(source: str | os.PathLike, *, max_side: int | None = None) -> PublishedBasis:
    """Read a relightable image in Relight's web format (what :func:`export_relightable` writes).

    Parameters
    ----------
    source : str or os.PathLike
        A ``web/`` folder, its ``info.json``, or an output folder of ``reconstruct run`` (its
        ``web/``).
    max_side : int, optional
        Read only what a picture of this many pixels on its longer side needs: the smallest
        pyramid level whose longer side is at least ``max_side``, or whole planes decoded at a
        DCT scale and area-averaged, to a longer side from ``max_side`` to ``2 · max_side``.
        Default: the full size.

    Returns
    -------
    PublishedBasis
        Planes ``(h, w, K)`` float32 in 0–1 units of its ``encoding`` (``viewer.json``'s; sRGB
        for a folder Relight wrote), the colour (LRGB) or the basis rows, lights, sigma,
        resolution (MRGB), the HSH order and the name (``viewer.json``'s ``basis``, else the
        type's: ``ptm``, ``hsh3``, ``rbf``, ``bilinear``).

    Raises
    ------
    InputError
        Naming the file and the problem: a missing ``info.json``, plane or tile; malformed JSON
        or DeepZoom descriptor; an unknown type or colour space; a size that is absurd or does
        not match the JPEGs; a plane count inconsistent with the type; a number that is not
        finite; planes that would not fit in the memory available.
    ValueError
        If ``max_side`` is not a positive whole number.
    """
    web = _open(Path(source), max_side)
    return READERS[web.info["type"]](web)


def relightable_shape(source: str | os.PathLike) -> tuple[int, int]:
    """The full ``(height, width)`` an ``info.json`` (or its folder) declares, checked as
    :func:`read_relightable` checks it; nothing is decoded."""
    source = Path(source)
    path = source / "info.json" if source.is_dir() else source
    info = _load_json(path, "info.json")
    return (_whole(info.get("height"), "height", path, 1, MAX_SIDE), _whole(info.get("width"), "width", path, 1, MAX_SIDE))


def find_web_folder(source: str | os.PathLike) -> Path | None:
    """The folder of a relightable image given as a ``web/`` folder, its ``info.json``, or an
    output folder holding ``web/info.json``; None when there is none."""
    source = Path(source)
    if source.is_file():
        return source.parent if source.suffix.lower() == ".json" else None
    for folder in (source, source / "web"):
        if (folder / "info.json").is_file():
            return folder
    return None


def published_folder(output: str | os.PathLike) -> Path | None:
    """An output folder's ``web/`` when it holds the basis chosen for the capture (its
    ``viewer.json`` names the ``basis``, as :func:`export_relightable` writes it) in a type
    :data:`READERS` reads; else None.

    Folders of older runs, and of runs from a ``.ptm`` file, hold the PTM itself in ``web/``
    (:func:`reconstruct.report.web.export_openlime`, no ``basis``): its own ``coefficients.ptm``
    (or the source ``.ptm``) is then read instead, exactly; so is it beside a type this module
    does not read yet (the viewers then show the PTM rather than nothing).

    Raises
    ------
    InputError
        If ``web/viewer.json`` or ``web/info.json`` is there but malformed.
    """
    web = Path(output) / "web"
    if not (web / "info.json").is_file() or not (web / "viewer.json").is_file():
        return None
    if "basis" not in _load_json(web / "viewer.json", "viewer.json"):
        return None
    kind = _load_json(web / "info.json", "info.json").get("type")
    return web if isinstance(kind, str) and kind in READERS else None
