"""Small in-memory stacks for unit tests (no files)."""

import numpy as np

from ptmcore.images import ImageStack


def stack_from_luminance(values: np.ndarray, saturated: np.ndarray | None = None) -> ImageStack:
    """An ImageStack holding linear luminance ``values`` (N, H, W) in [0, 1]."""
    lum = np.round(np.clip(values, 0, 1) * 65534).astype(np.uint16)
    if saturated is not None:
        lum[saturated] = 65535
    n, h, w = values.shape
    return ImageStack(lum, np.ones((h, w, 3), np.float32), [], 16, False, (lum == 65535).sum(axis=(1, 2)))


def dome(n: int = 40, seed: int = 0, min_elev: float = 15.0, max_elev: float = 75.0) -> np.ndarray:
    """Random unit light directions spread over a dome."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(min_elev, max_elev, n))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)


def sphere_normals(h: int, w: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a sphere seen from +z (y up) and its mask."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (cols - (w - 1) / 2) / radius
    y = -(rows - (h - 1) / 2) / radius
    r2 = x * x + y * y
    mask = r2 < 0.95**2
    z = np.sqrt(np.clip(1 - r2, 0, 1))
    n = np.stack([x, y, z], -1)
    n[~mask] = (0, 0, 1)
    return n.astype(np.float32), mask


#: Header tokens that parsers must reject or survive.
GARBAGE_TOKENS = [b"-1", b"0", b"99999999", b"1e999", b"nan", b"x", b"", b"3.5", b"2147483648",
                  b"-2147483649", b"18446744073709551617", b"\xff\xfe", b"1 2", b"+7", b"1_0"]


def mutate(good: bytes, rng: np.random.Generator, *, header_bytes: int, header_lines: int) -> bytes:
    """One random corruption of a valid file, for fuzzing readers.

    Truncation, bytes flipped (half the time within the first ``header_bytes``), a token of one
    of the first ``header_lines`` lines replaced by garbage, a line deleted or duplicated, or
    random bytes inserted.
    """
    data = bytearray(good)
    kind = rng.integers(0, 5)
    if kind == 0:
        return bytes(data[: rng.integers(0, len(data))])
    if kind == 1:
        for _ in range(rng.integers(1, 6)):
            limit = header_bytes if rng.random() < 0.5 else len(data)
            data[rng.integers(0, min(limit, len(data)))] = rng.integers(0, 256)
        return bytes(data)
    if kind in (2, 3):
        lines = bytes(data).split(b"\n")
        k = rng.integers(0, min(len(lines), header_lines))
        if kind == 2:
            toks = lines[k].split(b" ")
            toks[rng.integers(0, len(toks))] = GARBAGE_TOKENS[rng.integers(0, len(GARBAGE_TOKENS))]
            lines[k] = b" ".join(toks)
        elif rng.random() < 0.5:
            del lines[k]
        else:
            lines.insert(k, lines[k])
        return b"\n".join(lines)
    at = rng.integers(0, len(data))
    data[at:at] = rng.integers(0, 256, rng.integers(1, 20), dtype=np.uint8).tobytes()
    return bytes(data)


def run_cli(argv, capsys):
    """Run the ``reconstruct`` command in-process; return (status, stdout, stderr), with the
    status argparse exits with for a value its parser refuses."""
    from reconstruct.cli.main import main

    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


def jpeg_header(path, width: int, height: int, extra: int = 0) -> None:
    """A small JPEG whose frame header claims ``width × height`` pixels (its data is for 16 × 16),
    with ``extra`` bytes of padding in a comment segment."""
    import io

    import numpy as np
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.full((16, 16, 3), 100, np.uint8)).save(buf, "JPEG")
    data = bytearray(buf.getvalue())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    pad = b""
    while extra > 0:
        n = min(extra, 65533)
        pad += b"\xff\xfe" + (n + 2).to_bytes(2, "big") + b"\0" * n
        extra -= n
    path.write_bytes(bytes(data[:2]) + pad + bytes(data[2:]))


def bmp_header(path, width: int, height: int) -> None:
    """A 24-bit BMP that claims ``width × height`` pixels and holds 16 bytes of them."""
    import struct

    info = struct.pack("<IiiHHIIiiII", 40, width, height, 1, 24, 0, 0, 2835, 2835, 0, 0)
    path.write_bytes(b"BM" + struct.pack("<IHHI", 54 + 16, 0, 0, 54) + info + b"\0" * 16)


def tree(*folders) -> list[tuple[str, int, int]]:
    """Every path under ``folders`` with its size and modification time."""
    return sorted((str(p), p.stat().st_size, p.stat().st_mtime_ns) for f in folders for p in f.rglob("*"))
