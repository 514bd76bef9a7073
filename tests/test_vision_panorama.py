"""Panorama geometry, sidecar round trip and bad input."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from appliance.errors import InputError
from appliance.vision.panorama import Panorama, Projection, equirectangular, load_panorama, save_panorama


def test_equirectangular_geometry() -> None:
    img = np.zeros((100, 200, 3), np.uint8)
    p = equirectangular(img, azimuth_offset_deg=10.0)
    assert p.column_azimuth_deg(0.0) == pytest.approx(10.0 + 0.9)
    assert p.column_azimuth_deg(-0.5) == pytest.approx(10.0)
    assert p.row_elevation_deg(49.5) == pytest.approx(0.0)
    assert p.row_elevation_deg(-0.5) == pytest.approx(90.0)
    assert float(p.elevation_to_row(-45.0)) == pytest.approx(74.5)


def test_cylindrical_round_trip() -> None:
    f = 300.0
    w = int(round(2 * math.pi * f))
    p = Panorama(np.zeros((120, w, 3), np.uint8), Projection.CYLINDRICAL, w / (2 * math.pi), 350.0, 60.0, True)
    az = np.array([350.0, 0.0, 100.0, 349.9])
    np.testing.assert_allclose(p.column_azimuth_deg(p.azimuth_to_column(az)), az % 360.0, atol=1e-9)
    el = np.array([-10.0, 0.0, 5.0, 20.0])
    np.testing.assert_allclose(p.row_elevation_deg(p.elevation_to_row(el)), el, atol=1e-9)
    assert float(p.row_elevation_deg(60.0 - p.px_per_rad)) == pytest.approx(45.0)


def test_partial_panorama_outside_is_nan() -> None:
    p = Panorama(np.zeros((50, 100, 3), np.uint8), Projection.CYLINDRICAL, 100.0, 10.0, 25.0, False)
    cols = p.azimuth_to_column(np.array([10.0, 50.0, 200.0]))
    assert cols[0] == pytest.approx(0.0)
    assert np.isfinite(cols[1]) and np.isnan(cols[2])


def test_sidecar_round_trip(tmp_path: Path) -> None:
    img = np.random.default_rng(0).integers(0, 255, (40, 300, 3), dtype=np.uint8)
    p = Panorama(img, Projection.CYLINDRICAL, 60.0, 123.0, 17.5, False)
    save_panorama(p, tmp_path / "pano.png")
    q = load_panorama(tmp_path / "pano.png")
    assert q.geometry() == p.geometry()
    np.testing.assert_array_equal(q.image, img)
    shifted = load_panorama(tmp_path / "pano.png", azimuth_offset_deg=10.0)
    assert shifted.azimuth0_deg == pytest.approx(133.0)


def test_bad_inputs(tmp_path: Path) -> None:
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"not an image")
    with pytest.raises(InputError, match="not a readable image"):
        load_panorama(bad)
    with pytest.raises(InputError, match="not found"):
        load_panorama(tmp_path / "missing.png")
    square = tmp_path / "square.png"
    cv2.imwrite(str(square), np.zeros((100, 100, 3), np.uint8))
    with pytest.raises(InputError, match="360x180"):
        load_panorama(square)
    with pytest.raises(InputError, match="sidecar"):
        load_panorama(square, projection=Projection.CYLINDRICAL)


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("px_per_rad", float("nan"), "px_per_rad must be a finite number"),
        ("azimuth0_deg", "12", "azimuth0_deg must be a finite number"),
        ("horizon_row", True, "horizon_row must be a finite number"),
        ("full_circle", "false", "full_circle must be true or false"),
        ("width", [300], "width and height must be whole numbers"),
        ("height", "/etc/passwd", "width and height must be whole numbers"),
        ("width", 301, "geometry is for 301x40, image is 300x40"),
    ],
)
def test_malformed_sidecar_field_is_named(tmp_path: Path, field: str, value: object, words: str) -> None:
    import json

    img = np.random.default_rng(0).integers(0, 255, (40, 300, 3), dtype=np.uint8)
    side = save_panorama(Panorama(img, Projection.CYLINDRICAL, 60.0, 123.0, 17.5, False), tmp_path / "pano.png")
    meta = json.loads(side.read_text())
    meta[field] = value
    side.write_text(json.dumps(meta))
    with pytest.raises(InputError, match=f"{side}: .*{words}"):
        load_panorama(tmp_path / "pano.png")


def test_damaged_png_is_one_line_naming_the_decoders_complaint(tmp_path: Path) -> None:
    import subprocess
    import sys

    img = np.zeros((100, 400, 3), np.uint8)
    img[:50] = 200
    ok, buf = cv2.imencode(".png", img)
    data = bytearray(buf.tobytes())
    idat = data.index(b"IDAT") + 8  # inside the compressed pixels
    data[idat] ^= 0xFF
    (tmp_path / "bad.png").write_bytes(bytes(data))
    out = subprocess.run([sys.executable, "-m", "appliance.cli.main", "skyline", "bad.png", "--out", "sky.csv"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode != 0
    assert out.stderr.count("\n") == 1, out.stderr
    assert "bad.png: not a readable image" in out.stderr and "libpng" in out.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.png"]
