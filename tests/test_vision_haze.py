"""Skyline detection on the real Puy de Sancy panorama: a faint hazy horizon found, a rock left out.

The rows are hand readings of the 4096x2048 photo (../shared/data/panorama, MANIFEST section 4): between
azimuths 216 and 236 degrees the sky meets the haze over the far plain between rows 1020 and 1036 (the
red channel falls by a fifth there); the first path of the detector runs lower, along edges inside the
plain.  Between 52 and 60 degrees a rock close to the camera stands 5 degrees above the horizon.  Between
244 and 252 degrees a green hill's top (green above blue by 30 levels from there down) lies at rows 1045-1054,
below the far horizon: a line on it is below the skyline.
"""

from __future__ import annotations

import numpy as np
import pytest

from appliance.vision.panorama import load_panorama
from appliance.vision.skyline_detect import DetectionConfig, detect_columns
from tests.conftest import data_file


@pytest.fixture(scope="module")
def columns():  # type: ignore[no-untyped-def]
    pano = load_panorama(data_file("panorama/puydesancy_equirect_4096x2048.jpg"))
    return detect_columns(pano, DetectionConfig(min_elevation_deg=-30.0, max_elevation_deg=30.0))


def test_faint_hazy_horizon_is_found_on_its_row(columns) -> None:  # type: ignore[no-untyped-def]
    sel = (columns.azimuth_deg >= 216.0) & (columns.azimuth_deg < 236.0)
    rows = columns.row[sel]
    assert np.isfinite(rows).mean() >= 0.9
    found = rows[np.isfinite(rows)]
    assert found.min() >= 1020.0 and found.max() <= 1036.0


def test_rock_in_front_of_the_horizon_stays_missing(columns) -> None:  # type: ignore[no-untyped-def]
    sel = (columns.azimuth_deg >= 52.0) & (columns.azimuth_deg < 60.0)
    assert np.isfinite(columns.row[sel]).mean() <= 0.1


def test_no_line_on_the_green_hill_below_the_far_horizon(columns) -> None:  # type: ignore[no-untyped-def]
    sel = (columns.azimuth_deg >= 240.0) & (columns.azimuth_deg < 260.0)
    rows = columns.row[sel]
    found = rows[np.isfinite(rows)]
    assert found.size == 0 or (found.min() >= 1020.0 and found.max() <= 1036.0)
