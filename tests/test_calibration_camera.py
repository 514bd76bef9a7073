"""Camera intrinsics recovered from chessboard PNGs rendered through a known camera.

Each image is rendered by ray casting: every pixel (3x3 supersampled) is undistorted with the true
plumb_bob model to a normalised ray, intersected with the board plane of the pose, and shaded by
the checker square it lands in.  The recovered model is compared with the true one.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from viper_calibration.camera import calibrate_camera

from appliance.cli.main import main
from appliance.errors import CalibrationError, InputError
from appliance.vision.intrinsics import load_intrinsics

WIDTH, HEIGHT = 640, 480
K_TRUE = np.array([[520.0, 0.0, 322.5], [0.0, 515.0, 236.0], [0.0, 0.0, 1.0]])
DIST_TRUE = np.array([-0.25, 0.08, 0.001, -0.0008, 0.0])
PATTERN = (9, 6)  # inner corners
SQUARE_M = 0.03
SUPERSAMPLE = 3

# (rotation vector rad, board-centre position in the camera frame m)
POSES = [
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.45)),
    ((0.45, -0.3, 0.05), (-0.13, -0.09, 0.45)),
    ((-0.4, 0.3, 0.0), (0.13, 0.09, 0.45)),
    ((0.4, 0.4, -0.1), (0.13, -0.09, 0.45)),
    ((-0.4, -0.4, 0.1), (-0.13, 0.09, 0.45)),
    ((-0.35, 0.0, 0.3), (0.0, 0.06, 0.45)),
    ((0.35, 0.0, -0.2), (0.0, -0.06, 0.45)),
    ((0.0, 0.6, 0.0), (-0.14, 0.0, 0.42)),
    ((0.0, -0.6, 0.4), (0.14, 0.0, 0.42)),
    ((-0.2, 0.1, 1.2), (0.0, 0.0, 0.5)),
]


def _undistorted_rays() -> np.ndarray:
    off = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
    u = (np.arange(WIDTH)[:, None] + off[None, :]).ravel()
    v = (np.arange(HEIGHT)[:, None] + off[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    pixels = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
    return cv2.undistortPoints(pixels, K_TRUE, DIST_TRUE, R=None, P=None, criteria=criteria).reshape(-1, 2)


def _render(rays: np.ndarray, rvec: tuple[float, ...], centre: tuple[float, ...], rng) -> np.ndarray:
    cols, rows = PATTERN
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
    board_centre = np.array([(cols - 1) / 2 * SQUARE_M, (rows - 1) / 2 * SQUARE_M, 0.0])
    t = np.asarray(centre) - R @ board_centre
    H = np.column_stack([R[:, 0], R[:, 1], t])  # board (X, Y, 1) -> normalised image (x, y, 1)
    homog = np.column_stack([rays, np.ones(len(rays))]) @ np.linalg.inv(H).T
    X = homog[:, 0] / homog[:, 2]
    Y = homog[:, 1] / homog[:, 2]
    sx = np.floor(X / SQUARE_M)
    sy = np.floor(Y / SQUARE_M)
    shade = np.full(len(rays), 110.0)
    on_card = (
        (X > -2 * SQUARE_M) & (X < (cols + 1) * SQUARE_M) & (Y > -2 * SQUARE_M) & (Y < (rows + 1) * SQUARE_M)
    )
    shade[on_card] = 225.0
    on_squares = (sx >= -1) & (sx <= cols - 1) & (sy >= -1) & (sy <= rows - 1)
    shade[on_squares & ((sx + sy) % 2 == 0)] = 25.0
    image = shade.reshape(HEIGHT, SUPERSAMPLE, WIDTH, SUPERSAMPLE).mean(axis=(1, 3))
    image += rng.normal(0.0, 1.5, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def board_images(tmp_path_factory) -> list[Path]:
    folder = tmp_path_factory.mktemp("boards")
    rays = _undistorted_rays()
    rng = np.random.default_rng(3)
    paths = []
    for i, (rvec, centre) in enumerate(POSES):
        path = folder / f"board_{i:02d}.png"
        assert cv2.imwrite(str(path), _render(rays, rvec, centre, rng))
        paths.append(path)
    return paths


@pytest.fixture(scope="module")
def blank_images(tmp_path_factory) -> list[Path]:
    folder = tmp_path_factory.mktemp("blank")
    rng = np.random.default_rng(4)
    paths = []
    for i in range(2):
        path = folder / f"blank_{i}.png"
        cv2.imwrite(str(path), rng.integers(90, 140, (HEIGHT, WIDTH), dtype=np.uint8))
        paths.append(path)
    return paths


def _max_model_difference_px(intrinsics) -> float:
    """Largest pixel distance between the true and the fitted model over a grid of rays."""
    u, v = np.meshgrid(np.linspace(0, WIDTH - 1, 17), np.linspace(0, HEIGHT - 1, 13))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
    rays = cv2.undistortPoints(pixels, K_TRUE, DIST_TRUE, R=None, P=None, criteria=criteria).reshape(-1, 2)
    points = np.column_stack([rays, np.ones(len(rays))])
    fitted, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), intrinsics.matrix, intrinsics.dist_coeffs)
    return float(np.max(np.linalg.norm(fitted.reshape(-1, 2) - pixels.reshape(-1, 2), axis=1)))


def test_recovers_known_intrinsics(board_images, blank_images) -> None:
    result = calibrate_camera(board_images + blank_images, PATTERN, SQUARE_M, min_boards=5)
    k = result.intrinsics
    assert len(result.used) == len(POSES)
    assert result.rejected == tuple(blank_images)
    assert (k.width, k.height) == (WIDTH, HEIGHT)
    assert k.fx == pytest.approx(K_TRUE[0, 0], rel=0.01)
    assert k.fy == pytest.approx(K_TRUE[1, 1], rel=0.01)
    assert k.cx == pytest.approx(K_TRUE[0, 2], abs=3.0)
    assert k.cy == pytest.approx(K_TRUE[1, 2], abs=3.0)
    assert k.distortion[0] == pytest.approx(DIST_TRUE[0], abs=0.03)
    assert k.distortion[2] == pytest.approx(DIST_TRUE[2], abs=0.002)
    assert k.distortion[3] == pytest.approx(DIST_TRUE[3], abs=0.002)
    assert _max_model_difference_px(k) < 2.0
    assert 0.0 < result.reprojection_error_px < 0.3
    assert max(result.per_view_error_px) < 0.5


def test_cli_writes_calibration_file(board_images, tmp_path: Path, capsys) -> None:
    out = tmp_path / "camera.toml"
    argv = ["calibrate", "camera", *map(str, board_images), "--pattern", "9x6", "--square-m", "0.03"]
    assert main([*argv, "--output", str(out), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    loaded = load_intrinsics(out)
    assert printed["boards"] == len(POSES)
    assert loaded.fx == pytest.approx(printed["fx"]) and loaded.cy == pytest.approx(printed["cy"])
    assert loaded.fx == pytest.approx(K_TRUE[0, 0], rel=0.01)
    assert loaded.reprojection_error_px == pytest.approx(printed["reprojection_error_px"])


def test_refuses_too_few_boards(board_images, blank_images, tmp_path: Path, capsys) -> None:
    with pytest.raises(CalibrationError, match=r"found in 2 of 4 image\(s\); at least 5"):
        calibrate_camera(board_images[:2] + blank_images, PATTERN, SQUARE_M, min_boards=5)
    out = tmp_path / "camera.toml"
    out.write_text("[camera]\nwidth = 1\n")
    before = out.read_bytes()
    argv = ["calibrate", "camera", *map(str, blank_images), "--output", str(out)]
    assert main(argv) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "found in 0 of 2" in err
    assert out.read_bytes() == before


def test_bad_image_inputs(board_images, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="image file not found"):
        calibrate_camera([tmp_path / "missing.png"])
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    with pytest.raises(InputError, match="not a readable image"):
        calibrate_camera([junk])
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 120), np.uint8))
    with pytest.raises(InputError, match=r"120x100 but .* is 640x480"):
        calibrate_camera([board_images[0], small])
