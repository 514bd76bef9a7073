"""Photo-like synthetic images and panoramas whose true skyline is known.

The scene is a function of direction (azimuth, elevation in degrees) only: a sky gradient, the sun
with its glow, clouds, textured terrain below the skyline, haze growing with the distance of the
terrain (the renderer's ``distance_m``), then sensor noise and JPEG compression.  Clouds and terrain
texture are fixed in the world (seeded by ``scene_seed``), so overlapping photos taken from one spot
agree, as real ones do; ``rng`` draws only the sensor noise.

Images are HxWx3 uint8 BGR, as OpenCV reads them.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from appliance.errors import InputError, enum_member
from appliance.skyline import Skyline
from appliance.terrain.horizon import render_skyline
from appliance.vision.camera import CameraPose, pixels_to_directions
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama, Projection, full_circle_width

#: Maps azimuths (degrees, 1-D) to (skyline elevation in degrees, distance of the skyline in metres);
#: NaN where there is no terrain.
SkylineFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]

MAX_SKYLINE_SAMPLES = 7200
JPEG_QUALITY = 85
SENSOR_NOISE_SIGMA = 0.01  # fraction of full scale

_SKY_ZENITH = np.array([0.25, 0.45, 0.85])  # RGB
_SKY_HORIZON = np.array([0.72, 0.80, 0.90])
_TERRAIN_GREEN = np.array([0.20, 0.30, 0.14])
_TERRAIN_BROWN = np.array([0.36, 0.30, 0.22])


class Weather(enum.Enum):
    CLEAR = "clear"
    CLOUDY = "cloudy"  # broken clouds, down to the skyline
    HAZY = "hazy"  # visibility of about 12 km
    MIXED = "mixed"  # clouds and haze

    @classmethod
    def parse(cls, name: str | Weather) -> Weather:
        return enum_member(cls, name, "weather")

    @property
    def clouds(self) -> bool:
        return self in (Weather.CLOUDY, Weather.MIXED)

    @property
    def visibility_m(self) -> float:
        return 12_000.0 if self in (Weather.HAZY, Weather.MIXED) else 80_000.0


# ----------------------------------------------------------------------------- procedural noise


def _hash01(i: np.ndarray, j: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer lattice points (i, j)."""
    h = i.astype(np.uint64) * np.uint64(374761393) + j.astype(np.uint64) * np.uint64(668265263)
    h = h + np.uint64((seed * 2654435761 + 1013904223) & 0xFFFFFFFF)
    h = (h ^ (h >> np.uint64(13))) * np.uint64(1274126177)
    h = h & np.uint64(0xFFFFFFFF)
    h = h ^ (h >> np.uint64(16))
    return (h & np.uint64(0xFFFFFF)).astype(np.float64) / float(1 << 24)


def value_noise(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, cell_deg: float, seed: int) -> np.ndarray:
    """Smooth noise in [0, 1] over directions, periodic in azimuth, with features of ``cell_deg``."""
    n_az = max(1, int(round(360.0 / cell_deg)))
    x = np.mod(azimuth_deg, 360.0) / (360.0 / n_az)
    y = (elevation_deg + 90.0) / cell_deg
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    fx = fx * fx * (3 - 2 * fx)
    fy = fy * fy * (3 - 2 * fy)
    i0 = np.mod(x0, n_az).astype(np.int64)
    i1 = np.mod(x0 + 1, n_az).astype(np.int64)
    j0 = y0.astype(np.int64) + 1000
    j1 = j0 + 1
    top = _hash01(i0, j0, seed) * (1 - fx) + _hash01(i1, j0, seed) * fx
    bot = _hash01(i0, j1, seed) * (1 - fx) + _hash01(i1, j1, seed) * fx
    return np.asarray(top * (1 - fy) + bot * fy)


def fbm(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, cell_deg: float, octaves: int, seed: int) -> np.ndarray:
    """Fractal sum of ``octaves`` value-noise layers, halving the cell each time; values in [0, 1]."""
    total = np.zeros(np.broadcast_shapes(np.shape(azimuth_deg), np.shape(elevation_deg)))
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        total += amp * value_noise(azimuth_deg, elevation_deg, cell_deg / 2**k, seed + 7919 * k)
        norm += amp
        amp *= 0.5
    return total / norm


