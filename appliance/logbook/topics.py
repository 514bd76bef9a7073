"""Topic names, schema names and the JSON schemas of the raw records a session writes.

Foxglove messages (protobuf, schema names ``foxglove.*``):

============================  ==========================  ===========================================
topic                         schema                      content
============================  ==========================  ===========================================
``/camera/image``             foxglove.CompressedImage    each captured frame (JPEG or PNG)
``/camera/calibration``       foxglove.CameraCalibration  the intrinsics used for the session
``/camera/panorama``          foxglove.CompressedImage    the panorama stitched from the tagged frames
``/camera/panorama/skyline``  foxglove.ImageAnnotations   the detected skyline drawn over the panorama
``/gps/fix``                  foxglove.LocationFix        every GPS fix as received
``/gps/truth``                foxglove.LocationFix        the averaged ground truth of the session
``/estimate/fix``             foxglove.LocationFix        the onboard (or replayed) estimate
``/estimate/pose``            foxglove.PoseInFrame        the estimate at the origin of ``world`` (a ROS 2
                                                          log: PoseWithCovarianceStamped, its covariance)
``/tf``                       foxglove.FrameTransform     attitude (world->platform), stage (->camera),
                                                          camera->camera_optical, world->skyline-grid
``/log``                      foxglove.Log                daemon and procedure messages
``/region``                   foxglove.GeoJSON            the estimate's region (cells) and the estimate;
                                                          strict properties (``GEOJSON_FEATURE_PROPERTIES``)
``/estimate/posterior``       foxglove.Grid               log10 lower posterior, frame ``skyline-grid``
``/estimate/alone/fix``       foxglove.LocationFix        a traverse's stop: the estimate from its own
                                                          skyline alone (``/estimate/fix`` is the fused)
``/traverse/track``           foxglove.GeoJSON            the track so far: LineStrings of the stops'
                                                          estimates and of their GPS truths
============================  ==========================  ===========================================

A traverse (a rover's series of stops, :mod:`appliance.acquisition.traverse`) writes every stop's
session records into one log, one after the other, and per stop ``/traverse/odometry`` (the line
received) and ``/traverse/stop`` (the stop's estimates alone and fused, their errors and statuses).
With a MAVLink autopilot, also ``/traverse/rover`` as each stop's session begins (the autopilot's heading,
roll, pitch, armed state, mode and position) and ``/traverse/position_out`` after each estimate (what
was sent back to the autopilot, or why nothing was).

JSON-schema messages (schema names ``viper.*``): raw heading, tilt and stage readings, the tag of
every capture, the result of each procedure and the estimate's full record.  Their schemas are
strict: every field a writer writes is declared and no other is allowed (``additionalProperties``
false), so a reader can rely on the names.  log_time of every message is the acquisition time in
nanoseconds since the Unix epoch (UTC).  The same messages go live to Foxglove with ``--live``
(:mod:`appliance.logbook.live`).

A log written with ``[logbook] encoding = "ros2"`` has the same topics as standard ROS 2 messages
(:mod:`appliance.logbook.ros2`: NavSatFix, CompressedImage, CameraInfo, TFMessage, rcl_interfaces Log,
foxglove_msgs for the annotations, GeoJSON and grid) and the JSON records as ``std_msgs/msg/String``
whose channel metadata ``json_schema`` names their schema.  In a traverse every stop's frames are
named ``stop-N/...`` and ``/tf`` places each stop's ``stop-N/world`` in ``map``, the traverse's one
root (local east-north-up at the first stop).
"""

from __future__ import annotations

from typing import Any

#: the channel metadata key naming the JSON schema of a ROS 2 log's ``std_msgs/msg/String`` channel
JSON_SCHEMA_KEY = "json_schema"

IMAGE = "/camera/image"
PANORAMA = "/camera/panorama"
PANORAMA_SKYLINE = "/camera/panorama/skyline"
CALIBRATION = "/camera/calibration"
GPS_FIX = "/gps/fix"
GPS_TRUTH = "/gps/truth"
ESTIMATE_FIX = "/estimate/fix"
ESTIMATE_POSE = "/estimate/pose"
TF = "/tf"
LOG = "/log"
REGION = "/region"
POSTERIOR = "/estimate/posterior"
HEADING_RAW = "/heading/raw"
TILT_RAW = "/tilt/raw"
STAGE_RAW = "/stage/raw"
CAPTURE = "/camera/capture"
PROCEDURE = "/session/procedure"
SESSION = "/session/info"
ESTIMATE_RECORD = "/estimate/record"
SKYLINE_DETECTED = "/skyline/detected"
SKYLINE_RENDERED = "/skyline/rendered"
ESTIMATE_ALONE_FIX = "/estimate/alone/fix"
TRAVERSE_TRACK = "/traverse/track"
TRAVERSE_STOP = "/traverse/stop"
ODOMETRY = "/traverse/odometry"
CLOCK = "/session/clock"
ROVER_STATE = "/traverse/rover"
POSITION_OUT = "/traverse/position_out"

