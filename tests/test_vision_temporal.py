"""The capture ring's temporal cue (appliance.vision.temporal): frames read from the camera twin under
drifting cloud, stitched by their poses; the pixels the cloud moved over are marked, the terrain's are
not, also with the exposure changed between frames and a pose off by half a pixel."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from appliance.errors import InputError
from appliance.sim.camera_twin import NOMINAL_EXPOSURE, SimVideoCapture
from appliance.sim.weather import WeatherScene, draw_weather, render_weather_directions
from appliance.sim.world import SimWorld
from appliance.vision.camera import CameraPose
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama, Projection
from appliance.vision.posed_stitch import PosedImage, stitch_posed
from appliance.vision.skyline_detect import DetectionConfig, detect_columns
from appliance.vision.synth import analytic_skyline_fn
from appliance.vision.temporal import (
    MOVING_SHIFT_PX,
    cloud_below,
    frame_disagreement,
    motion_edge,
    moving_around,
    moving_pixels,
)

CAMERA = CameraIntrinsics.from_fov(640, 480, 60.0)
FN = analytic_skyline_fn(seed=3, mean_deg=2.0, amplitude_deg=2.0)
STAGES_DEG = (0.0, 40.0)


def _scene(condition: str, drift_deg: float) -> WeatherScene:
    scene = draw_weather(condition, 11, FN)
    return replace(scene, cloud_cover=0.5, drift_deg_per_frame=drift_deg)


def _ring(scene: WeatherScene, exposures: tuple[float, float] = (NOMINAL_EXPOSURE, NOMINAL_EXPOSURE),
          tag_error_deg: float = 0.0) -> Panorama:
    """Two overlapping frames read from the camera twin (its clouds drift between reads), stitched
    by their headings (the second's tag off by ``tag_error_deg``)."""
    world = SimWorld(45.0, 6.0, 1000.0)
    cam = SimVideoCapture(world, CAMERA, skyline_fn=FN, seed=5, weather=scene)
    shots = []
    for stage, exposure in zip(STAGES_DEG, exposures):
        world.stage_deg = stage
        assert cam.set(cv2.CAP_PROP_EXPOSURE, exposure)
        ok, img = cam.read()
        assert ok and img is not None
        error = tag_error_deg if stage else 0.0
        shots.append(PosedImage(img, CameraPose(world.head_heading_deg + error, 0.0, 0.0)))
    return stitch_posed(shots, CAMERA)


def _truth(pano: Panorama, scene: WeatherScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Over the panorama's pixels: the overlap of the two frames, the terrain at least 3 rows below
    the skyline, and where the twin's noiseless scene changes between the two reads by 0.05 or more
    of full scale (the drifting cloud)."""
    h, w = pano.height, pano.width
    az = pano.column_azimuth_deg(np.arange(w, dtype=np.float64))
    el = pano.row_elevation_deg(np.arange(h, dtype=np.float64))
    # the frames span +-30 deg about their axes: both see 10..30 deg, less a column at each end
    overlap_cols = (az > 11.0) & (az < 29.0)
    az_g, el_g = np.meshgrid(az[overlap_cols], el)
    first = render_weather_directions(az_g, el_g, FN, scene, 0).mean(axis=2)
    second = render_weather_directions(az_g, el_g, FN, scene, 1).mean(axis=2)
    sky_el, _ = FN(az)
    sky_row = pano.elevation_to_row(sky_el)
    terrain = np.zeros((h, w), bool)
    terrain[:, overlap_cols] = np.arange(h)[:, None] > sky_row[overlap_cols][None, :] + 3.0
    changed = np.zeros((h, w), bool)
    changed[:, overlap_cols] = np.abs(second - first) >= 0.05
    overlap = np.zeros((h, w), bool)
    overlap[:, overlap_cols] = True
    return overlap, terrain, changed


@pytest.mark.parametrize("condition", ["cumulus", "snow"])
def test_drifting_cloud_is_marked_and_terrain_is_not(condition: str) -> None:
    scene = _scene(condition, drift_deg=0.8)
    pano = _ring(scene)
    assert pano.motion is not None and pano.motion.shape == pano.image.shape[:2]
    overlap, terrain, changed = _truth(pano, scene)
    # the map covers the overlap (less the corners that one frame's top or bottom misses) and nothing else
    assert np.isfinite(pano.motion[40:-40][overlap[40:-40]]).mean() > 0.98
    az = pano.column_azimuth_deg(np.arange(pano.width, dtype=np.float64))
    assert not np.isfinite(pano.motion[:, (az < 9.5) | (az > 30.5)]).any()
    moving = moving_pixels(pano.motion)
    assert changed.sum() > 2000
    assert moving[changed].mean() > 0.5
    assert terrain.sum() > 30_000
    assert moving[terrain].mean() < 0.001


def test_exposure_change_and_a_half_pixel_tag_error_do_not_move_the_terrain() -> None:
    scene = _scene("cumulus", drift_deg=0.8)
    # the second frame 15 % darker and its heading tag off by half a pixel
    pano = _ring(scene, exposures=(NOMINAL_EXPOSURE, 0.85 * NOMINAL_EXPOSURE),
                 tag_error_deg=0.5 * math.degrees(1.0 / CAMERA.fx))
    overlap, terrain, changed = _truth(pano, scene)
    assert pano.motion is not None
    moving = moving_pixels(pano.motion)
    assert moving[terrain].mean() < 0.001
    assert np.nanmedian(pano.motion[terrain]) < 0.2 * MOVING_SHIFT_PX
    assert moving[changed].mean() > 0.5


def test_still_clouds_are_not_marked() -> None:
    scene = _scene("cumulus", drift_deg=0.0)
    pano = _ring(scene)
    overlap, _, _ = _truth(pano, scene)
    assert pano.motion is not None
    assert moving_pixels(pano.motion)[overlap].mean() < 0.001


def test_one_frame_has_no_motion_map() -> None:
    scene = _scene("snow", drift_deg=0.8)
    world = SimWorld(45.0, 6.0, 1000.0)
    ok, img = SimVideoCapture(world, CAMERA, skyline_fn=FN, seed=5, weather=scene).read()
    assert ok and img is not None
    assert stitch_posed([PosedImage(img, CameraPose(0.0, 0.0, 0.0))], CAMERA).motion is None


def test_a_motion_map_of_another_shape_is_refused() -> None:
    img = np.zeros((40, 360, 3), np.uint8)
    with pytest.raises(InputError, match="motion map"):
        Panorama(img, Projection.CYLINDRICAL, 360 / (2 * math.pi), 0.0, 19.5, True, None,
                 np.zeros((40, 359), np.float32))


def test_moving_around_a_line() -> None:
    moving = np.zeros((40, 3), bool)
    moving[10, 0] = True  # 3 rows above a line at row 13: sky above
    moving[[20, 22], 1] = True  # 2 pixels 7 and 9 rows below the line: a cloud below it
    moving[5, 2] = True  # 8 rows above: too far to vouch for the line
    above, below = moving_around(moving, np.array([13.0, 13.0, 13.0]))
    assert above.tolist() == [True, False, False]
    assert below.tolist() == [False, True, False]
    above, below = moving_around(moving, np.array([np.nan, np.nan, np.nan]))
    assert not above.any() and not below.any()



def _smooth_heap(shift_px: float, seed: int) -> np.ndarray:
    """A 120x400 luminance: a pale sky (0.8) with a smooth white heap (+0.15, Gaussian, 40 px across
    and 20 px high) centred at column 200 + ``shift_px``, and sensor noise (0.003)."""
    rr, cc = np.mgrid[0:120, 0:400].astype(np.float64)
    heap = 0.15 * np.exp(-0.5 * ((cc - 200.0 - shift_px) / 40.0) ** 2 - 0.5 * ((rr - 60.0) / 20.0) ** 2)
    noise = np.random.default_rng(seed).normal(0.0, 0.003, rr.shape)
    return (0.8 + heap + noise).astype(np.float32)


def test_a_smooth_cloud_that_drifted_reads_as_moving_and_a_still_one_does_not() -> None:
    # the heap's slope (at most 0.0023 per pixel) is far under what a shift can be measured on against
    # the noise; drifted by 10 px its flanks change by about 0.02, five times the noise
    both = np.ones((120, 400), bool)
    drifted = frame_disagreement([(_smooth_heap(0.0, 1), both), (_smooth_heap(10.0, 2), both)])
    still = frame_disagreement([(_smooth_heap(0.0, 1), both), (_smooth_heap(0.0, 2), both)])
    flanks = np.zeros((120, 400), bool)
    flanks[50:71, 155:176] = True
    flanks[50:71, 235:256] = True
    assert moving_pixels(drifted)[flanks].mean() > 0.8
    # the plain sky beside the heap, and the heap that did not drift, do not move
    assert not moving_pixels(drifted)[:, :80].any() and not moving_pixels(drifted)[:, 330:].any()
    assert moving_pixels(still).mean() < 0.001


def test_cloud_below_and_the_cloud_s_lower_edge() -> None:
    moving = np.zeros((30, 3), bool)
    moving[10:15, 0] = True  # a cloud in rows 10-14 over still ground
    moving[[20, 22], 1] = True  # two moving pixels in rows 20 and 22
    moving[25, 2] = True  # one alone
    below = cloud_below(moving)
    # at least two moving pixels 2-14 rows below: down to row 11 of column 0 (row 12 has only row 14)
    assert below[:12, 0].all() and not below[12:, 0].any()
    assert below[8:19, 1].all() and not below[:8, 1].any() and not below[19:, 1].any()
    assert not below[:, 2].any()
    edge = motion_edge(moving)
    # the first still rows under the cloud (rows 15-18: moving pixels 1-4 rows above, none 1-3 below)
    assert np.flatnonzero(edge[:, 0]).tolist() == [15, 16, 17, 18]
    # under the lone pixel at row 25 but not between the two at rows 20 and 22 (row 21: one just below)
    assert np.flatnonzero(edge[:, 2]).tolist() == [26, 27, 28, 29]
    assert np.flatnonzero(edge[:, 1]).tolist() == [23, 24, 25, 26]


def test_a_snowy_ring_with_white_cloud_behind_the_ridges_is_found_further_with_the_motion() -> None:
    # the full capture ring (nine frames 40 deg apart) over snow with drifting cumulus behind the ridges
    scene = replace(draw_weather("snow", 12, FN), cloud_cover=0.4, drift_deg_per_frame=0.8)
    world = SimWorld(45.0, 6.0, 1000.0)
    cam = SimVideoCapture(world, CAMERA, skyline_fn=FN, seed=5, weather=scene)
    shots = []
    for stage in range(0, 360, 40):
        world.stage_deg = float(stage)
        ok, img = cam.read()
        assert ok and img is not None
        shots.append(PosedImage(img, CameraPose(world.head_heading_deg, 0.0, 0.0)))
    pano = stitch_posed(shots, CAMERA)
    assert pano.motion is not None
    az = pano.column_azimuth_deg(np.arange(pano.width, dtype=np.float64))
    true_row = pano.elevation_to_row(FN(az)[0])
    with_motion = detect_columns(pano)
    without = detect_columns(replace(pano, motion=None))
    # the same image with the motion switched off in the detector is the same as without the map
    off = detect_columns(pano, DetectionConfig(motion=False))
    np.testing.assert_array_equal(off.row, without.row)
    err_with, err_without = with_motion.row - true_row, without.row - true_row
    # nothing drawn half a degree (5 rows) or more below the true skyline, with or without
    assert not (err_with > 5.0).any() and not (err_without > 5.0).any()
    # more of the skyline within 2 rows: the columns whose white cloud behind the ridge moved
    assert (np.abs(err_with) < 2.0).sum() >= (np.abs(err_without) < 2.0).sum() + 100
