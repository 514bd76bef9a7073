"""Far ground under haze and short gaps in a line: appliance.vision.skyline_edges.haze_reversal and
hazy_ground, appliance.vision.skyline_detect._join_gaps, on synthetic columns and a synthetic ridge.

The colours of the hazy columns are read off a far plain under haze in a real summit panorama (the
Puy de Sancy photo, azimuth 205 deg, 11.4 rows per degree): the sky whitens towards the horizon (blue
minus red 48 levels 6.5 degrees up, 13 just above the horizon), the plain below it is darker and
bluer (blue minus red 33 just below the horizon, 71 at -2.8 degrees): its colour is that of the sky
about four degrees up.
"""

from __future__ import annotations

import numpy as np

from appliance.vision.skyline_detect import DetectionConfig, _join_gaps, detect_rows
from appliance.vision.skyline_edges import blue_minus_red, haze_reversal, hazy_ground
from appliance.vision.skyline_pixels import intensity

SKY_HIGH = (241.0, 218.0, 194.0)  # BGR, the sky 6.5 degrees above the horizon
SKY_HORIZON = (238.0, 231.0, 225.0)  # the sky whitened just above the horizon
PLAIN_FAR = (233.0, 216.0, 200.0)  # the far plain through haze, just below the horizon
PLAIN_NEAR = (204.0, 165.0, 133.0)  # the plain 2.8 degrees lower, nearer and less hazy
CLOUD = (240.0, 238.0, 236.0)
HORIZON = 74


def ramp(top: tuple[float, float, float], bottom: tuple[float, float, float], rows: int) -> np.ndarray:
    """``rows`` rows of colour going linearly from ``top`` to ``bottom`` (float BGR, rows x 3)."""
    t = np.linspace(0.0, 1.0, rows)[:, None]
    return np.asarray(top) + (np.asarray(bottom) - np.asarray(top)) * t


def image(*ramps: np.ndarray, width: int = 8) -> np.ndarray:
    col = np.concatenate(ramps)
    return np.repeat(np.round(col)[:, None, :], width, axis=1).astype(np.uint8)


def lum_chroma(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return intensity(img), blue_minus_red(img, 1.5)


def hazy_plain() -> np.ndarray:
    sky = ramp(SKY_HIGH, SKY_HORIZON, HORIZON)
    return image(sky, ramp(PLAIN_FAR, PLAIN_NEAR, 32), ramp(PLAIN_NEAR, PLAIN_NEAR, 30))


def test_far_plain_under_haze_below_the_whitened_sky_is_ground() -> None:
    lum, chroma = lum_chroma(hazy_plain())
    w = lum.shape[1]
    assert np.all(hazy_ground(lum, chroma, np.full(w, HORIZON)) >= 0.9)
    # a line inside the sky has more sky below it, brighter and whiter, not ground
    assert np.all(hazy_ground(lum, chroma, np.full(w, HORIZON - 25)) == 0.0)


def test_sky_below_a_cloud_base_brightens_towards_the_horizon_and_is_not_hazy_ground() -> None:
    # white cloud over blue sky: below its base the pixels are darker and bluer, as under haze, but
    # the sky goes on whitening down to the horizon instead of darkening as ground nears
    img = image(ramp(CLOUD, CLOUD, 30), ramp(SKY_HIGH, SKY_HORIZON, 50), ramp(PLAIN_NEAR, PLAIN_NEAR, 40))
    # (the cloud's base is 30 rows above the ground here; the sky below it whitens over 50 rows)
    lum, chroma = lum_chroma(img)
    assert np.all(hazy_ground(lum, chroma, np.full(lum.shape[1], 30)) == 0.0)


def test_the_reversal_marks_the_hazy_plain_not_the_sky_above_it() -> None:
    lum, chroma = lum_chroma(hazy_plain())
    rev = haze_reversal(lum, chroma, 12, 24)
    assert np.all(rev[: HORIZON - 2] == 0.0)
    # the plain's first rows, whose colour is the sky's a few degrees up, under the whitened sky
    assert np.all(rev[HORIZON + 2 : HORIZON + 12] >= 0.9)


def test_an_image_shorter_than_the_reach_has_no_reversal() -> None:
    lum, chroma = lum_chroma(hazy_plain()[:20])
    assert not haze_reversal(lum, chroma, 12, 24).any()


def gap_case(gap: slice, *, edge_at_gap: float = 0.1, step_at: int | None = None, sky_below: bool = False):  # type: ignore[no-untyped-def]
    """A line along row 30 over 40 columns (sky above it, ground below, an edge of 0.1 on it), its
    confidence 1 except in ``gap``; returns what _join_gaps makes of the gap's confidence."""
    h, w = 60, 40
    rows = np.full(w, 30.0)
    if step_at is not None:
        rows[step_at:] = 35.0
    cols = np.arange(w)
    rr = np.arange(h)[:, None]
    llr = np.where(rr < rows[None, :], 1.0, -1.0).astype(np.float32)
    edge = np.zeros((h, w), np.float32)
    edge[rows.astype(int), cols] = 0.1
    edge[rows[gap].astype(int), cols[gap]] = edge_at_gap
    if sky_below:
        llr[:, gap] = 1.0
    conf = np.ones(w)
    conf[gap] = 0.2
    out = _join_gaps(rows, conf, edge, llr, DetectionConfig(), np.zeros(w, bool), wrap=False)
    return out[gap]


def test_a_short_gap_on_a_continuous_line_is_joined() -> None:
    assert np.all(gap_case(slice(18, 21)) == 0.5)


def test_a_long_gap_a_weak_edge_sky_below_or_a_step_nearby_is_not_joined() -> None:
    assert np.all(gap_case(slice(18, 24)) == 0.2)  # six columns: room for an occluder
    assert np.all(gap_case(slice(18, 21), edge_at_gap=0.03) == 0.2)
    assert np.all(gap_case(slice(18, 21), sky_below=True) == 0.2)
    # the line steps by 5 rows two columns after the gap: two lines meet there, not one edge
    assert np.all(gap_case(slice(18, 21), step_at=23) == 0.2)


def test_a_wisp_just_above_a_ridge_leaves_no_hole_in_its_line() -> None:
    # a ridge under clear sky; a grey wisp of cloud 2-7 rows above it over four columns spoils the
    # sky above the line there: the line goes on along the ridge
    rng = np.random.default_rng(1)
    h, w = 160, 400
    rr = np.arange(h, dtype=np.float64)[:, None]
    cols = np.arange(w)
    ridge = 80 + 6 * np.sin(cols / 29.0)
    sky = ramp((230.0, 180.0, 135.0), (240.0, 225.0, 210.0), 81)[np.minimum(rr[:, 0].astype(int), 80)]
    img = np.repeat(sky[:, None, :], w, axis=1)
    ground = rr >= ridge[None, :]
    img[ground] = (55.0, 100.0, 75.0)
    img += rng.normal(0, 1.0, img.shape)
    img[ground] += rng.normal(0, 8.0, (int(ground.sum()), 1))
    for c in range(200, 204):
        r = int(ridge[c])
        img[r - 7 : r - 2, c] = (120.0, 118.0, 116.0)
    rows, _ = detect_rows(np.clip(img, 0, 255).astype(np.uint8), DetectionConfig(), wrap=False)
    near = slice(195, 210)
    assert np.all(np.abs(rows[near] - ridge[near]) <= 0.5)
