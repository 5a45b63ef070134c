"""Command line: ``python -m data_synthetic OUT_DIR [options]`` writes a synthetic capture."""

from __future__ import annotations

import argparse
import sys
import time

from ptmcore.errors import InputError

from .capture import ENCODINGS, write_capture
from .lights import ring_lights
from .surfaces import SCENES


def _size(text: str) -> tuple[int, int]:
    """Parse WIDTHxHEIGHT into (H, W)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT such as 512x384, got {text!r}") from None
    return h, w


def build_parser() -> argparse.ArgumentParser:
    """The argument parser, separate so its help can be tested."""
    parser = argparse.ArgumentParser(
        prog="python -m data_synthetic",
        description=(
            "Render a synthetic RTI capture with known ground truth: one image per light, "
            "lights.lp, ground_truth/ (normals.npy, height.npy in mm, albedo.npy, mask.png, "
            "scene.json, scan_transform.txt) and a laser scan scan.ply. Same arguments and "
            "seed give identical files."
        ),
    )
    parser.add_argument("out_dir", metavar="OUT_DIR", help="capture folder (created if missing)")
    parser.add_argument("--scene", choices=sorted(SCENES), default="tablet",
                        help="object to render (default: %(default)s)")
    parser.add_argument("--size", type=_size, default="512x384", metavar="WxH",
                        help="image width x height in pixels (default: %(default)s)")
    parser.add_argument("--lights", type=int, default=48, metavar="N",
                        help="number of lights (default: %(default)s)")
    parser.add_argument("--encoding", choices=sorted(ENCODINGS), default="tiff16",
                        help="tiff16: 16-bit linear TIFF; jpeg8: 8-bit sRGB JPEG, quality 95 "
                             "(default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0,
                        help="drives the scene, the sensor noise and the scan "
                             "(default: %(default)s)")
    parser.add_argument("--pixel-size", type=float, default=None, metavar="MM",
                        help="millimetres per pixel (default: 80 mm across the longer side)")
    parser.add_argument("--min-elevation", type=float, default=15.0, metavar="DEG",
                        help="elevation of the dome's lowest ring (default: %(default)s)")
    parser.add_argument("--max-elevation", type=float, default=75.0, metavar="DEG",
                        help="elevation of the dome's highest ring (default: %(default)s)")
    parser.add_argument("--ring-elevation", type=float, default=None, metavar="DEG",
                        help="put all lights on one ring at this elevation instead of a dome "
                             "(rank-deficient for PTM fitting)")
    parser.add_argument("--specular", type=float, default=0.0, metavar="K",
                        help="peak of the Blinn-Phong highlight; 0 is purely Lambertian "
                             "(default: %(default)s)")
    parser.add_argument("--shininess", type=float, default=30.0, metavar="EXP",
                        help="Blinn-Phong exponent (default: %(default)s)")
    parser.add_argument("--ambient", type=float, default=0.0, metavar="K",
                        help="uniform light added to every image, as a fraction of the albedo "
                             "(default: %(default)s)")
    parser.add_argument("--noise", type=float, default=0.005, metavar="STD",
                        help="sensor noise, relative to full scale (default: %(default)s)")
    parser.add_argument("--no-shadows", action="store_true", help="disable cast shadows")
    parser.add_argument("--scan-points", type=int, default=None, metavar="N",
                        help="laser-scan points; 0 writes no scan "
                             "(default: one per four pixels)")
    parser.add_argument("--scan-noise", type=float, default=0.02, metavar="MM",
                        help="laser-scan depth noise (default: %(default)s)")
    parser.add_argument("--spheres", type=int, default=0, metavar="N",
                        help="put N black glossy spheres (1 to 4) in the frame's corners, for highlight "
                             "RTI: lights.lp then goes into ground_truth/, so `reconstruct calibrate` and "
                             "`reconstruct run` read the lights from the spheres (default: none)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status."""
    args = build_parser().parse_args(argv)
    start = time.perf_counter()
    try:
        lights = None
        if args.ring_elevation is not None:
            if args.lights < 1 or not 0 < args.ring_elevation <= 90:
                raise InputError("--ring-elevation needs 0 < DEG ≤ 90 and at least one light")
            lights = ring_lights(args.lights, args.ring_elevation)
        info = write_capture(
            args.out_dir, args.scene, args.size, args.lights, args.encoding, args.seed,
            pixel_size=args.pixel_size, specular=args.specular, shininess=args.shininess,
            cast_shadows=not args.no_shadows, ambient=args.ambient, noise=args.noise,
            min_elevation_deg=args.min_elevation, max_elevation_deg=args.max_elevation,
            lights=lights, scan_points=args.scan_points, scan_noise_mm=args.scan_noise,
            spheres=args.spheres,
        )
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    h, w = info.shape
    print(f"wrote {len(info.image_paths)} images of {w}x{h} px ({info.pixel_size:.4g} mm/px) "
          f"to {info.folder} in {time.perf_counter() - start:.1f} s")
    if info.spheres:
        radii = ", ".join(f"{r:.0f}" for _, _, r in info.spheres)
        print(f"{len(info.spheres)} glossy sphere(s) of radius {radii} px in the frame's corners; the true "
              f"lights are in {info.lp_path}: try `reconstruct calibrate {info.folder} -o lights.lp`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
