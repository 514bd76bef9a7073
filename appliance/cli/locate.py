"""``viper locate PHOTO --map MAP``: one photo (or panorama) and a map in, a position and an orientation out."""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from appliance.atomic import check_output_folder
from appliance.cli.estimate import _checked_height, _lat_lon, _numbers, _pair
from appliance.cli.skyline import check_azimuth_mask
from appliance.config import load_config
from appliance.errors import InputError
from appliance.locating.map_source import OpenedMap, SearchArea, area_log_prior, open_map
from appliance.locating.photo_pose import (
    MIN_ARC_DEG,
    OrientationPrior,
    PhotoAnswer,
    PhotoView,
    locate_photo,
    start_loading_optimizer,
)
from appliance.locating.position import Position, answer_text, locate, truth_in_ellipse, truth_in_region
from appliance.skyline import Skyline
from appliance.terrain.database import SkylineDatabase
from appliance.vision.camera import CameraPose
from appliance.vision.exif import PhotoExif, heading_true_deg, intrinsics_from_exif, read_exif
from appliance.vision.intrinsics import CameraIntrinsics, load_intrinsics
from appliance.vision.panorama import load_panorama, read_image, sidecar_path
from appliance.vision.photo import Photo, detect_photo, parse_rect
from appliance.vision.skyline_detect import DetectionConfig, detect_columns, parse_mask, resample

LOG = logging.getLogger(__name__)

