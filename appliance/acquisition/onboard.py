"""The onboard estimate: tagged frames -> panorama -> skyline -> position.

Stitching uses the tags, not image features (:mod:`appliance.vision.posed_stitch`).  The position
comes from the skyline database with :func:`appliance.locating.position.locate` (the interval-valued
posterior of the paper, section 4); :mod:`appliance.outputs.records` turns it into the log's
records, for the session and for ``viper replay`` alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from appliance.acquisition.procedures import TaggedFrame
from appliance.config import EstimatorConfig, SessionConfig
from appliance.errors import EstimationError, InputError
from appliance.skyline import Skyline
from appliance.vision.camera import CameraPose
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama
from appliance.vision.posed_stitch import PosedImage, stitch_posed

if TYPE_CHECKING:
    from appliance.estimator.exact import PositionPrior
    from appliance.locating.position import Position
    from appliance.terrain.database import SkylineDatabase
    from appliance.terrain.dem import Dem


def stitch_frames(
    frames: Sequence[TaggedFrame], intrinsics: CameraIntrinsics, height_px: int | None = None
) -> Panorama:
    """A full-circle cylindrical panorama (azimuth 0 = true north at column 0) of the frames that
    have a heading, each placed by its tag (:func:`appliance.vision.posed_stitch.stitch_posed`)."""
    shots = [PosedImage(f.frame.image, CameraPose(float(f.heading_deg), float(f.pitch_deg or 0.0),
                                                  float(f.roll_deg or 0.0)))
             for f in frames if f.heading_deg is not None]
    if not shots:
        raise InputError("stitch: no frame has a heading (compass failed?); cannot place frames")
    return stitch_posed(shots, intrinsics, height_px)


def load_session_database(cfg: SessionConfig, dem: Dem | None = None) -> SkylineDatabase | None:
    """The skyline database of ``[session] database`` (checked against ``dem`` when given), or None
    when none is configured (the estimate is then skipped)."""
    # the database and the estimator (compiled kernels) load only when a session has a database
    from appliance.terrain.database import load_database

    if cfg.database is None:
        return None
    return load_database(cfg.database, dem)


def locate_skyline(db: SkylineDatabase, skyline: Skyline, cfg: EstimatorConfig, source: str = "",
                   log_prior: np.ndarray | None = None, position_prior: PositionPrior | None = None) -> Position:
    """The position of ``skyline`` in ``db`` (under ``log_prior``, per node, and ``position_prior``,
    its continuous form, when given: a traverse's transported posterior); refuses a skyline with too
    few valid azimuths."""
    from appliance.locating.position import locate  # as above: only when a session estimates

    if skyline.valid_fraction < cfg.min_valid_fraction:
        raise EstimationError(
            f"skyline has {skyline.valid_fraction:.0%} valid azimuths, below {cfg.min_valid_fraction:.0%}"
        )
    return locate(db, skyline, cfg.sigma_deg, cfg.heading_tolerance_deg, log_prior=log_prior, source=source,
                  occlusion_weight=cfg.occlusion_weight, map_sigma_m=cfg.map_vertical_sigma_m,
                  position_prior=position_prior, sigma_floor_deg=cfg.sigma_floor_deg)


def mask_stage_angles(skyline: Skyline, platform_heading_deg: float,
                      stage_ranges_deg: Sequence[tuple[float, float]]) -> Skyline:
    """The skyline with the azimuths that the platform's own body hides removed: each range is in
    stage angles (deg, from..to clockwise), placed on true azimuths by the platform's heading."""
    if not stage_ranges_deg:
        return skyline
    rel = np.mod(skyline.azimuth_deg - platform_heading_deg, 360.0)
    hidden = np.zeros(rel.shape, dtype=bool)
    for lo, hi in stage_ranges_deg:
        width = (hi - lo) % 360.0
        hidden |= np.mod(rel - lo, 360.0) <= width
    el = np.where(hidden, np.nan, skyline.elevation_deg)
    conf = None if skyline.confidence is None else np.where(hidden, 0.0, skyline.confidence)
    return Skyline(skyline.azimuth_deg, el, conf)
