"""``viper calibrate theodolite|camera|compass|inclinometer``: thin wrappers over calibration/."""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from viper_calibration import compass, inclinometer, theodolite
from viper_calibration.config_edit import significant, update_toml_table

from appliance.atomic import check_output_path, write_text_atomic
from appliance.config import Config, from_mapping
from appliance.errors import ConfigError
from appliance.vision.intrinsics import load_intrinsics

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def _validate_config_text(path: Path) -> Any:
    def validate(text: str) -> None:
        try:
            from_mapping(Config, tomllib.loads(text))
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: the edited configuration is not valid TOML: {exc}") from None
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None

    return validate


def _theodolite(args: argparse.Namespace) -> int:
    points = theodolite.read_points_csv(args.points)
    result = theodolite.calibrate_sigma(points, confidence=args.confidence, map_sigma_deg=args.map_share)
    sensor = [significant(v) for v in result.sigma_deg]
    lo, hi = (significant(v) for v in result.estimator_sigma_deg)
    if args.config is not None:
        update_toml_table(
            args.config, "estimator", {"sensor_sigma_deg": [lo, hi]},
            validate=_validate_config_text(args.config),
        )
    if args.json:
        print(
            json.dumps(
                {
                    "n": result.n,
                    "confidence": result.confidence,
                    "mean_residual_deg": result.mean_residual_deg,
                    "s_deg": result.s_deg,
                    "sensor_sigma_deg": sensor,
                    "map_sigma_deg": list(result.map_sigma_deg),
                    "sigma_deg": [lo, hi],
                }
            )
        )
    else:
        print(theodolite.format_report(result))
        if args.config is not None:
            print(f"wrote estimator.sensor_sigma_deg = [{lo}, {hi}] (the floor of the sigma the estimator learns) "
                  f"to {args.config}")
    return 0


