"""Pure builders of the Foxglove protobuf messages a session writes (no clock, no I/O).

Frames: ``world`` is local east-north-up at the tripod; ``platform`` is the levelled base rotated
by the heading (yaw), then pitch and roll from the inclinometers; ``camera`` is the platform
rotated about its vertical axis by the stage angle, so that at rest its +x points right, +y forward
(along the optical axis) and +z up; ``camera_optical`` is the same camera in the optical convention
of images and calibrations (+x right, +y down, +z forward); ``skyline-grid`` is the skyline
database's grid (x east along the map's columns, y north along its rows, origin at the south-west
corner), placed in ``world`` by :func:`grid_transform`.  Azimuths and headings are degrees clockwise
from true north; in ENU the rotation about up is counter-clockwise, hence ``yaw = -azimuth``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.GeoJSON_pb2 import GeoJSON
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from google.protobuf.timestamp_pb2 import Timestamp

from appliance.vision.intrinsics import CameraIntrinsics

LOG_LEVELS = {
    "debug": Log.DEBUG,
    "info": Log.INFO,
    "warning": Log.WARNING,
    "error": Log.ERROR,
    "fatal": Log.FATAL,
}


def timestamp(time_ns: int) -> Timestamp:
    ts = Timestamp()
    ts.FromNanoseconds(int(time_ns))
    return ts


CAMERA_OPTICAL = "camera_optical"


def compressed_image(
    time_ns: int, data: bytes, fmt: str = "jpeg", frame_id: str = CAMERA_OPTICAL
) -> CompressedImage:
    return CompressedImage(timestamp=timestamp(time_ns), frame_id=frame_id, data=bytes(data), format=fmt)


def camera_calibration(
    time_ns: int, intrinsics: CameraIntrinsics, frame_id: str = CAMERA_OPTICAL
) -> CameraCalibration:
    k = intrinsics.matrix
    p = np.hstack([k, np.zeros((3, 1))])
    return CameraCalibration(
        timestamp=timestamp(time_ns),
        frame_id=frame_id,
        width=intrinsics.width,
        height=intrinsics.height,
        distortion_model="plumb_bob",
        D=list(intrinsics.distortion),
        K=[float(v) for v in k.ravel()],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[float(v) for v in p.ravel()],
    )


def location_fix(
    time_ns: int,
    lat_deg: float,
    lon_deg: float,
    altitude_m: float | None = None,
    sigma_m: float | None = None,
    frame_id: str = "gps",
    covariance_enu_m2: np.ndarray | None = None,
) -> LocationFix:
    """A fix; ``covariance_enu_m2`` (3 x 3, east, north, up) fills a full covariance (KNOWN), else
    ``sigma_m`` (1-sigma horizontal) a diagonal one, else it stays UNKNOWN."""
    fix = LocationFix(
        timestamp=timestamp(time_ns),
        frame_id=frame_id,
        latitude=float(lat_deg),
        longitude=float(lon_deg),
        altitude=float(altitude_m) if altitude_m is not None and math.isfinite(altitude_m) else 0.0,
    )
    if covariance_enu_m2 is not None and np.all(np.isfinite(covariance_enu_m2)):
        fix.position_covariance.extend(float(v) for v in np.asarray(covariance_enu_m2, dtype=float).ravel())
        fix.position_covariance_type = LocationFix.KNOWN
    elif sigma_m is not None and math.isfinite(sigma_m):
        var = float(sigma_m) ** 2
        fix.position_covariance.extend([var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var])
        fix.position_covariance_type = LocationFix.DIAGONAL_KNOWN
    return fix


def quaternion_from_euler_deg(yaw_deg: float, pitch_deg: float, roll_deg: float) -> tuple[float, ...]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll), angles about ENU axes in degrees."""
    cy, sy = math.cos(math.radians(yaw_deg) / 2), math.sin(math.radians(yaw_deg) / 2)
    cp, sp = math.cos(math.radians(pitch_deg) / 2), math.sin(math.radians(pitch_deg) / 2)
    cr, sr = math.cos(math.radians(roll_deg) / 2), math.sin(math.radians(roll_deg) / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def frame_transform(
    time_ns: int, parent: str, child: str, yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0
) -> FrameTransform:
    x, y, z, w = quaternion_from_euler_deg(yaw_deg, pitch_deg, roll_deg)
    tf = FrameTransform(timestamp=timestamp(time_ns), parent_frame_id=parent, child_frame_id=child)
    tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w = x, y, z, w
    return tf


def attitude_transform(time_ns: int, heading_deg: float, roll_deg: float, pitch_deg: float) -> FrameTransform:
    """world -> platform: heading (clockwise from north) and the inclinometers' roll and pitch."""
    return frame_transform(time_ns, "world", "platform", -heading_deg, pitch_deg, roll_deg)


def stage_transform(time_ns: int, stage_deg: float) -> FrameTransform:
    """platform -> camera: the pan stage's angle (clockwise seen from above)."""
    return frame_transform(time_ns, "platform", "camera", -stage_deg)


def optical_transform(time_ns: int) -> FrameTransform:
    """camera -> camera_optical: optical +z (forward) on the camera's +y, +x on +x, +y (down) on -z."""
    return frame_transform(time_ns, "camera", CAMERA_OPTICAL, 0.0, 0.0, -90.0)


def grid_transform(time_ns: int, east_m: float, north_m: float, convergence_deg: float,
                   frame_id: str = "skyline-grid") -> FrameTransform:
    """world -> ``frame_id``: the grid's origin ``east_m``/``north_m`` metres from the world's origin
    (along true east and north), its +y axis (grid north) at the true azimuth ``convergence_deg``."""
    tf = frame_transform(time_ns, "world", frame_id, -convergence_deg)
    tf.translation.x, tf.translation.y = float(east_m), float(north_m)
    return tf


def map_transform(time_ns: int, east_m: float, north_m: float, up_m: float = 0.0) -> FrameTransform:
    """map -> world: a stop's ``world`` (east-north-up at its tripod) ``east_m``/``north_m``/``up_m`` from
    the origin of a traverse's ``map`` (east-north-up at its first stop), axes parallel."""
    tf = frame_transform(time_ns, MAP, "world", 0.0)
    tf.translation.x, tf.translation.y, tf.translation.z = float(east_m), float(north_m), float(up_m)
    return tf


def skyline_annotations(time_ns: int, columns: np.ndarray, rows: np.ndarray,
                        rgba: tuple[float, float, float, float] = (0.0, 1.0, 1.0, 1.0)) -> ImageAnnotations:
    """The skyline drawn over an image: one line strip per run of valid points (pixel ``columns`` and
    ``rows``, NaN = none); a run also ends where the columns jump back (a panorama's seam)."""
    cols = np.asarray(columns, float)
    rws = np.asarray(rows, float)
    valid = np.isfinite(cols) & np.isfinite(rws)
    breaks = np.flatnonzero(~valid | np.concatenate([[False], np.diff(cols) < 0]))
    out = ImageAnnotations()
    start = 0
    for stop in [*breaks.tolist(), cols.size]:
        run = np.arange(start, stop)
        run = run[valid[run]]
        if run.size >= 2:
            line = out.points.add(timestamp=timestamp(time_ns), type=PointsAnnotation.LINE_STRIP, thickness=2.0)
            line.outline_color.r, line.outline_color.g, line.outline_color.b, line.outline_color.a = rgba
            for i in run:
                line.points.add(x=float(cols[i]), y=float(rws[i]))
        start = stop
    return out


def pose_in_frame(time_ns: int, frame_id: str, position_m: Sequence[float]) -> PoseInFrame:
    """A position (x, y, z in metres) in ``frame_id`` with no rotation."""
    pose = PoseInFrame(timestamp=timestamp(time_ns), frame_id=frame_id)
    pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = (float(v) for v in position_m)
    pose.pose.orientation.w = 1.0
    return pose


#: the frames of one session's transform tree (``map`` is a traverse's root, above them)
SESSION_FRAMES = frozenset({"world", "platform", "camera", CAMERA_OPTICAL, "skyline-grid"})
MAP = "map"


def with_frame_prefix(message: Any, prefix: str) -> Any:
    """``message`` with each of its frames of :data:`SESSION_FRAMES` named ``prefix + frame`` (a copy;
    ``message`` itself unchanged): a traverse's stops each keep their own tree under ``map``."""
    fields = [f for f in ("frame_id", "parent_frame_id", "child_frame_id")
              if f in type(message).DESCRIPTOR.fields_by_name and getattr(message, f) in SESSION_FRAMES]
    if not prefix or not fields:
        return message
    copy = type(message)()
    copy.CopyFrom(message)
    for f in fields:
        setattr(copy, f, prefix + getattr(message, f))
    return copy


def log_message(time_ns: int, level: str, text: str, name: str = "viper") -> Log:
    return Log(timestamp=timestamp(time_ns), level=LOG_LEVELS[level], message=text, name=name)


def geojson(features: Sequence[dict[str, Any]]) -> GeoJSON:
    return GeoJSON(geojson=json.dumps({"type": "FeatureCollection", "features": list(features)}))


def polygon_feature(lonlat_ring: Sequence[tuple[float, float]], name: str) -> dict[str, Any]:
    ring = [[float(lon), float(lat)] for lon, lat in lonlat_ring]
    if ring and ring[0] != ring[-1]:
        ring.append(ring[0])
    return {
        "type": "Feature",
        "properties": {"name": name},
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }


def point_feature(lon: float, lat: float, name: str) -> dict[str, Any]:
    return {
        "type": "Feature",
        "properties": {"name": name},
        "geometry": {"type": "Point", "coordinates": [lon, lat]},
    }


def grid(
    time_ns: int,
    values: np.ndarray,
    cell_size_m: tuple[float, float],
    origin_xy_m: tuple[float, float],
    frame_id: str = "map",
    field_name: str = "probability",
) -> Grid:
    """A float32 grid; row 0 at ``origin_xy_m`` (the lowest y), columns along +x."""
    arr = np.ascontiguousarray(np.asarray(values, dtype="<f4"))
    if arr.ndim != 2:
        raise ValueError(f"grid: expected a 2-D array, got shape {arr.shape}")
    cols = arr.shape[1]
    g = Grid(
        timestamp=timestamp(time_ns), frame_id=frame_id, column_count=cols, cell_stride=4, row_stride=4 * cols
    )
    g.cell_size.x, g.cell_size.y = float(cell_size_m[0]), float(cell_size_m[1])
    g.pose.position.x, g.pose.position.y = float(origin_xy_m[0]), float(origin_xy_m[1])
    g.pose.orientation.w = 1.0
    g.fields.append(PackedElementField(name=field_name, offset=0, type=PackedElementField.FLOAT32))
    g.data = arr.tobytes()
    return g


def grid_values(g: Grid) -> np.ndarray:
    """Inverse of :func:`grid` for a single-float32-field grid."""
    arr = np.frombuffer(g.data, dtype="<f4")
    return arr.reshape(-1, g.column_count)


def to_jsonable(value: Any) -> Any:
    """Plain JSON values: numpy arrays and scalars to lists and numbers, NaN and inf to null."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f if math.isfinite(f) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if hasattr(value, "value") and hasattr(value, "name") and not isinstance(value, (str, int)):
        return to_jsonable(value.value)
    return value