# ----------------------------------------------------------------------------- skyline sources


def dem_skyline_fn(dem: Any, lat: float, lon: float, height_m: float) -> SkylineFn:
    """The skyline seen from (lat, lon), ``height_m`` above the DEM, via the terrain renderer."""
    def fn(azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h = render_skyline(dem, lat, lon, height_m=height_m, azimuths_deg=np.asarray(azimuth_deg, dtype=np.float64))
        return np.asarray(h.elevation_deg, dtype=np.float64), np.asarray(h.distance_m, dtype=np.float64)

    return fn


def analytic_skyline_fn(seed: int = 0, mean_deg: float = 2.0, amplitude_deg: float = 3.0) -> SkylineFn:
    """A smooth, DEM-free mountain skyline (a sum of sines with random phases) and its distances."""
    rng = np.random.default_rng(seed)
    harmonics = np.array([1, 2, 3, 5, 8, 13, 21, 34])
    amps = amplitude_deg * rng.uniform(0.3, 1.0, harmonics.size) / np.sqrt(harmonics)
    phases = rng.uniform(0, 2 * np.pi, harmonics.size)
    dphase = rng.uniform(0, 2 * np.pi)

    def fn(azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
        el = mean_deg + (amps[:, None] * np.sin(harmonics[:, None] * a[None, :] + phases[:, None])).sum(axis=0)
        dist = 6000.0 + 4000.0 * np.sin(2 * a + dphase)
        return el, dist

    return fn


def sample_skyline(fn: SkylineFn, start_deg: float, stop_deg: float, step_deg: float) -> Skyline:
    """Sample ``fn`` from ``start_deg`` to ``stop_deg`` (increasing, may pass 360) every ``step_deg``."""
    n = int(math.ceil((stop_deg - start_deg) / step_deg)) + 1
    if n > MAX_SKYLINE_SAMPLES:
        n = MAX_SKYLINE_SAMPLES
    az = np.linspace(start_deg, stop_deg, n)
    el, _ = fn(np.mod(az, 360.0))
    return Skyline(np.mod(az, 360.0), el)


# ----------------------------------------------------------------------------- scene


@dataclass(frozen=True)
class _Sun:
    azimuth_deg: float
    elevation_deg: float


def _scene_sun(scene_seed: int) -> _Sun:
    r = np.random.default_rng(scene_seed + 104729)
    return _Sun(float(r.uniform(0, 360)), float(r.uniform(8, 45)))


def render_directions(
    azimuth_deg: np.ndarray,
    elevation_deg: np.ndarray,
    skyline_fn: SkylineFn,
    weather: Weather | str = Weather.CLEAR,
    scene_seed: int = 0,
) -> np.ndarray:
    """The noiseless scene seen in each direction (HxW arrays, degrees): HxWx3 RGB floats in [0, 1].

    The sky/terrain boundary is antialiased over one pixel (estimated from the rows' elevation
    step), so the true skyline is located to a fraction of a pixel.
    """
    w = Weather.parse(weather)
    az = np.mod(np.asarray(azimuth_deg, dtype=np.float64), 360.0)
    el = np.asarray(elevation_deg, dtype=np.float64)
    # skyline at each pixel's azimuth, from a dense periodic sampling of the azimuths in view
    sky_el, sky_dist = _skyline_at(az, el, skyline_fn)

    # sky
    t = np.clip(el / 40.0, 0.0, 1.0)[..., None] ** 0.6
    sky = _SKY_HORIZON * (1 - t) + _SKY_ZENITH * t
    sun = _scene_sun(scene_seed)
    cos_ang = np.sin(np.radians(el)) * math.sin(math.radians(sun.elevation_deg)) + np.cos(np.radians(el)) * math.cos(
        math.radians(sun.elevation_deg)
    ) * np.cos(np.radians(az - sun.azimuth_deg))
    ang = np.degrees(np.arccos(np.clip(cos_ang, -1.0, 1.0)))
    glow = 0.45 * np.exp(-ang / 2.5) + 0.12 * np.exp(-ang / 15.0)
    sky = sky + glow[..., None] * np.array([1.0, 0.95, 0.85])
    if w.clouds:
        el_c = el * 2.5  # clouds are flatter than they are wide
        density = fbm(az, el_c, 12.0, 5, scene_seed + 11)
        cover = np.clip((density - 0.48) / 0.12, 0.0, 1.0)[..., None]
        shade = 0.62 + 0.35 * fbm(az, el_c, 6.0, 2, scene_seed + 13)[..., None]
        sky = sky * (1 - cover) + cover * shade * np.array([1.0, 1.0, 1.0])
    # terrain
    tex = fbm(az, el, 1.5, 6, scene_seed + 17)
    kind = value_noise(az, el, 20.0, scene_seed + 19)[..., None]
    base = _TERRAIN_GREEN * (1 - kind) + _TERRAIN_BROWN * kind
    terrain = base * (0.55 + 0.9 * tex[..., None])
    depth_deg = np.clip(sky_el - el, 0.0, None)
    dist = np.where(np.isfinite(sky_dist), sky_dist, 1.0e5) / (1.0 + depth_deg / 1.0)
    transmission = np.exp(-dist / w.visibility_m)[..., None]
    airlight = _SKY_HORIZON * 0.95
    terrain = terrain * transmission + airlight * (1 - transmission)

    # antialiased boundary: fraction of the pixel above the skyline
    step = np.abs(np.gradient(el, axis=0)) if el.ndim == 2 and el.shape[0] > 1 else np.full_like(el, 0.05)
    step = np.maximum(step, 1e-6)
    above = np.where(np.isfinite(sky_el), np.clip((el - sky_el) / step + 0.5, 0.0, 1.0), 1.0)[..., None]
    img = sky * above + terrain * (1 - above)
    return np.asarray(np.clip(img, 0.0, 1.0))


def _skyline_at(az: np.ndarray, el: np.ndarray, fn: SkylineFn) -> tuple[np.ndarray, np.ndarray]:
    """Skyline elevation and distance at each pixel's azimuth, from a dense sampling of ``fn``."""
    if el.ndim == 2 and el.shape[0] > 1:
        step_pix = float(np.nanmedian(np.abs(np.diff(el, axis=0))))
    else:
        step_pix = 0.1
    step = min(0.05, max(step_pix / 2.0, 360.0 / MAX_SKYLINE_SAMPLES))
    # the azimuth interval in view (it may wrap through north)
    ref = float(np.degrees(np.arctan2(np.sin(np.radians(az)).mean(), np.cos(np.radians(az)).mean())))
    rel = np.mod(az - ref + 180.0, 360.0) - 180.0
    lo, hi = float(rel.min()) - step, float(rel.max()) + step
    if hi - lo > 300.0:
        lo, hi = -180.0, 180.0
    n = min(MAX_SKYLINE_SAMPLES, int(math.ceil((hi - lo) / step)) + 1)
    samples = np.linspace(lo, hi, n)
    s_el, s_dist = fn(np.mod(samples + ref, 360.0))
    # np.interp ignores NaN poorly: interpolate a "no terrain" marker separately
    missing = ~np.isfinite(s_el)
    e = np.interp(rel, samples, np.where(missing, -90.0, s_el))
    d = np.interp(rel, samples, np.where(np.isfinite(s_dist), s_dist, 1.0e5))
    gap = np.interp(rel, samples, missing.astype(np.float64)) > 0.5
    e = np.where(gap, np.nan, e)
    return e, d


def skyline_at(az: np.ndarray, el: np.ndarray, fn: SkylineFn) -> tuple[np.ndarray, np.ndarray]:
    """Skyline elevation (deg) and distance (m) at each pixel's azimuth (HxW arrays of the pixels'
    azimuth and elevation), from a dense sampling of ``fn``; NaN elevation where there is no terrain."""
    return _skyline_at(az, el, fn)


def finish(rgb: np.ndarray, rng: np.random.Generator, jpeg_quality: int | None = JPEG_QUALITY) -> np.ndarray:
    """Sensor noise then JPEG compression: RGB floats in [0, 1] -> HxWx3 uint8 BGR."""
    noisy = rgb + rng.normal(0.0, SENSOR_NOISE_SIGMA, rgb.shape)
    bgr = np.clip(noisy[..., ::-1] * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if jpeg_quality is None:
        return bgr
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 BGR
        raise InputError("synthetic image: JPEG encoding failed")
    return np.asarray(cv2.imdecode(buf, cv2.IMREAD_COLOR))


# ----------------------------------------------------------------------------- photos, panoramas


def render_photo_from(
    skyline_fn: SkylineFn,
    pose: CameraPose,
    intrinsics: CameraIntrinsics,
    rng: np.random.Generator,
    weather: Weather | str = Weather.CLEAR,
    scene_seed: int = 0,
    jpeg_quality: int | None = JPEG_QUALITY,
) -> np.ndarray:
    """What a camera with ``intrinsics`` at ``pose`` sees of the scene: HxWx3 uint8 BGR."""
    v, u = np.mgrid[0 : intrinsics.height, 0 : intrinsics.width].astype(np.float64)
    az, el = pixels_to_directions(intrinsics, pose, u, v)
    return finish(render_directions(az, el, skyline_fn, weather, scene_seed), rng, jpeg_quality)


def render_photo(
    dem: Any,
    lat: float,
    lon: float,
    height_m: float,
    yaw_deg: float,
    pitch_deg: float,
    roll_deg: float,
    intrinsics: CameraIntrinsics,
    rng: np.random.Generator,
    weather: str = "clear",
    scene_seed: int = 0,
) -> np.ndarray:
    """The photo a camera ``height_m`` above the DEM at (lat, lon) takes at the given pose.

    ``yaw_deg`` is the azimuth of the optical axis (clockwise from true north), ``pitch_deg`` its
    elevation, ``roll_deg`` the rotation about it (right side down positive); ``weather`` is one of
    clear, cloudy, hazy, mixed.  Returns HxWx3 uint8 BGR (JPEG-compressed, with sensor noise).
    """
    fn = dem_skyline_fn(dem, lat, lon, height_m)
    pose = CameraPose(yaw_deg, pitch_deg, roll_deg)
    return render_photo_from(fn, pose, intrinsics, rng, weather, scene_seed)


@dataclass(frozen=True)
class SyntheticPanorama:
    panorama: Panorama
    #: the true skyline at the azimuth of every column
    truth: Skyline


def render_panorama(
    skyline_fn: SkylineFn,
    rng: np.random.Generator,
    px_per_rad: float = 557.0,
    height_px: int = 300,
    horizon_row: float | None = None,
    projection: Projection = Projection.CYLINDRICAL,
    azimuth0_deg: float = 0.0,
    width_px: int | None = None,
    weather: Weather | str = Weather.CLEAR,
    scene_seed: int = 0,
    jpeg_quality: int | None = JPEG_QUALITY,
) -> SyntheticPanorama:
    """A synthetic panorama (360 degrees unless ``width_px`` is smaller) and its true skyline."""
    full = full_circle_width(px_per_rad)
    if projection is Projection.EQUIRECTANGULAR and width_px is None:
        px_per_rad = full / (2 * math.pi)
    elif width_px is None or width_px >= full:
        px_per_rad = full / (2 * math.pi)  # exact closure: the columns span exactly 360 degrees
    width = full if width_px is None else min(width_px, full)
    row0 = height_px * 0.6 if horizon_row is None else horizon_row
    geom = Panorama(np.zeros((1, width, 3), np.uint8), projection, px_per_rad, azimuth0_deg, row0, width == full)
    cols = np.arange(width, dtype=np.float64)
    rows = np.arange(height_px, dtype=np.float64)
    az_col = geom.column_azimuth_deg(cols)
    el_row = geom.row_elevation_deg(rows)
    az, el = np.meshgrid(az_col, el_row)
    rgb = render_directions(az, el, skyline_fn, weather, scene_seed)
    img = finish(rgb, rng, jpeg_quality)
    pano = Panorama(img, projection, px_per_rad, azimuth0_deg, row0, width == full)
    true_el, _ = skyline_fn(az_col)
    visible = (true_el < el_row[0]) & (true_el > el_row[-1])
    return SyntheticPanorama(pano, Skyline(az_col, np.where(visible, true_el, np.nan)))
