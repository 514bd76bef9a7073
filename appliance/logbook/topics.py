"""Topic names, schema names and the JSON schemas of the raw records a session writes.

Foxglove messages (protobuf, schema names ``foxglove.*``):

==========================  ==========================  ===========================================
topic                       schema                      content
==========================  ==========================  ===========================================
``/camera/image``           foxglove.CompressedImage    each captured frame (JPEG or PNG)
``/camera/calibration``     foxglove.CameraCalibration  the intrinsics used for the session
``/camera/panorama``        foxglove.CompressedImage    the panorama stitched from the tagged frames
``/gps/fix``                foxglove.LocationFix        every GPS fix as received
``/gps/truth``              foxglove.LocationFix        the averaged ground truth of the session
``/estimate/fix``           foxglove.LocationFix        the onboard (or replayed) estimate
``/tf``                     foxglove.FrameTransform     attitude (world->platform), stage (->camera)
``/log``                    foxglove.Log                daemon and procedure messages
``/region``                 foxglove.GeoJSON            the estimate's region (cells) and the estimate
``/estimate/posterior``     foxglove.Grid               log10 lower posterior over the database grid
==========================  ==========================  ===========================================

JSON-schema messages (schema names ``viper.*``): raw heading, tilt and stage readings, the tag of
every capture, the result of each procedure and the estimate's full record.  log_time of every
message is the acquisition time in nanoseconds since the Unix epoch (UTC).
"""

from __future__ import annotations

from typing import Any

IMAGE = "/camera/image"
PANORAMA = "/camera/panorama"
CALIBRATION = "/camera/calibration"
GPS_FIX = "/gps/fix"
GPS_TRUTH = "/gps/truth"
ESTIMATE_FIX = "/estimate/fix"
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

_NUM = {"type": ["number", "null"]}
_INT = {"type": "integer"}
_STR = {"type": "string"}


def _object(title: str, properties: dict[str, Any], required: tuple[str, ...] = ()) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "properties": properties,
        "required": list(required),
        "additionalProperties": True,
    }


JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "viper.HeadingRaw": _object(
        "Raw compass reading: heading (deg clockwise from magnetic north) and field (any unit)",
        {"heading_deg": _NUM, "mag_x": _NUM, "mag_y": _NUM, "mag_z": _NUM, "device": _STR},
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
            "black": {"type": "boolean"},
        },
        ("index", "stage_deg"),
    ),
    "viper.Procedure": _object(
        "Outcome of one procedure (level, compass, truth, capture, estimate)",
        {"procedure": _STR, "status": _STR, "reason": _STR},
        ("procedure", "status"),
    ),
    "viper.Session": _object(
        "Session description: identifier, platform, configuration", {"session_id": _STR, "platform": _STR}
    ),
    "viper.Estimate": _object(
        "The estimate's full record (appliance.position.Position.to_json) and its error against the GPS truth",
        {
            "lat": _NUM,
            "lon": _NUM,
            "heading_correction_deg": _NUM,
            "lower": _NUM,
            "upper": _NUM,
            "rms_residual_deg": _NUM,
            "valid_fraction": _NUM,
            "error_m": _NUM,
            "truth_lat": _NUM,
            "truth_lon": _NUM,
        },
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
}