_NUM = {"type": ["number", "null"]}
_INT = {"type": "integer"}
_COUNT = {"type": ["integer", "null"]}
_STR = {"type": "string"}
_OPT_STR = {"type": ["string", "null"]}
_BOOL = {"type": "boolean"}
_NUMBERS = {"type": "array", "items": {"type": ["number", "null"]}}


def _object(title: str, properties: dict[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    """A strict object schema: every field a writer may write is declared, and no other is allowed."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "properties": properties,
        "required": list(required),
        "additionalProperties": False,
    }


def _nested(properties: dict[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    return {"type": "object", "properties": properties, "required": list(required), "additionalProperties": False}


JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "viper.HeadingRaw": _object(
        "Raw compass reading: heading (deg clockwise from magnetic north), field (any unit) and the pan "
        "stage's angle (deg) when it was read",
        {"heading_deg": _NUM, "mag_x": _NUM, "mag_y": _NUM, "mag_z": _NUM, "stage_deg": _NUM, "device": _STR},
    ),
    "viper.TiltRaw": _object(
        "Raw inclinometer reading: roll and pitch in degrees", {"roll_deg": _NUM, "pitch_deg": _NUM}
    ),
    "viper.StageRaw": _object(
        "Pan stage state: commanded and reported angle in degrees", {"angle_deg": _NUM, "target_deg": _NUM}
    ),
    "viper.Capture": _object(
        "Tag of one captured frame",
        {
            "index": _INT,
            "stage_deg": _NUM,
            "heading_deg": _NUM,
            "roll_deg": _NUM,
            "pitch_deg": _NUM,
            "yaw_deg": _NUM,
            "black": _BOOL,
        },
        ("index", "stage_deg"),
    ),
    "viper.Procedure": _object(
        "Outcome of one procedure (level, compass, truth, capture, estimate) and its measured values",
        {
            "procedure": {"enum": ["level", "compass", "truth", "capture", "estimate"]},
            "status": {"enum": ["ok", "ambiguous", "degraded", "failed"]},
            "reason": _STR,
            # level
            "roll_deg": _NUM,
            "pitch_deg": _NUM,
            # compass: heading of the platform from magnetic north (deg), hard- and soft-iron fit
            "heading_magnetic_deg": _NUM,
            "hard_iron": _NUMBERS,
            "soft_iron": {"type": "array", "items": _NUMBERS},
            "residual": _NUM,
            # truth: averaged GPS position (deg), its standard error and spread (m), fixes used and rejected
            "lat": _NUM,
            "lon": _NUM,
            "sigma_m": _NUM,
            "spread_m": _NUM,
            "fix_type": _OPT_STR,
            "used": _COUNT,
            "rejected": _COUNT,
            # capture and estimate
            "frames": _COUNT,
            "region_cells": _COUNT,
        },
        ("procedure", "status"),
    ),
    "viper.Session": _object(
        "Session description: identifier, platform, configuration", {"session_id": _STR, "platform": _STR}
    ),
    "viper.Estimate": _object(
        "The estimate's full record (appliance.locating.position.Position.to_json) and its error against the GPS truth",
        {
            "skyline": _STR,
            "lat": _NUM,
            "lon": _NUM,
            "x": _NUM,
            "y": _NUM,
            "crs": _STR,
            "heading_correction_deg": _NUM,
            "lower": _NUM,
            "upper": _NUM,
            "log10_lower": _NUM,
            "region": _nested(
                {
                    "area_m2": _NUM,
                    "cell_size_m": _NUMBERS,
                    "n_cells": _INT,
                    "cells": {"type": "array", "items": _NUMBERS},
                    "cells_truncated": _BOOL,
                },
                ("area_m2", "n_cells", "cells"),
            ),
            "covariance_m2": {"type": ["array", "null"], "items": _NUMBERS},
            "radius95_m": _NUM,
            "altitude_m": _NUM,
            "independent_azimuths": _NUM,
            "ambiguous": _BOOL,
            "status": {"enum": ["ok", "ambiguous"]},
            "rms_residual_deg": _NUM,
            "valid_azimuths": _INT,
            "sigma_deg": _NUMBERS,
            "candidates": _INT,
            "elapsed_ms": _NUM,
            "notes": {"type": "array", "items": _STR},
            "truth": _nested({"lat": _NUM, "lon": _NUM, "error_m": _NUM}, ("lat", "lon")),
            "valid_fraction": _NUM,
            "error_m": _NUM,
            "truth_lat": _NUM,
            "truth_lon": _NUM,
        },
        ("lat", "lon", "lower", "upper", "region", "status"),
    ),
    "viper.Skyline": _object(
        "A skyline: elevation (deg above horizontal) per azimuth (deg clockwise from north); null=missing",
        {
            "azimuth_deg": {"type": "array", "items": {"type": "number"}},
            "elevation_deg": {"type": "array", "items": {"type": ["number", "null"]}},
        },
        ("azimuth_deg", "elevation_deg"),
    ),
}

_ESTIMATE_SUMMARY = _nested(
    {
        "lat": _NUM,
        "lon": _NUM,
        "status": {"enum": ["ok", "ambiguous"]},
        "region_cells": _INT,
        "region_area_m2": _NUM,
        "error_m": _NUM,
    },
    ("lat", "lon", "status", "region_cells", "region_area_m2", "error_m"),
)

_ODOMETRY_FIELDS = {"stop_id": _INT, "east_m": _NUM, "north_m": _NUM, "sigma_m": _NUM, "receive_time_ns": _INT,
                    "reset": _BOOL}
JSON_SCHEMAS["viper.Odometry"] = _object(
    "The rover's odometry of one stop: displacement from the previous stop (m, true east and north) "
    "and its 1-sigma per axis (m); reset: the autopilot's position frame was reset since (not fused)",
    _ODOMETRY_FIELDS, tuple(_ODOMETRY_FIELDS))
_ROVER_FIELDS = {"stop": _INT, "heading_deg": _NUM, "roll_deg": _NUM, "pitch_deg": _NUM,
                 "armed": {"type": ["boolean", "null"]}, "mode": _OPT_STR, "lat": _NUM, "lon": _NUM,
                 "time_boot_ms": _COUNT, "boots": _INT, "faults": {"type": "object",
                                                                  "additionalProperties": _INT}}
JSON_SCHEMAS["viper.RoverState"] = _object(
    "What the rover's autopilot last said as a stop's session (and its capture) began: heading (deg "
    "clockwise from true north), roll and pitch (deg), armed state, mode, its global position (deg), its time since "
    "boot (ms), "
    "the reboots seen and the link's faults so far by kind (null: not heard)", _ROVER_FIELDS, tuple(_ROVER_FIELDS))
_OUT_FIELDS = {"stop": _INT, "message": _STR, "sent": _BOOL, "reason": _STR, "fix_type": _COUNT,
               "horiz_accuracy_m": _NUM, "lat": _NUM, "lon": _NUM, "ok": _BOOL}
JSON_SCHEMAS["viper.PositionOut"] = _object(
    "A stop's estimate sent back to the autopilot (GPS_INPUT or VISION_POSITION_ESTIMATE): whether it was "
    "sent and why not, its fix type and horizontal accuracy (m, sqrt of the covariance's trace)",
    _OUT_FIELDS, tuple(_OUT_FIELDS))
JSON_SCHEMAS["viper.TraverseStop"] = _object(
    "One stop of a traverse: its estimate from its own skyline alone and fused with the previous stop's "
    "posterior moved by the odometry (the stop's position), against the GPS truth",
    {
        "stop": _INT,
        "session_id": _STR,
        "status": {"enum": ["ok", "ambiguous", "degraded", "failed"]},
        "odometry": {"anyOf": [{"type": "null"}, _nested(_ODOMETRY_FIELDS, tuple(_ODOMETRY_FIELDS))]},
        "fused": _BOOL,
        "fusion_note": _STR,
        "prior_peak": {"anyOf": [{"type": "null"}, _nested({"lat": _NUM, "lon": _NUM}, ("lat", "lon"))]},
        "alone": {"anyOf": [{"type": "null"}, _ESTIMATE_SUMMARY]},
        "position": {"anyOf": [{"type": "null"}, _ESTIMATE_SUMMARY]},
        "truth": {"anyOf": [{"type": "null"}, _nested({"lat": _NUM, "lon": _NUM}, ("lat", "lon"))]},
    },
    ("stop", "session_id", "status", "odometry", "fused", "fusion_note", "prior_peak", "alone", "position",
     "truth"),
)

JSON_SCHEMAS["viper.Clock"] = _object(
    "The system clock against the GPS time in one session: the least (receive time - GPS UTC) over the "
    "fixes with a date (s; positive: the clock is ahead), the session's limit, the fixes, and whether it "
    "was exceeded",
    {"offset_s": _NUM, "max_offset_s": _NUM, "fixes": _INT, "flagged": _BOOL},
    ("offset_s", "max_offset_s", "fixes", "flagged"),
)

JSON_TOPIC_SCHEMAS: dict[str, str] = {
    HEADING_RAW: "viper.HeadingRaw",
    TILT_RAW: "viper.TiltRaw",
    STAGE_RAW: "viper.StageRaw",
    CAPTURE: "viper.Capture",
    PROCEDURE: "viper.Procedure",
    SESSION: "viper.Session",
    ESTIMATE_RECORD: "viper.Estimate",
    SKYLINE_DETECTED: "viper.Skyline",
    SKYLINE_RENDERED: "viper.Skyline",
    ODOMETRY: "viper.Odometry",
    ROVER_STATE: "viper.RoverState",
    POSITION_OUT: "viper.PositionOut",
    TRAVERSE_STOP: "viper.TraverseStop",
    CLOCK: "viper.Clock",
}

#: The Foxglove (protobuf) schema of each topic written with ``Logbook.write_proto``: with
#: :data:`JSON_TOPIC_SCHEMAS`, every topic a session or a traverse writes, so the live view can
#: advertise them all before its first client connects (:mod:`appliance.logbook.live_channels`).
PROTO_TOPIC_SCHEMAS: dict[str, str] = {
    IMAGE: "foxglove.CompressedImage",
    PANORAMA: "foxglove.CompressedImage",
    PANORAMA_SKYLINE: "foxglove.ImageAnnotations",
    CALIBRATION: "foxglove.CameraCalibration",
    GPS_FIX: "foxglove.LocationFix",
    GPS_TRUTH: "foxglove.LocationFix",
    ESTIMATE_FIX: "foxglove.LocationFix",
    ESTIMATE_ALONE_FIX: "foxglove.LocationFix",
    ESTIMATE_POSE: "foxglove.PoseInFrame",
    TF: "foxglove.FrameTransform",
    LOG: "foxglove.Log",
    REGION: "foxglove.GeoJSON",
    TRAVERSE_TRACK: "foxglove.GeoJSON",
    POSTERIOR: "foxglove.Grid",
}

#: The GeoJSON features of ``/region`` (a foxglove.GeoJSON, so no JSON schema of its own) and of the
#: report's layers (``-region.geojson``, ``-points.geojson``): each feature's ``properties`` by its
#: ``kind``, strict like the JSON schemas above (every property declared, no other allowed).
#: How a viewer draws a feature (the simplestyle-spec's names, :mod:`appliance.outputs.styles`): a polygon's
#: outline and fill, a point's marker.
_POLYGON_STYLE = {"stroke": _STR, "stroke-width": _NUM, "stroke-opacity": _NUM, "fill": _STR, "fill-opacity": _NUM}
_MARKER_STYLE = {"marker-color": _STR, "marker-symbol": _STR, "marker-size": _STR}
GEOJSON_FEATURE_PROPERTIES: dict[str, dict[str, Any]] = {
    "region": _nested(
        {"name": _STR, "kind": {"const": "region"}, "area_m2": _NUM, "n_cells": _INT, "lower": _NUM, "upper": _NUM,
         **_POLYGON_STYLE},
        ("name", "kind", "area_m2", "n_cells", "lower", "upper"),
    ),
    "estimate": _nested(
        {"name": _STR, "kind": {"const": "estimate"}, "lower": _NUM, "upper": _NUM, "heading_correction_deg": _NUM,
         "status": _STR, "covariance_m2": {"type": ["array", "null"], "items": _NUMBERS}, "radius95_m": _NUM,
         **_MARKER_STYLE},
        ("name", "kind", "lower", "upper", "heading_correction_deg", "status"),
    ),
    "truth": _nested({"name": _STR, "kind": {"const": "truth"}, **_MARKER_STYLE}, ("name", "kind")),
    # ``/traverse/track``: one line through the stops' estimates, one through their GPS truths
    "track": _nested({"name": {"enum": ["estimates", "truth"]}, "kind": {"const": "track"}, "stops": _INT},
                     ("name", "kind", "stops")),
}

#: the geometry of each kind of feature
GEOJSON_FEATURE_GEOMETRY: dict[str, str] = {"region": "MultiPolygon", "estimate": "Point", "truth": "Point",
                                            "track": "LineString"}
