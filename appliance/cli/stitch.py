"""``viper stitch IMAGES... --out PANO``: stitch the stage's images into a cylindrical panorama.

Each image's stage angle (degrees) comes, in this order, from ``--stage-angles`` (one per image,
in the order given), from a sidecar ``<image>.json`` (``{"stage_angle_deg": 15.0, "pitch_deg": 0.1,
"roll_deg": -0.2}``; pitch and roll optional), or from the file name (``..._stage015.0...``).
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from appliance.atomic import check_output_path
from appliance.errors import InputError
from appliance.inputs import read_json_bounded
from appliance.logsetup import progress
from appliance.vision.intrinsics import CameraIntrinsics, load_intrinsics
from appliance.vision.panorama import read_image, save_panorama, sidecar_path
from appliance.vision.stitching import Shot, stitch

STAGE_IN_NAME = re.compile(r"stage[_-]?(-?\d+(?:\.\d+)?)", re.IGNORECASE)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("stitch", help="stitch images taken at known stage angles into a panorama")
    p.add_argument("images", nargs="+", help="image files")
    p.add_argument("--out", required=True, help="panorama PNG to write (geometry in <out>.json)")
    p.add_argument("--calibration", help="camera calibration TOML ([camera] table)")
    p.add_argument("--hfov-deg", type=float, help="horizontal field of view, without a calibration file")
    p.add_argument("--stage-angles", help="comma-separated stage angles (deg), one per image")
    p.add_argument("--heading-offset", type=float, default=0.0, help="azimuth (deg) of stage angle 0")
    p.add_argument("--force", action="store_true", help="replace the panorama and its geometry if they exist")
    p.set_defaults(func=run)


def shot_pose(path: Path, given: float | None) -> tuple[float, float, float]:
    """(stage angle, pitch, roll) in degrees of one image."""
    side = path.with_name(path.name + ".json")
    meta: dict[str, object] = {}
    if side.is_file():
        try:
            meta = read_json_bounded(side, "pose sidecar")
        except OSError as exc:
            raise InputError(f"{side}: cannot read the pose sidecar: {exc.strerror or exc}") from None
        if not isinstance(meta, dict):
            raise InputError(f"{side}: not valid JSON: expected an object, got {type(meta).__name__}")
    try:
        pitch = float(meta.get("pitch_deg", 0.0))  # type: ignore[arg-type]
        roll = float(meta.get("roll_deg", 0.0))  # type: ignore[arg-type]
        if given is not None:
            return given, pitch, roll
        if "stage_angle_deg" in meta:
            return float(meta["stage_angle_deg"]), pitch, roll  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise InputError(f"{side}: {exc}") from None
    m = STAGE_IN_NAME.search(path.stem)
    if m is None:
        raise InputError(
            f"{path}: no stage angle (use --stage-angles, a {side.name} sidecar, or '_stageNNN' in the name)"
        )
    return float(m.group(1)), pitch, roll


def run(args: argparse.Namespace) -> int:
    paths = [Path(p) for p in args.images]
    inputs = [*paths, *(p.with_name(p.name + ".json") for p in paths), *filter(None, [args.calibration])]
    check_output_path(args.out, inputs, args.force)
    check_output_path(sidecar_path(args.out), inputs, args.force)
    angles: list[float | None] = [None] * len(paths)
    if args.stage_angles:
        try:
            parsed = [float(a) for a in args.stage_angles.split(",") if a.strip()]
        except ValueError:
            raise InputError(f"--stage-angles {args.stage_angles!r}: expected comma-separated numbers") from None
        if len(parsed) != len(paths):
            raise InputError(f"--stage-angles gives {len(parsed)} angles for {len(paths)} images")
        angles = list(parsed)
    images = [read_image(p) for p in progress(paths, len(paths), "reading", "image")]
    h, w = images[0].shape[:2]
    if args.calibration:
        intrinsics = load_intrinsics(args.calibration)
    elif args.hfov_deg:
        intrinsics = CameraIntrinsics.from_fov(w, h, args.hfov_deg)
    else:
        raise InputError("stitch: give --calibration FILE or --hfov-deg DEG")
    shots = []
    for p, img, a in zip(paths, images, angles):
        stage, pitch, roll = shot_pose(p, a)
        shots.append(Shot(img, stage, pitch, roll))
    result = stitch(shots, intrinsics, args.heading_offset, [str(p) for p in paths])
    side = save_panorama(result.panorama, args.out)
    kind = "360-degree" if result.panorama.full_circle else "partial"
    print(f"{args.out}: {kind} panorama {result.panorama.width}x{result.panorama.height}, geometry in {side}")
    if result.panorama.full_circle:
        print(f"loop misclosure {result.misclosure_deg:+.3f} deg, spread over {len(shots)} seams")
    return 0
