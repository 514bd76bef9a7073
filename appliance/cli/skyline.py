"""``viper skyline IMAGE --out skyline.csv``: detect the skyline in a panorama or in one photo."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import cv2
import numpy as np

from appliance.atomic import check_output_path, write_bytes_atomic
from appliance.errors import InputError
from appliance.skyline import write_skyline_csv
from appliance.vision.camera import CameraPose
from appliance.vision.panorama import Projection, load_panorama, read_image, sidecar_path
from appliance.vision.photo import (
    PHOTO_MAX_ELEVATION_DEG,
    PHOTO_MIN_ELEVATION_DEG,
    Rect,
    detect_photo,
    draw_photo_overlay,
    load_photo,
    parse_orientation,
    parse_rect,
    read_sidecar,
    resample_photo,
)
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
        help="detect the skyline in a panorama or a photo and write the azimuth/elevation CSV",
        description=(
            "A single perspective photo needs its camera (--camera, a calibration TOML from 'viper calibrate"
            " camera' or 'viper calibrate pose') and its orientation (--orientation, or a sidecar PHOTO.json"
            " with yaw_deg, pitch_deg, roll_deg): the skyline is found in the photo's own pixels and every"
            " column turned into a true azimuth and elevation through the lens model. A panorama written by"
            " 'viper stitch' carries its geometry in PANO.json; any other image is read as an"
            " equirectangular 360-degree photo (left edge = azimuth 0, middle row = horizon)."
        ),
    )
    p.add_argument("image", help="photo or panorama (PNG/JPEG)")
    p.add_argument("--out", required=True, help="skyline CSV to write (azimuth_deg,elevation_deg)")
    p.add_argument("--camera", help="photo: camera calibration TOML ([camera] table)")
    p.add_argument(
        "--orientation",
        type=_orientation,
        help="photo: YAW,PITCH,ROLL in degrees (yaw: true azimuth of the optical axis; pitch up and roll"
        " right-side-down positive)",
    )
    p.add_argument(
        "--mask",
        action="append",
        default=[],
        help="photo: a pixel rectangle x0,y0,x1,y1 to ignore (repeatable; burnt-in text is found by itself);"
        " panorama: azimuth ranges, e.g. '120-135,350-10' (degrees)",
    )
    p.add_argument("--keep-text", action="store_true", help="photo: do not look for burnt-in text to mask")
    p.add_argument("--projection", choices=[m.value for m in Projection], help="panorama projection")
    p.add_argument("--overlay", help="PNG to write: the image with the detected skyline in red")
    p.add_argument("--azimuth-offset", type=float, default=0.0, help="panorama: azimuth (deg) of the left edge")
    p.add_argument("--method", choices=[m.value for m in Method], default=Method.DP.value)
    p.add_argument("--step-deg", type=float, default=1.0, help="azimuth step of the CSV rows (default 1)")
    p.add_argument("--min-elevation-deg", type=float, help="lowest elevation searched (photo -30, panorama -45)")
    p.add_argument("--max-elevation-deg", type=float, help="highest elevation searched (photo 45, panorama 60)")
    p.add_argument("--force", action="store_true", help="replace the CSV and the overlay if they exist")
    p.set_defaults(func=run)


def _orientation(text: str) -> CameraPose:
    try:
        return parse_orientation(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _is_photo(args: argparse.Namespace) -> bool:
    """A photo when a camera or an orientation is given, or when its sidecar holds an orientation."""
    if args.camera or args.orientation:
        return True
    return read_sidecar(args.image)[0] is not None


def run(args: argparse.Namespace) -> int:
    check_output_path(args.out, [args.image, *filter(None, [args.overlay])], args.force)
    if args.overlay:
        check_output_path(args.overlay, [args.image], args.force)
    photo_mode = _is_photo(args)
    lo, hi = args.min_elevation_deg, args.max_elevation_deg
    if lo is None:
        lo = PHOTO_MIN_ELEVATION_DEG if photo_mode else DetectionConfig.min_elevation_deg
    if hi is None:
        hi = PHOTO_MAX_ELEVATION_DEG if photo_mode else DetectionConfig.max_elevation_deg
    cfg = DetectionConfig(
        method=Method(args.method), step_deg=args.step_deg, min_elevation_deg=lo, max_elevation_deg=hi
    )
    if photo_mode:
        return _run_photo(args, cfg)
    check_azimuth_mask(args.mask)
    image = None
    if args.projection is None and not sidecar_path(args.image).is_file():
        image = read_image(args.image)
        h, w = image.shape[:2]
        if abs(w - 2 * h) > 0.02 * w:
            raise InputError(
                f"{args.image}: a {w}x{h} image is not a 360-degree panorama; for a single photo give"
                " --camera camera.toml and --orientation YAW,PITCH,ROLL (or a sidecar with yaw_deg,"
                " pitch_deg, roll_deg)"
            )
    projection = Projection(args.projection) if args.projection else None
    pano = load_panorama(args.image, projection, args.azimuth_offset)
    columns = detect_columns(pano, cfg, parse_mask(",".join(args.mask)))
    if args.overlay:
        _write_png(args.overlay, draw_overlay(pano, columns, thickness_px=max(1, pano.height // 500)))
    skyline = resample(columns, pano, cfg.step_deg)
    if not skyline.valid.any():
        raise InputError(f"{args.image}: no skyline found (no column shows sky above ground)")
    write_skyline_csv(skyline, args.out)
    print(f"{args.out}: {skyline.valid.sum()} of {skyline.azimuth_deg.size} azimuths detected")
    return 0


def check_azimuth_mask(masks: list[str]) -> None:
    """A panorama's mask ranges: every end an azimuth within [-360, 360] degrees."""
    for text in masks:
        for part in (p.strip() for p in text.split(",")):
            match = _RANGE.fullmatch(part)
            if not part or match is None:
                continue  # the mask parser names malformed ranges
            for end in match.groups():
                value = float(end)
                if not -360.0 <= value <= 360.0:
                    raise InputError(f"--mask {part!r}: azimuth {end} outside [-360, 360] degrees")


_RANGE = re.compile(r"\s*([-+]?[0-9.eE+]+)\s*[-:]\s*([-+]?[0-9.eE+]+)\s*")


def _write_png(path: str, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise InputError(f"{path}: cannot encode the overlay")
    write_bytes_atomic(path, buf.tobytes())


def _run_photo(args: argparse.Namespace, cfg: DetectionConfig) -> int:
    rects: list[Rect] = [parse_rect(text) for text in args.mask]
    photo = load_photo(args.image, args.camera, args.orientation)
    sky = detect_photo(photo, cfg, rects, find_text=not args.keep_text)
    if args.overlay:
        _write_png(args.overlay, draw_photo_overlay(photo, sky, thickness_px=max(1, photo.image.shape[0] // 540)))
    skyline = resample_photo(sky, cfg.step_deg)
    if not skyline.valid.any():
        raise InputError(f"{args.image}: no skyline found (no column shows sky above ground)")
    write_skyline_csv(skyline, args.out)
    span = float(sky.azimuth_deg[-1] - sky.azimuth_deg[0]) % 360.0
    columns = float(np.isfinite(sky.row).mean())
    texts = len(sky.masked) - len(rects)
    print(
        f"{Path(args.out)}: {int(skyline.valid.sum())} azimuths detected over the photo's {span:.1f} deg view"
        f" ({columns:.1%} of its columns); {len(rects)} masked rectangles, {texts} text boxes found"
    )
    return 0
