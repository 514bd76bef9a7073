"""The log's Foxglove messages as ROS 2 messages (CDR), for logs written with ``encoding = "ros2"``.

:func:`to_ros2` maps each Foxglove protobuf message a session writes to its standard ROS 2 message,
field by field (nothing is dropped but what the ROS 2 message has no field for):

==========================  ======================================================================
Foxglove (protobuf)         ROS 2
==========================  ======================================================================
foxglove.LocationFix        sensor_msgs/msg/NavSatFix (covariance and its type as given)
foxglove.CompressedImage    sensor_msgs/msg/CompressedImage
foxglove.CameraCalibration  sensor_msgs/msg/CameraInfo
foxglove.FrameTransform     tf2_msgs/msg/TFMessage (one transform)
foxglove.Log                rcl_interfaces/msg/Log (levels 10..50)
foxglove.ImageAnnotations   foxglove_msgs/msg/ImageAnnotations
foxglove.GeoJSON            foxglove_msgs/msg/GeoJSON
foxglove.Grid               foxglove_msgs/msg/Grid
==========================  ======================================================================

The JSON records (``viper.*``) go as ``std_msgs/msg/String`` holding the JSON text, so every channel
of such a log is a ROS 2 one; :func:`pose_with_covariance` makes the estimate's
``geometry_msgs/msg/PoseWithCovarianceStamped``.  :class:`Ros2Encoder` serialises them with
``mcap_ros2`` (the CDR encoder of ``mcap_ros2.writer``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from appliance.errors import LogError
from appliance.extras import require
from appliance.logbook.ros2_schemas import schema_text

SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
STRING = "std_msgs/msg/String"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
#: foxglove.Log's levels (1..5) as rcl_interfaces/msg/Log's (10..50)
_LOG_LEVELS = {0: 0, 1: 10, 2: 20, 3: 30, 4: 40, 5: 50}


def _time(ts: Any) -> dict[str, int]:
    return {"sec": int(ts.seconds), "nanosec": int(ts.nanos)}


def _header(ts: Any, frame_id: str) -> dict[str, Any]:
    return {"stamp": _time(ts), "frame_id": frame_id}


def _nav_sat_fix(m: Any) -> dict[str, Any]:
    cov = list(m.position_covariance) or [0.0] * 9
    return {"header": _header(m.timestamp, m.frame_id), "status": {"status": 0, "service": 1},
            "latitude": m.latitude, "longitude": m.longitude, "altitude": m.altitude,
            "position_covariance": cov, "position_covariance_type": int(m.position_covariance_type)}


def _compressed_image(m: Any) -> dict[str, Any]:
    return {"header": _header(m.timestamp, m.frame_id), "format": m.format, "data": bytes(m.data)}


def _camera_info(m: Any) -> dict[str, Any]:
    return {"header": _header(m.timestamp, m.frame_id), "height": m.height, "width": m.width,
            "distortion_model": m.distortion_model, "d": list(m.D), "k": list(m.K), "r": list(m.R),
            "p": list(m.P), "binning_x": 0, "binning_y": 0,
            "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False}}


def _tf_message(m: Any) -> dict[str, Any]:
    t, r = m.translation, m.rotation
    return {"transforms": [{
        "header": _header(m.timestamp, m.parent_frame_id), "child_frame_id": m.child_frame_id,
        "transform": {"translation": {"x": t.x, "y": t.y, "z": t.z},
                      "rotation": {"x": r.x, "y": r.y, "z": r.z, "w": r.w}}}]}


def _log(m: Any) -> dict[str, Any]:
    return {"stamp": _time(m.timestamp), "level": _LOG_LEVELS.get(int(m.level), 0), "name": m.name,
            "msg": m.message, "file": m.file, "function": "", "line": int(m.line)}


def _color(c: Any) -> dict[str, float]:
    return {"r": c.r, "g": c.g, "b": c.b, "a": c.a}


def _point2(p: Any) -> dict[str, float]:
    return {"x": p.x, "y": p.y}


def _image_annotations(m: Any) -> dict[str, Any]:
    return {
        "circles": [{"timestamp": _time(c.timestamp), "position": _point2(c.position), "diameter": c.diameter,
                     "thickness": c.thickness, "fill_color": _color(c.fill_color),
                     "outline_color": _color(c.outline_color)} for c in m.circles],
        "points": [{"timestamp": _time(p.timestamp), "type": int(p.type), "points": [_point2(q) for q in p.points],
                    "outline_color": _color(p.outline_color), "outline_colors": [_color(c) for c in p.outline_colors],
                    "fill_color": _color(p.fill_color), "thickness": p.thickness} for p in m.points],
        "texts": [{"timestamp": _time(t.timestamp), "position": _point2(t.position), "text": t.text,
                   "font_size": t.font_size, "text_color": _color(t.text_color),
                   "background_color": _color(t.background_color)} for t in m.texts],
    }


def _grid(m: Any) -> dict[str, Any]:
    p, o = m.pose.position, m.pose.orientation
    return {"timestamp": _time(m.timestamp), "frame_id": m.frame_id,
            "pose": {"position": {"x": p.x, "y": p.y, "z": p.z}, "orientation": {"x": o.x, "y": o.y, "z": o.z,
                                                                                "w": o.w}},
            "column_count": m.column_count, "cell_size": {"x": m.cell_size.x, "y": m.cell_size.y},
            "row_stride": m.row_stride, "cell_stride": m.cell_stride,
            "fields": [{"name": f.name, "offset": f.offset, "type": int(f.type)} for f in m.fields],
            "data": bytes(m.data)}


def _geojson(m: Any) -> dict[str, Any]:
    return {"geojson": m.geojson}


#: the ROS 2 type and field mapping of each Foxglove schema
CONVERSIONS: dict[str, tuple[str, Callable[[Any], dict[str, Any]]]] = {
    "foxglove.LocationFix": ("sensor_msgs/msg/NavSatFix", _nav_sat_fix),
    "foxglove.CompressedImage": ("sensor_msgs/msg/CompressedImage", _compressed_image),
    "foxglove.CameraCalibration": ("sensor_msgs/msg/CameraInfo", _camera_info),
    "foxglove.FrameTransform": ("tf2_msgs/msg/TFMessage", _tf_message),
    "foxglove.Log": ("rcl_interfaces/msg/Log", _log),
    "foxglove.ImageAnnotations": ("foxglove_msgs/msg/ImageAnnotations", _image_annotations),
    "foxglove.GeoJSON": ("foxglove_msgs/msg/GeoJSON", _geojson),
    "foxglove.Grid": ("foxglove_msgs/msg/Grid", _grid),
}


def to_ros2(message: Any) -> tuple[str, dict[str, Any]]:
    """The ROS 2 type name and field values of a Foxglove protobuf ``message``."""
    name = type(message).DESCRIPTOR.full_name
    known = CONVERSIONS.get(name)
    if known is None:
        raise LogError(f"no ROS 2 message for {name} (known: {', '.join(sorted(CONVERSIONS))})")
    ros_type, convert = known
    return ros_type, convert(message)


def pose_with_covariance(time_ns: int, frame_id: str, position_m: Sequence[float],
                         covariance_m2: Sequence[Sequence[float]] | None) -> dict[str, Any]:
    """A ``geometry_msgs/msg/PoseWithCovarianceStamped``: ``position_m`` (x, y, z) in ``frame_id``, no
    rotation; its 6 x 6 covariance holds ``covariance_m2`` (3 x 3, metres squared) for x, y, z, and the
    rotation's variances are -1 (unknown), as ROS 2 marks a part of a pose it does not give."""
    cov = [0.0] * 36
    if covariance_m2 is not None:
        for i in range(3):
            for j in range(3):
                cov[6 * i + j] = float(covariance_m2[i][j])
    for i in range(3, 6):
        cov[7 * i] = -1.0
    sec, nanosec = divmod(int(time_ns), 1_000_000_000)
    x, y, z = (float(v) for v in position_m)
    return {"header": {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame_id},
            "pose": {"pose": {"position": {"x": x, "y": y, "z": z},
                              "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                     "covariance": cov}}


class Ros2Encoder:
    """CDR encoders of the ROS 2 types, made once per type from :func:`schema_text`."""

    def __init__(self) -> None:
        # mcap-ros2-support is optional (the rover extra): loaded only for a ROS 2 log
        self._writer_module = require("mcap_ros2.writer", "a ROS 2-encoded log (logbook encoding \"ros2\")")
        self._encoders: dict[str, Callable[[Any], bytes]] = {}

    def schema(self, ros_type: str) -> bytes:
        """The ``ros2msg`` schema data of ``ros_type``."""
        return schema_text(ros_type).encode()

    def encode(self, ros_type: str, fields: dict[str, Any]) -> bytes:
        enc = self._encoders.get(ros_type)
        if enc is None:
            made = self._writer_module.serialize_dynamic(ros_type, schema_text(ros_type))
            enc = self._encoders[ros_type] = made[ros_type]
        return bytes(enc(fields))
