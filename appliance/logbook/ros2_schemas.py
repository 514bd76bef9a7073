"""The ROS 2 message definitions (``ros2msg``) a log written with ``encoding = "ros2"`` declares.

Each definition is the ``.msg`` text of its package (``sensor_msgs``, ``geometry_msgs``, ``tf2_msgs``,
``std_msgs``, ``rcl_interfaces``, ``builtin_interfaces`` and Foxglove's ``foxglove_msgs``), with every
field type fully qualified.  :func:`schema_text` joins a type's definition and those it uses, in the
concatenated form rosbag2 stores in an MCAP schema record (each dependency after a line of 80 ``=`` and
``MSG: pkg/Name``), which ``mcap_ros2``, ``rosbags`` and Foxglove all read.
"""

from __future__ import annotations

import re

_TIME = "builtin_interfaces/Time"

#: the definitions by full name (``pkg/msg/Name``); field types as ``pkg/Name``
DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": f"{_TIME} stamp\nstring frame_id\n",
    "std_msgs/msg/String": "string data\n",
    "sensor_msgs/msg/NavSatStatus": (
        "int8 STATUS_NO_FIX=-1\nint8 STATUS_FIX=0\nint8 STATUS_SBAS_FIX=1\nint8 STATUS_GBAS_FIX=2\n"
        "int8 status\n"
        "uint16 SERVICE_GPS=1\nuint16 SERVICE_GLONASS=2\nuint16 SERVICE_COMPASS=4\nuint16 SERVICE_GALILEO=8\n"
        "uint16 service\n"
    ),
    "sensor_msgs/msg/NavSatFix": (
        "std_msgs/Header header\nsensor_msgs/NavSatStatus status\n"
        "float64 latitude\nfloat64 longitude\nfloat64 altitude\n"
        "float64[9] position_covariance\n"
        "uint8 COVARIANCE_TYPE_UNKNOWN=0\nuint8 COVARIANCE_TYPE_APPROXIMATED=1\n"
        "uint8 COVARIANCE_TYPE_DIAGONAL_KNOWN=2\nuint8 COVARIANCE_TYPE_KNOWN=3\n"
        "uint8 position_covariance_type\n"
    ),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/msg/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/msg/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n"
        "float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
        "sensor_msgs/RegionOfInterest roi\n"
    ),
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n",
    "geometry_msgs/msg/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    "geometry_msgs/msg/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose\n",
    "geometry_msgs/msg/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
    ),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "rcl_interfaces/msg/Log": (
        "byte DEBUG=10\nbyte INFO=20\nbyte WARN=30\nbyte ERROR=40\nbyte FATAL=50\n"
        f"{_TIME} stamp\nuint8 level\nstring name\nstring msg\nstring file\nstring function\nuint32 line\n"
    ),
    "foxglove_msgs/msg/Color": "float64 r\nfloat64 g\nfloat64 b\nfloat64 a\n",
    "foxglove_msgs/msg/Point2": "float64 x\nfloat64 y\n",
    "foxglove_msgs/msg/Vector2": "float64 x\nfloat64 y\n",
    "foxglove_msgs/msg/PointsAnnotation": (
        f"{_TIME} timestamp\n"
        "uint8 UNKNOWN=0\nuint8 POINTS=1\nuint8 LINE_LOOP=2\nuint8 LINE_STRIP=3\nuint8 LINE_LIST=4\n"
        "uint8 type\nfoxglove_msgs/Point2[] points\nfoxglove_msgs/Color outline_color\n"
        "foxglove_msgs/Color[] outline_colors\nfoxglove_msgs/Color fill_color\nfloat64 thickness\n"
    ),
    "foxglove_msgs/msg/CircleAnnotation": (
        f"{_TIME} timestamp\nfoxglove_msgs/Point2 position\nfloat64 diameter\nfloat64 thickness\n"
        "foxglove_msgs/Color fill_color\nfoxglove_msgs/Color outline_color\n"
    ),
    "foxglove_msgs/msg/TextAnnotation": (
        f"{_TIME} timestamp\nfoxglove_msgs/Point2 position\nstring text\nfloat64 font_size\n"
        "foxglove_msgs/Color text_color\nfoxglove_msgs/Color background_color\n"
    ),
    "foxglove_msgs/msg/ImageAnnotations": (
        "foxglove_msgs/CircleAnnotation[] circles\nfoxglove_msgs/PointsAnnotation[] points\n"
        "foxglove_msgs/TextAnnotation[] texts\n"
    ),
    "foxglove_msgs/msg/GeoJSON": "string geojson\n",
    "foxglove_msgs/msg/PackedElementField": (
        "uint8 UNKNOWN=0\nuint8 UINT8=1\nuint8 INT8=2\nuint8 UINT16=3\nuint8 INT16=4\nuint8 UINT32=5\n"
        "uint8 INT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
        "string name\nuint32 offset\nuint8 type\n"
    ),
    "foxglove_msgs/msg/Grid": (
        f"{_TIME} timestamp\nstring frame_id\ngeometry_msgs/Pose pose\nuint32 column_count\n"
        "foxglove_msgs/Vector2 cell_size\nuint32 row_stride\nuint32 cell_stride\n"
        "foxglove_msgs/PackedElementField[] fields\nuint8[] data\n"
    ),
}

_SEPARATOR = "=" * 80
_TYPE = re.compile(r"^([A-Za-z0-9_]+/[A-Za-z0-9_]+)(\[\d*\])?\s+\w+\s*$")


def _full(short: str) -> str:
    """``pkg/Name`` -> ``pkg/msg/Name``."""
    pkg, name = short.split("/")
    return f"{pkg}/msg/{name}"


def dependencies(name: str) -> list[str]:
    """The types ``name`` uses, directly or not, each once, in the order of first use (``pkg/msg/Name``)."""
    seen: list[str] = []
    todo = [name]
    while todo:
        current = todo.pop(0)
        for line in DEFINITIONS[current].splitlines():
            match = _TYPE.match(line)
            if match is None:
                continue
            dep = _full(match.group(1))
            if dep != name and dep not in seen:
                seen.append(dep)
                todo.append(dep)
    return seen


def schema_text(name: str) -> str:
    """The ``ros2msg`` schema of ``name`` (``pkg/msg/Name``): its definition, then each dependency's."""
    parts = [DEFINITIONS[name]]
    for dep in dependencies(name):
        pkg, _, short = dep.split("/")
        parts.append(f"{_SEPARATOR}\nMSG: {pkg}/{short}\n{DEFINITIONS[dep]}")
    return "".join(parts)
