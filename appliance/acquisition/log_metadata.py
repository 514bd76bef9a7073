"""The MCAP metadata records at the start of every session log: what produced it and with what.

=====================  ===================================================================================
record                 keys
=====================  ===================================================================================
``viper.software``     ``name``, ``version`` (``appliance.__version__``), ``python``, ``mcap``
``viper.config``       ``format`` (``json``), ``text``: the resolved configuration, every section and key
``viper.calibration``  ``camera_intrinsics`` (JSON: width, height, fx, fy, cx, cy, distortion) and, for each
                       calibration file configured (``devices.camera.intrinsics_file``,
                       ``devices.calibration_file``), its ``*_path``, ``*_sha256`` and ``*_text``; the
                       compass's hard- and soft-iron fit, the inclinometer's offsets and the sensor's sigma
                       from the configuration (JSON)
``viper.map``          ``path``, ``sha256`` (of the skyline database file), ``bytes``, ``dem_sha256`` and
                       ``dem_source`` (the DEM it was built from), when the session has a map
=====================  ===================================================================================

Every value is a string (MCAP metadata are string pairs); a file that cannot be read is recorded as
such (``*_sha256`` = ``unreadable: ...``) rather than failing the session.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import platform as host
from importlib import metadata as dist_metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from appliance import __version__
from appliance.config import Config
from appliance.logbook.messages import to_jsonable
from appliance.logbook.writer import Logbook

if TYPE_CHECKING:
    from appliance.terrain.database import SkylineDatabase
    from appliance.vision.intrinsics import CameraIntrinsics

SOFTWARE = "viper.software"
CONFIG = "viper.config"
CALIBRATION = "viper.calibration"
MAP = "viper.map"

#: file digests already computed, by (path, size, mtime): a daemon's sessions hash their map once
_DIGESTS: dict[tuple[str, int, int], str] = {}


def file_sha256(path: str | Path) -> str:
    """The sha256 (hex) of the file at ``path``, read in 1 MiB blocks; 'unreadable: ...' if it cannot be."""
    p = Path(path)
    try:
        st = p.stat()
        key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
        if key not in _DIGESTS:
            h = hashlib.sha256()
            with open(p, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    h.update(block)
            _DIGESTS[key] = h.hexdigest()
        return _DIGESTS[key]
    except OSError as exc:
        return f"unreadable: {exc.strerror or exc}"


def _json(value: Any) -> str:
    return json.dumps(to_jsonable(value), default=str, sort_keys=True)


def software_record() -> dict[str, str]:
    try:
        mcap_version = dist_metadata.version("mcap")
    except dist_metadata.PackageNotFoundError:
        mcap_version = "unknown"
    return {"name": "viper-appliance", "version": __version__, "python": host.python_version(), "mcap": mcap_version}


def config_record(config: Config) -> dict[str, str]:
    """The resolved configuration (defaults filled in) as JSON text."""
    return {"format": "json", "text": _json(dataclasses.asdict(config))}


def _file_entries(prefix: str, path: Path | None) -> dict[str, str]:
    if path is None:
        return {}
    out = {f"{prefix}_path": str(path), f"{prefix}_sha256": file_sha256(path)}
    try:
        if os.path.getsize(path) <= 1 << 16:
            out[f"{prefix}_text"] = Path(path).read_text(errors="replace")
    except OSError:
        pass
    return out


def calibration_record(config: Config, intrinsics: CameraIntrinsics | None) -> dict[str, str]:
    """The calibrations the session uses: the camera's intrinsics, the calibration files and the
    configured compass, inclinometer and sensor values."""
    d = config.devices
    out: dict[str, str] = {}
    if intrinsics is not None:
        out["camera_intrinsics"] = _json({"width": intrinsics.width, "height": intrinsics.height,
                                          "fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx,
                                          "cy": intrinsics.cy, "distortion": list(intrinsics.distortion)})
    out.update(_file_entries("intrinsics_file", d.camera.intrinsics_file))
    out.update(_file_entries("calibration_file", d.calibration_file))
    out["compass"] = _json({"hard_iron_offset": d.compass.hard_iron_offset,
                            "soft_iron_matrix": d.compass.soft_iron_matrix})
    out["inclinometer"] = _json({"pitch_offset_deg": d.inclinometer.pitch_offset_deg,
                                 "roll_offset_deg": d.inclinometer.roll_offset_deg})
    out["sensor_sigma_deg"] = _json(config.estimator.sensor_sigma_deg)
    return out


def map_record(db: SkylineDatabase) -> dict[str, str]:
    """The map: the skyline database file, its digest and the DEM it was built from."""
    out = {"path": str(db.path), "sha256": file_sha256(db.path)}
    try:
        out["bytes"] = str(os.path.getsize(db.path))
    except OSError:
        pass
    for key in ("dem_sha256", "dem_source"):
        if db.header.get(key) is not None:
            out[key] = str(db.header[key])
    return out


def write_log_metadata(log: Logbook, config: Config | None, db: SkylineDatabase | None,
                       intrinsics: CameraIntrinsics | None) -> None:
    """The metadata records of this module into ``log`` (the configuration and calibration when
    ``config`` is given, the map when ``db`` is)."""
    log.write_metadata(SOFTWARE, software_record())
    if config is not None:
        log.write_metadata(CONFIG, config_record(config))
        log.write_metadata(CALIBRATION, calibration_record(config, intrinsics))
    if db is not None:
        log.write_metadata(MAP, map_record(db))
