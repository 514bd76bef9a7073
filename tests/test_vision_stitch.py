"""Stitching: rotations between neighbours recovered, loop closure, bad input, and the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.cli.main import main
from appliance.errors import InputError
from appliance.skyline import read_skyline_csv
from appliance.vision.camera import CameraPose, directions_to_pixels
from appliance.vision.intrinsics import CameraIntrinsics, save_intrinsics
from appliance.vision.stitching import Shot, _strip_geometry, _WarpMaps, stitch
from appliance.vision.synth import analytic_skyline_fn, render_photo_from

K = CameraIntrinsics.from_fov(320, 240, 60.0)
FN = analytic_skyline_fn(4)


@pytest.fixture(scope="module")
def ring() -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    nominal = np.arange(12) * 30.0
    true = nominal + rng.normal(0.0, 0.5, nominal.size)
    images = [render_photo_from(FN, CameraPose(y, 0.0, 0.0), K, rng, "cloudy") for y in true]
    return images, nominal, true


def test_rotations_between_neighbours_recovered(ring: tuple[list[np.ndarray], np.ndarray, np.ndarray]) -> None:
    images, nominal, true = ring
    res = stitch([Shot(im, a) for im, a in zip(images, nominal)], K)
    true_gaps = np.diff(np.concatenate([true, [true[0] + 360.0]]))
    # 320-pixel images: 0.19 degree per pixel, so this is a fifth of a pixel
    np.testing.assert_allclose(res.seam_rotation_deg, true_gaps, atol=0.05)
    assert res.seam_rotation_deg.sum() == pytest.approx(360.0)
    assert res.panorama.full_circle
    assert abs(res.misclosure_deg) < 0.2


def test_tilted_shots_share_maps_only_when_their_tilt_is_the_same() -> None:
    # two tilts alternate: the warp maps are computed once per (pitch, roll) and reused; the
    # rotations must come out as for a level camera
    rng = np.random.default_rng(8)
    nominal = np.arange(12) * 30.0
    true = nominal + rng.normal(0.0, 0.5, nominal.size)
    tilts = [(0.8, -0.5) if i % 2 else (-0.4, 0.6) for i in range(nominal.size)]
    images = [render_photo_from(FN, CameraPose(y, p, r), K, rng, "clear") for y, (p, r) in zip(true, tilts)]
    res = stitch([Shot(im, a, p, r) for im, a, (p, r) in zip(images, nominal, tilts)], K)
    true_gaps = np.diff(np.concatenate([true, [true[0] + 360.0]]))
    np.testing.assert_allclose(res.seam_rotation_deg, true_gaps, atol=0.05)


def test_shifted_warp_maps_match_the_camera_model() -> None:
    # a strip shifted by a fraction of a column takes interpolated maps: compare with the model
    f = 300.0
    ws, h, horizon = _strip_geometry(K, f)
    maps = _WarpMaps(K, f, ws, h, horizon)
    frac = 0.37
    u, v = maps.maps(0.9, -0.6, frac)
    x = np.arange(ws, dtype=np.float64) - (ws - 1) / 2.0 - frac
    el = np.degrees(np.arctan((horizon - np.arange(h, dtype=np.float64)) / f))
    azg, elg = np.meshgrid(np.degrees(x / f), el)
    u_ref, v_ref = directions_to_pixels(K, CameraPose(0.0, 0.9, -0.6), azg, elg)
    inside = (u_ref >= 0) & (u_ref <= K.width - 1) & (v_ref >= 0) & (v_ref <= K.height - 1)
    assert inside.mean() > 0.5
    assert np.abs(u[inside] - u_ref[inside]).max() < 1e-3
    assert np.abs(v[inside] - v_ref[inside]).max() < 1e-3


def test_images_that_do_not_overlap(ring: tuple[list[np.ndarray], np.ndarray, np.ndarray]) -> None:
    images, nominal, _ = ring
    with pytest.raises(InputError, match="do not overlap"):
        stitch([Shot(images[0], 0.0), Shot(images[3], 90.0)], K)


def test_unrelated_images_are_rejected() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    b = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    with pytest.raises(InputError):
        stitch([Shot(a, 0.0), Shot(b, 30.0)], K)


def test_cli_stitch_then_skyline(tmp_path: Path, ring: tuple[list[np.ndarray], np.ndarray, np.ndarray]) -> None:
    images, nominal, true = ring
    paths = []
    for im, a in zip(images, nominal):
        p = tmp_path / f"shot_stage{a:05.1f}.png"
        cv2.imwrite(str(p), im)
        paths.append(str(p))
    cal = tmp_path / "camera.toml"
    save_intrinsics(K, cal)
    pano = tmp_path / "pano.png"
    assert main(["stitch", *paths, "--out", str(pano), "--calibration", str(cal)]) == 0
    meta = json.loads((tmp_path / "pano.png.json").read_text())
    assert meta["projection"] == "cylindrical" and meta["full_circle"] is True
    csv = tmp_path / "sky.csv"
    overlay = tmp_path / "ov.png"
    assert main(["skyline", str(pano), "--out", str(csv), "--overlay", str(overlay), "--mask", "100-110"]) == 0
    sky = read_skyline_csv(csv)
    assert cv2.imread(str(overlay)) is not None
    # the stitched azimuths keep the stage angles' mean: compare against the scene shifted alike
    offset = float(np.mean(nominal - true))
    truth, _ = FN(np.mod(sky.azimuth_deg - offset, 360.0))
    ok = sky.valid
    assert ok.mean() >= 0.7
    assert np.all(np.isnan(sky.elevation_deg[100:111]))
    assert np.sqrt(np.mean((sky.elevation_deg[ok] - truth[ok]) ** 2)) <= 0.2


def test_cli_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "x_stage0.png"
    bad.write_bytes(b"garbage")
    assert main(["stitch", str(bad), "--out", str(tmp_path / "p.png"), "--hfov-deg", "60"]) == 2
    assert "not a readable image" in capsys.readouterr().err
    flat = tmp_path / "flat.png"
    cv2.imwrite(str(flat), np.full((100, 200, 3), 90, np.uint8))
    assert main(["skyline", str(flat), "--out", str(tmp_path / "s.csv")]) == 2
    assert "no skyline found" in capsys.readouterr().err
