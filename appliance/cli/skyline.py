"""``viper skyline PANO --out skyline.csv``: detect the skyline in a panorama."""

from __future__ import annotations

import argparse

import cv2

from appliance.atomic import check_output_path, write_bytes_atomic
from appliance.errors import InputError
from appliance.skyline import write_skyline_csv
from appliance.vision.panorama import Projection, load_panorama
from appliance.vision.skyline_detect import (
    DetectionConfig,
    Method,
    detect_columns,
    draw_overlay,
    parse_mask,
    resample,
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "skyline",
        help="detect the skyline in a panorama and write the azimuth/elevation CSV",
        description=(
            "A panorama written by 'viper stitch' carries its geometry in PANO.json; any other image is "
            "read as an equirectangular 360-degree photo (left edge = azimuth 0, middle row = horizon)."
        ),
    )
    p.add_argument("panorama", help="panorama image (PNG/JPEG)")
    p.add_argument("--out", required=True, help="skyline CSV to write (azimuth_deg,elevation_deg)")
    p.add_argument("--projection", choices=[m.value for m in Projection], help="panorama projection")
    p.add_argument("--mask", default="", help="azimuth ranges to ignore, e.g. '120-135,350-10' (degrees)")
    p.add_argument("--overlay", help="PNG to write: the panorama with the detected skyline in red")
    p.add_argument("--azimuth-offset", type=float, default=0.0, help="azimuth (deg) of the left edge / added")
    p.add_argument("--method", choices=[m.value for m in Method], default=Method.DP.value)
    p.add_argument("--step-deg", type=float, default=1.0, help="azimuth step of the CSV rows (default 1)")
    p.add_argument("--min-elevation-deg", type=float, default=DetectionConfig.min_elevation_deg)
    p.add_argument("--max-elevation-deg", type=float, default=DetectionConfig.max_elevation_deg)
    p.add_argument("--force", action="store_true", help="replace the CSV and the overlay if they exist")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_output_path(args.out, [args.panorama, *filter(None, [args.overlay])], args.force)
    if args.overlay:
        check_output_path(args.overlay, [args.panorama], args.force)
    cfg = DetectionConfig(
        method=Method(args.method),
        step_deg=args.step_deg,
        min_elevation_deg=args.min_elevation_deg,
        max_elevation_deg=args.max_elevation_deg,
    )
    projection = Projection(args.projection) if args.projection else None
    pano = load_panorama(args.panorama, projection, args.azimuth_offset)
    columns = detect_columns(pano, cfg, parse_mask(args.mask))
    if args.overlay:
        ok, buf = cv2.imencode(".png", draw_overlay(pano, columns, thickness_px=max(1, pano.height // 500)))
        if not ok:
            raise InputError(f"{args.overlay}: cannot encode the overlay")
        write_bytes_atomic(args.overlay, buf.tobytes())
    skyline = resample(columns, pano, cfg.step_deg)
    if not skyline.valid.any():
        raise InputError(f"{args.panorama}: no skyline found (no column shows sky above ground)")
    write_skyline_csv(skyline, args.out)
    print(f"{args.out}: {skyline.valid.sum()} of {skyline.azimuth_deg.size} azimuths detected")
    return 0