#: The radius (m) of the search circle around the photo's own EXIF position, when no area is given.
EXIF_NEAR_RADIUS_M = 1000.0
#: A compass heading's tolerance (deg) when none is given: a phone's or a rover's magnetometer.
DEFAULT_HEADING_TOLERANCE_DEG = 15.0
#: The least share of the photo's columns where a skyline must be found.
MIN_SKY_COLUMNS = 0.1
#: A calibrated lens's focal length error (1 sigma, fraction).
CALIBRATED_FOCAL_SIGMA = 0.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "locate",
        help="locate a photo or a panorama on a map: position and orientation, in one command",
        description=(
            "The skyline is found in the photo's own pixels; the camera's yaw, pitch, roll and the focal length's"
            " correction are solved with the position. MAP is a skyline database (viper precompute), a tiled"
            " database's folder, or a DEM: its database for the search area is built once and kept in the cache."
            " The lens comes from --camera or from the photo's EXIF (35 mm equivalent focal length)."
        ),
    )
    p.add_argument("photo", help="photo (JPEG/PNG), or a panorama (2:1 equirectangular, or with a PANO.json sidecar)")
    p.add_argument("--map", required=True, help="skyline database, tiled database folder, or DEM file")
    p.add_argument("--camera", help="camera calibration TOML (else the lens from the photo's EXIF)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--near", metavar="LAT,LON,RADIUS_M", help="search within RADIUS_M metres of LAT,LON "
                       "(default: the photo's EXIF position, within 1 km, when it has one)")
    where.add_argument("--search-bounds", metavar="W,S,E,N", help="search within this lon/lat box (degrees)")
    p.add_argument("--heading", type=float, metavar="DEG",
                   help="true azimuth of the optical axis (a compass); default: EXIF GPSImgDirection, else unknown")
    p.add_argument("--heading-tolerance", type=float, metavar="DEG",
                   help=f"the heading's error bound (default {DEFAULT_HEADING_TOLERANCE_DEG:g})")
    p.add_argument("--pitch-tolerance", type=float, default=5.0, metavar="DEG",
                   help="how far from level the camera's axis may point (default 5)")
    p.add_argument("--roll-tolerance", type=float, default=3.0, metavar="DEG",
                   help="how far the camera may be rolled (default 3)")
    p.add_argument("--crs", help="CRS of a DEM file that carries none")
    p.add_argument("--cache", help="folder of the databases built from DEMs (default: the appliance's cache)")
    p.add_argument("--height", type=float, metavar="M", help="camera height above the map's surface (default 1.5)")
    p.add_argument("--sigma", help="sigma interval LO,HI in degrees for the search (default: [estimator] sigma_deg)")
    p.add_argument("--config", help="configuration TOML")
    p.add_argument("--mask", action="append", default=[],
                   help="photo: a pixel rectangle x0,y0,x1,y1 to ignore (repeatable); panorama: azimuth ranges")
    p.add_argument("--keep-text", action="store_true", help="photo: do not look for burnt-in text to mask")
    p.add_argument("--truth", metavar="LAT,LON|exif", help="the true position, for the error (exif: the photo's own)")
    p.add_argument("--json", action="store_true", help="print the answer as one JSON object")
    p.add_argument("--report", metavar="DIR", help="write the picture, posteriors, region and report.html here")
    p.add_argument("--force", action="store_true", help="replace report files that exist")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    cfg = load_config(args.config).estimator
    sigma = _pair(args.sigma, "--sigma") if args.sigma is not None else cfg.sigma_deg
    height = _checked_height(args.height)
    image = read_image(args.photo)
    exif = read_exif(args.photo)
    panorama = _is_panorama(args.photo, image.shape[1], image.shape[0])
    if not panorama:
        start_loading_optimizer()  # the photo's orientation fits need it; meanwhile its skyline is found
    area = _area(args, exif)
    truth = _truth(args.truth, exif)
    report = Path(args.report) if args.report else None
    if report is not None:
        from appliance.outputs import report as pages  # the report writers (rasterio, figures) load only for --report

        check_output_folder(report, [args.photo, args.map], pages.estimate_report_names([args.photo]), args.force)
    name = Path(args.photo).name
    # everything about the photo is checked before a database is built for it
    view: PhotoView | None = None
    skyline: Skyline | None = None
    if panorama:
        skyline = _panorama_skyline(args)
    else:
        intrinsics, focal_sigma = _lens(args.camera, exif, name)
        view = _photo_view(args, image, intrinsics, name)
    cache = Path(args.cache) if args.cache else None
    if height is None:
        opened = open_map(args.map, area=area, crs=args.crs, cache_dir=cache)
    else:
        opened = open_map(args.map, area=area, crs=args.crs, cache_dir=cache, height_m=height)
    db = _single_database(opened, args.map)
    log_prior = area_log_prior(db, area)
    answer: PhotoAnswer | None = None
    if view is None:
        assert skyline is not None
        tolerance = None if args.heading is None else _tolerance(args)
        pos = locate(db, skyline, sigma, tolerance, log_prior=log_prior, source=name, height_m=height,
                     occlusion_weight=cfg.occlusion_weight, map_sigma_m=cfg.map_vertical_sigma_m,
                     sigma_floor_deg=cfg.sigma_floor_deg)
    else:
        prior = OrientationPrior(*_heading(args, exif, area), pitch_tolerance_deg=args.pitch_tolerance,
                                 roll_tolerance_deg=args.roll_tolerance, focal_sigma=focal_sigma)
        answer = locate_photo(db, view, prior, sigma_deg=sigma, log_prior=log_prior, height_m=height,
                              occlusion_weight=cfg.occlusion_weight, map_sigma_m=cfg.map_vertical_sigma_m,
                              sigma_floor_deg=cfg.sigma_floor_deg)
        pos, skyline = answer.position, answer.skyline
    record = pos.to_json(db, truth)
    if truth is not None:
        record["truth"].update(in_region=truth_in_region(db, pos, truth), in_ellipse=truth_in_ellipse(db, pos, truth))
    if answer is not None:
        record["orientation"] = answer.orientation_json()
    record["timing"] = {"build_s": None if opened.built_s is None else round(opened.built_s, 2),
                        "total_s": round(time.perf_counter() - t0, 3)}
    if opened.cache_path is not None:
        record["database"] = str(opened.cache_path)
    if report is not None:
        entry = pages.write_estimate_files(db, report, 0, name, pos, skyline, truth)
        pages.write_estimate_report(db, [entry], report, title="Viper locate")
    _print(args, name, pos, record, answer, opened)
    return 0


def _print(args: argparse.Namespace, name: str, pos: Position, record: dict, answer: PhotoAnswer | None,
           opened: OpenedMap) -> None:
    if args.json:
        print(json.dumps(record), flush=True)
        return
    if opened.built_s is not None:
        print(f"{args.map}: database built for the search area in {opened.built_s:.1f} s ({opened.cache_path})")
    print(f"{name}: {answer_text(pos, record)}")
    if answer is not None:
        o = answer.pose
        print(f"  orientation: yaw {o.yaw_deg:.2f} deg, pitch {o.pitch_deg:+.2f} deg, roll {o.roll_deg:+.2f} deg,"
              f" focal length {answer.focal_px:.1f} px")
    for note in pos.notes:
        LOG.info("  %s", note)


def _is_panorama(photo: str, width: int, height: int) -> bool:
    """A panorama has a PANO.json sidecar or is a 2:1 equirectangular image."""
    return sidecar_path(photo).is_file() or abs(width - 2 * height) <= 0.02 * width