def _map_share(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO,HI in degrees, got {text!r}") from None
    if not (0.0 <= lo <= hi < 90.0):
        raise argparse.ArgumentTypeError(f"expected 0 <= LO <= HI < 90 degrees, got {text!r}")
    return lo, hi


def _confidence(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"must lie strictly between 0 and 1, got {value}")
    return value


def _pattern(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected COLSxROWS inner corners such as 9x6, got {text!r}"
        ) from None
    if cols < 3 or rows < 3:
        raise argparse.ArgumentTypeError(f"a board needs at least 3x3 inner corners, got {text!r}")
    return cols, rows


def _camera(args: argparse.Namespace) -> int:
    # OpenCV loads only for the camera and pose subcommands
    from viper_calibration.camera import calibrate_camera, format_report, write_camera_calibration

    result = calibrate_camera(
        args.images, pattern_size=args.pattern, square_size_m=args.square_m, min_boards=args.min_boards
    )
    if args.output is not None:
        write_camera_calibration(args.output, result.intrinsics)
    if args.json:
        print(json.dumps(result.as_dict()))
    else:
        print(format_report(result))
        if args.output is not None:
            print(f"wrote {args.output}")
    return 0


def _compass(args: argparse.Namespace) -> int:
    result = compass.calibrate_compass_file(
        args.log,
        mode=args.mode,
        accel_path=args.accel,
        accel_measures=args.accel_measures,
        known_bearing_deg=args.known_bearing_deg,
        bearing_window_s=args.bearing_window_s,
        declination_deg=args.declination_deg,
    )
    if args.output is not None:
        compass.write_compass_calibration(args.output, result)
    if args.json:
        print(json.dumps(result.as_dict()))
    else:
        print(compass.format_report(result))
        if args.output is not None:
            print(f"wrote [compass] to {args.output}")
    return 0


def _inclinometer(args: argparse.Namespace) -> int:
    result = inclinometer.calibrate_reversal(
        inclinometer.read_reversal_csv(args.readings), angle_tolerance_deg=args.angle_tolerance_deg
    )
    if args.output is not None:
        inclinometer.write_inclinometer_calibration(args.output, result)
    if args.json:
        print(json.dumps(result.as_dict()))
    else:
        print(inclinometer.format_report(result))
        if args.output is not None:
            print(f"wrote [inclinometer] to {args.output}")
    return 0


def _pose(args: argparse.Namespace) -> int:
    # OpenCV loads only for the camera and pose subcommands
    from viper_calibration.camera import write_camera_calibration
    from viper_calibration.pose import fit_pose, format_report, read_control_points

    from appliance.vision.panorama import read_image

    for out in filter(None, [args.out, args.camera_out]):
        check_output_path(out, [args.photo, args.points], force=args.force or out == args.camera_out)
    intrinsics = load_intrinsics(args.camera)
    h, w = read_image(args.photo).shape[:2]
    if (w, h) != (intrinsics.width, intrinsics.height):
        raise ConfigError(
            f"{args.camera}: calibration for {intrinsics.width}x{intrinsics.height} images, but {args.photo} is {w}x{h}"
        )
    points = read_control_points(args.points, crs=args.crs)
    fit = fit_pose(points, intrinsics, refine=args.refine)
    if args.camera_out is not None:
        write_camera_calibration(args.camera_out, replace(fit.intrinsics, reprojection_error_px=fit.rms_px))
    record = fit.as_dict()
    if args.out is not None:
        sidecar = {k: record[k] for k in ("yaw_deg", "pitch_deg", "roll_deg")}
        if args.camera_out is not None:
            sidecar["camera"] = os.path.relpath(Path(args.camera_out).resolve(), Path(args.out).resolve().parent)
        sidecar.update({k: v for k, v in record.items() if k not in sidecar})
        write_text_atomic(args.out, json.dumps(sidecar, indent=1) + "\n")
    if args.json:
        print(json.dumps(record))
    else:
        print(format_report(fit))
        for out in filter(None, [args.out, args.camera_out]):
            print(f"wrote {out}")
    return 0


def _refine(text: str) -> tuple[str, ...]:
    from viper_calibration.pose import REFINABLE  # OpenCV, only when --refine is given

    names = tuple(t.strip().lower() for t in text.split(",") if t.strip())
    bad = [n for n in names if n not in REFINABLE]
    if bad:
        raise argparse.ArgumentTypeError(f"cannot refine {', '.join(bad)}: choose among {','.join(REFINABLE)}")
    return names


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


def register(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "calibrate", help="calibrate the theodolite sigma, camera, compass, inclinometers"
    )
    sub = parser.add_subparsers(dest="target", metavar="TARGET", required=True)
    for add in (_add_theodolite, _add_camera, _add_pose, _add_compass, _add_inclinometer):
        add(sub)


def _add_theodolite(sub: Any) -> None:
    p = sub.add_parser("theodolite", help="sigma interval of the elevation residuals against a theodolite")
    p.add_argument("points", type=Path, help="CSV: point,camera_elevation_deg,theodolite_elevation_deg")
    p.add_argument("--config", type=Path, help="configuration TOML to receive [estimator] sigma_deg")
    p.add_argument("--confidence", type=_confidence, default=0.95, help="confidence level (default 0.95)")
    p.add_argument(
        "--map-share", type=_map_share, default=(0.0, 0.0), metavar="LO,HI",
        help="a share (deg) a map known to add error of its own adds to the floor of the estimator's learned"
        " sigma, in quadrature with the sensor's (default 0,0: the estimator learns the map's share per skyline)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object with n, s_deg and sigma_deg")
    p.set_defaults(func=_theodolite)


def _add_camera(sub: Any) -> None:
    p = sub.add_parser(
        "camera", help="intrinsics (focal length, principal point, plumb_bob) from chessboards"
    )
    p.add_argument("images", type=Path, nargs="+", help="chessboard images (PNG, JPEG...)")
    p.add_argument("--pattern", type=_pattern, default=(9, 6), help="inner corners COLSxROWS (default 9x6)")
    p.add_argument(
        "--square-m", type=_positive_float, default=0.025, help="square size, metres (default 0.025)"
    )
    p.add_argument("--min-boards", type=int, default=5, help="fewest boards to accept (default 5)")
    p.add_argument("--output", type=Path, help="camera calibration TOML to write ([camera] table)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_camera)


def _add_pose(sub: Any) -> None:
    p = sub.add_parser(
        "pose",
        help="camera orientation (and focal length, radial distortion) from ground-control points in a photo",
        description=(
            "Fits the orientation and centre of the camera to image points whose map positions are known"
            " (solvePnP through cv2.calibrateCamera on one view). POINTS: CSV with u_px,v_px (or x_img,y_img)"
            " and lat_deg,lon_deg,height_m, or x,y,z in --crs; optional name and use (0 leaves a point out)."
            " Yaw is the true azimuth of the optical axis."
        ),
    )
    p.add_argument("photo", type=Path, help="the photo the points were picked on (its size is checked)")
    p.add_argument("--camera", type=Path, required=True, help="camera calibration TOML: the starting intrinsics")
    p.add_argument("--points", type=Path, required=True, help="ground-control points CSV")
    p.add_argument("--crs", help="CRS of x,y,z map coordinates, e.g. EPSG:32632")
    p.add_argument(
        "--refine", type=_refine, default=(), help="intrinsics to fit as well: any of f,k1,k2 (e.g. f,k1,k2)"
    )
    p.add_argument("--out", type=Path, help="JSON to write: the photo's sidecar (yaw_deg, pitch_deg, roll_deg...)")
    p.add_argument("--camera-out", type=Path, help="camera calibration TOML to receive the fitted [camera] table")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_pose)


def _add_compass(sub: Any) -> None:
    p = sub.add_parser("compass", help="hard and soft iron from a logged rotation, and the mounting offset")
    p.add_argument(
        "log", type=Path, help="CSV with columns mag_x_gauss,mag_y_gauss,mag_z_gauss (+ optional ones)"
    )
    p.add_argument(
        "--mode",
        choices=("sphere", "level"),
        default="sphere",
        help="sphere: ellipsoid fit of a full-sphere rotation; level: ellipse fit of a levelled turn",
    )
    p.add_argument(
        "--accel", type=Path, help="accelerometer CSV t_s,acc_x_g,acc_y_g,acc_z_g (tilt compensation)"
    )
    p.add_argument(
        "--accel-measures",
        choices=("up", "down"),
        default="up",
        help="the accelerometer's reading at rest points up (usual) or down",
    )
    p.add_argument("--known-bearing-deg", type=float, help="true azimuth the x axis faces at the start")
    p.add_argument(
        "--bearing-window-s", type=_positive_float, default=1.0, help="how long it faces it (default 1 s)"
    )
    p.add_argument("--declination-deg", type=float, default=0.0, help="magnetic declination, east positive")
    p.add_argument("--output", type=Path, help="calibration TOML to receive the [compass] table")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_compass)


def _add_inclinometer(sub: Any) -> None:
    p = sub.add_parser("inclinometer", help="offsets by the two-position (reversal) method")
    p.add_argument("readings", type=Path, help="CSV: stage_deg,tilt_x_deg,tilt_y_deg at stage 0 and 180 deg")
    p.add_argument(
        "--angle-tolerance-deg", type=float, default=2.0, help="how far from 0/180 a stage angle may be"
    )
    p.add_argument("--output", type=Path, help="calibration TOML to receive the [inclinometer] table")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_inclinometer)
