"""The weather twin's classes and the detector under weather; frames and panoramas with no skyline."""

from __future__ import annotations

import numpy as np
import pytest

from appliance.acquisition import onboard
from appliance.config import EstimatorConfig
from appliance.errors import EstimationError, InputError
from appliance.sim.weather import (
    SkyCondition,
    bank_base_deg,
    draw_weather,
    render_weather_directions,
    render_weather_panorama,
    weather_truth,
)
from appliance.vision.panorama import Panorama, Projection
from appliance.vision.skyline_detect import DetectionConfig, detect_columns, detect_skyline
from appliance.vision.synth import analytic_skyline_fn


def luminance(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(0.3 * rgb[..., 0] + 0.4 * rgb[..., 1] + 0.3 * rgb[..., 2])


def test_overcast_banks_hide_ridges_and_the_detector_never_draws_their_base():
    hidden = visible_total = found_within = below = found = 0
    for seed in (2, 3, 6, 8):
        fn = analytic_skyline_fn(seed)
        scene = draw_weather("overcast", seed, fn)
        pano, true_el, visible = render_weather_panorama(fn, scene, np.random.default_rng(seed), 1200)
        err = detect_columns(pano).elevation_deg - true_el
        ok = np.isfinite(err)
        hidden += int((~visible).sum())
        visible_total += int(visible.sum())
        found_within += int((ok & visible & (np.abs(np.nan_to_num(err, nan=9.0)) <= 0.2)).sum())
        below += int((ok & (np.nan_to_num(err) < -0.5)).sum())
        found += int(ok.sum())
    assert hidden > 0.2 * (hidden + visible_total)  # the banks hide a good part of the ridges
    assert found_within >= 0.95 * visible_total
    assert below <= 0.01 * found  # the banks' diffuse bases are left out, not taken for the skyline


def test_fresh_snow_brighter_than_the_sky_the_line_is_not_drawn_on_the_rocks_below_it():
    scores = {}
    for snow in (False, True):
        visible_total = found_within = below = found = 0
        for seed in (2, 3, 6, 8):
            fn = analytic_skyline_fn(seed)
            scene = draw_weather("snow", seed, fn)
            pano, true_el, visible = render_weather_panorama(fn, scene, np.random.default_rng(seed), 1200)
            err = detect_columns(pano, DetectionConfig(snow=snow)).elevation_deg - true_el
            ok = np.isfinite(err)
            visible_total += int(visible.sum())
            found_within += int((ok & visible & (np.abs(np.nan_to_num(err, nan=9.0)) <= 0.2)).sum())
            below += int((ok & (np.nan_to_num(err) < -0.5)).sum())
            found += int(ok.sum())
        scores[snow] = (found_within / visible_total, below / max(found, 1))
    # the brightness drop alone is at the top of the dark rocks in the snow, below the skyline
    assert scores[False][1] > 0.2
    # by colour: more than half of the skyline found, and (the target) at most 1 % below it
    assert scores[True][0] > 0.5
    assert scores[True][1] <= 0.01


def test_white_cumulus_behind_the_ridge_counts_as_sky_and_no_line_is_drawn_below_the_ridge():
    scores = {}
    for cloud in (False, True):
        visible_total = found_within = below = found = 0
        for seed in (2, 3, 6, 8):
            fn = analytic_skyline_fn(seed)
            scene = draw_weather("cumulus", seed, fn)
            pano, true_el, visible = render_weather_panorama(fn, scene, np.random.default_rng(seed), 1200)
            err = detect_columns(pano, DetectionConfig(cloud=cloud)).elevation_deg - true_el
            ok = np.isfinite(err)
            visible_total += int(visible.sum())
            found_within += int((ok & visible & (np.abs(np.nan_to_num(err, nan=9.0)) <= 0.2)).sum())
            below += int((ok & (np.nan_to_num(err) < -0.5)).sum())
            found += int(ok.sum())
        scores[cloud] = (found_within / visible_total, below / max(found, 1))
    # the learnt sky is the clear blue: a ridge with a white cloud behind it was left out
    assert scores[False][0] < 0.9
    # the targets: 90 % of the visible skyline within 0.2 deg, at most 1 % below it
    assert scores[True][0] >= 0.9
    assert scores[True][1] <= 0.01


def test_the_snow_pass_leaves_a_green_ground_alone():
    fn = analytic_skyline_fn(3)
    scene = draw_weather("cumulus", 3, fn)
    pano, _, _ = render_weather_panorama(fn, scene, np.random.default_rng(3), 1200)
    with_pass = detect_columns(pano, DetectionConfig(snow=True))
    without = detect_columns(pano, DetectionConfig(snow=False))
    assert np.isfinite(with_pass.row).mean() > 0.5
    assert np.array_equal(with_pass.row, without.row, equal_nan=True)


def test_a_bank_covers_the_ridge_where_the_truth_says_hidden():
    fn = analytic_skyline_fn(2)
    scene = draw_weather(SkyCondition.OVERCAST, 2, fn)
    az = np.arange(0.0, 360.0, 0.5)
    el, visible = weather_truth(scene, fn, az)
    assert 0 < visible.sum() < az.size
    base = bank_base_deg(scene, az, el)
    # the bank's fading base begins below every hidden skyline
    assert np.all(base[~visible] - 0.5 * scene.bank_soft_deg < el[~visible])
    # the scene's contrast across the true skyline: gone under a bank, plain where it is visible
    grid_az = np.repeat(az[None, :], 2, axis=0)
    grid_el = np.stack([el + 0.3, el - 0.3])
    rgb = render_weather_directions(grid_az, grid_el, fn, scene)
    contrast = np.abs(luminance(rgb[0]) - luminance(rgb[1]))
    assert np.median(contrast[~visible]) < 0.05 < np.median(contrast[visible])


def test_clouds_drift_between_frames_the_terrain_does_not():
    fn = analytic_skyline_fn(4)
    scene = draw_weather("cumulus", 4, fn)
    az, el = np.meshgrid(np.arange(0.0, 360.0, 0.5), np.arange(-10.0, 30.0, 0.5))
    a = render_weather_directions(az, el, fn, scene, frame_index=0)
    b = render_weather_directions(az, el, fn, scene, frame_index=1)
    sky_el, _ = fn(az[0])
    above = el > sky_el[None, :] + 0.5
    below = el < sky_el[None, :] - 0.5
    assert np.abs(a - b)[above].max() > 0.2  # a cloud has moved
    assert np.abs(a - b)[below].max() == 0.0


def test_each_class_draws_what_it_says():
    fn = analytic_skyline_fn(5)
    low = draw_weather("low_sun", 5, fn)
    ridge, _ = fn(np.array([low.sun_azimuth_deg]))
    assert 0.3 <= low.sun_elevation_deg - ridge[0] <= 4.0
    az, el = np.meshgrid(np.arange(0.0, 360.0, 1.0), np.arange(-12.0, 30.0, 0.5))
    sky_el, _ = fn(az[0])
    ground = el < sky_el[None, :] - 1.0
    sky = el > sky_el[None, :] + 1.0
    snow = render_weather_directions(az, el, fn, draw_weather("snow", 5, fn))
    assert np.median(luminance(snow)[ground]) > 0.7  # white ground
    dusk = render_weather_directions(az, el, fn, draw_weather("dusk", 5, fn))
    assert np.median(luminance(dusk)[sky]) < 0.4 and np.median(luminance(dusk)[ground]) < 0.1
    haze = draw_weather("haze", 5, fn)
    assert 6_000 <= haze.visibility_m <= 20_000


def test_haze_hides_a_skyline_far_beyond_the_visibility():
    def far(azimuth_deg):
        a = np.asarray(azimuth_deg, dtype=float)
        return np.full(a.shape, 2.0), np.where(a < 180.0, 5_000.0, 150_000.0)

    scene = draw_weather("haze", 1, far)
    _, visible = weather_truth(scene, far, np.array([10.0, 90.0, 200.0, 300.0]))
    assert visible.tolist() == [True, True, False, False]


def test_an_unknown_weather_class_is_one_line_naming_the_classes():
    with pytest.raises(InputError, match="weather class 'fog' unknown; expected one of clear, cumulus"):
        SkyCondition.parse("fog")


def panorama(image: np.ndarray) -> Panorama:
    return Panorama(image, Projection.CYLINDRICAL, image.shape[1] / (2 * np.pi), 0.0, (image.shape[0] - 1) / 2, True)


@pytest.mark.parametrize("kind", ["sky", "ground", "white", "black"])
def test_a_panorama_without_skyline_gives_no_azimuth_and_no_estimate(kind):
    rng = np.random.default_rng(1)
    h, w = 240, 1800
    if kind == "sky":
        ramp = np.linspace(1.0, 0.7, h)[:, None, None] * np.array([230, 200, 150])[None, None, :]
        image = np.broadcast_to(ramp, (h, w, 3)) + rng.normal(0, 2, (h, w, 3))
    elif kind == "ground":
        image = np.array([40, 80, 60])[None, None, :] * rng.uniform(0.5, 1.5, (h, w, 1))
    else:
        image = np.full((h, w, 3), 255 if kind == "white" else 0)
    sky = detect_skyline(panorama(np.clip(image, 0, 255).astype(np.uint8)))
    assert sky.valid.sum() == 0
    with pytest.raises(EstimationError, match="skyline has 0% valid azimuths, below"):
        onboard.locate_skyline(None, sky, EstimatorConfig())  # type: ignore[arg-type]