def _area(args: argparse.Namespace, exif: PhotoExif) -> SearchArea | None:
    if args.near is not None:
        lat, lon, radius = _numbers(args.near, "--near", 3)
        return SearchArea(circle=(lat, lon, radius))
    if args.search_bounds is not None:
        west, south, east, north = _numbers(args.search_bounds, "--search-bounds", 4)
        return SearchArea(box=(west, south, east, north))
    if exif.lat is not None and exif.lon is not None:
        LOG.debug("searching within %.0f m of the photo's EXIF position %.6f, %.6f", EXIF_NEAR_RADIUS_M, exif.lat,
                  exif.lon)
        return SearchArea(circle=(exif.lat, exif.lon, EXIF_NEAR_RADIUS_M))
    return None


def _truth(text: str | None, exif: PhotoExif) -> tuple[float, float] | None:
    if text is None:
        return None
    if text.strip().lower() == "exif":
        if exif.lat is None or exif.lon is None:
            raise InputError("--truth exif: the photo's EXIF holds no GPS position")
        return exif.lat, exif.lon
    return _lat_lon(text, "--truth")


def _single_database(opened: OpenedMap, map_path: str) -> SkylineDatabase:
    if opened.database is None:
        raise InputError(f"{map_path}: a tiled database is not yet searched by 'viper locate'; give the tile's "
                         "database file, or the DEM with --near")
    return opened.database


def _tolerance(args: argparse.Namespace) -> float:
    tol = DEFAULT_HEADING_TOLERANCE_DEG if args.heading_tolerance is None else float(args.heading_tolerance)
    if not (math.isfinite(tol) and 0.0 <= tol <= 180.0):
        raise InputError(f"--heading-tolerance {tol}: expected 0..180 degrees")
    return tol


def _heading(args: argparse.Namespace, exif: PhotoExif, area: SearchArea | None) -> tuple[float | None, float]:
    """The heading prior: --heading, else the EXIF image direction (true), else none."""
    if args.heading is not None:
        if not math.isfinite(args.heading):
            raise InputError(f"--heading {args.heading}: expected degrees")
        return float(args.heading) % 360.0, _tolerance(args)
    if args.heading_tolerance is not None:
        raise InputError("--heading-tolerance needs --heading")
    lat = lon = None
    if area is not None and area.circle is not None:
        lat, lon = area.circle[0], area.circle[1]
    heading = heading_true_deg(exif, lat, lon)
    if heading is None:
        return None, 180.0
    LOG.debug("heading from the photo's EXIF: %.1f deg true", heading)
    return heading, DEFAULT_HEADING_TOLERANCE_DEG


def _lens(camera: str | None, exif: PhotoExif, name: str) -> tuple[CameraIntrinsics, float]:
    if camera is not None:
        return load_intrinsics(camera), CALIBRATED_FOCAL_SIGMA
    return intrinsics_from_exif(exif, name)


def _photo_view(args: argparse.Namespace, image: np.ndarray, intrinsics: CameraIntrinsics, name: str) -> PhotoView:
    photo = Photo(image, intrinsics, CameraPose(0.0, 0.0, 0.0), name)
    sky = detect_photo(photo, DetectionConfig(min_elevation_deg=-30.0, max_elevation_deg=45.0),
                       [parse_rect(t) for t in args.mask], find_text=not args.keep_text)
    detected = float(np.isfinite(sky.row).mean())
    if detected < MIN_SKY_COLUMNS:
        raise InputError(f"{name}: no sky above the terrain: a skyline was found in {detected:.0%} of the photo's "
                         "columns (a photo of the skyline is needed)")
    view = PhotoView.from_detection(sky, intrinsics, name)
    arc = view.arc_deg()
    if arc < MIN_ARC_DEG:
        raise InputError(f"{name}: the skyline spans {arc:.1f} deg of the view, less than the {MIN_ARC_DEG:g} deg "
                         "needed to locate a photo")
    return view


def _panorama_skyline(args: argparse.Namespace) -> Skyline:
    check_azimuth_mask(args.mask)
    pano = load_panorama(args.photo, None, 0.0)
    cfg = DetectionConfig()
    skyline = resample(detect_columns(pano, cfg, parse_mask(",".join(args.mask))), pano, cfg.step_deg)
    if not skyline.valid.any():
        raise InputError(f"{args.photo}: no skyline found (no column shows sky above ground)")
    return skyline
