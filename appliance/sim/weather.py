"""Weather in the camera twin: what an unattended camera sees of the DEM's scene hour after hour.

Each class is drawn per seed (:func:`draw_weather`) into a frozen :class:`WeatherScene`; frames are
rendered from it by :func:`render_weather_photo` (a camera's frame, with the lens's flare where the
sun is in or near the view) over :func:`render_weather_directions` (the scene in any direction).
Clouds drift between frames (``frame_index``), the terrain and the cloud banks resting on ridges
do not.  :func:`weather_truth` gives, per azimuth, the true skyline and whether it can be seen.

Classes (:class:`SkyCondition`):

- ``clear``: the plain scene of :mod:`appliance.vision.synth` (blue sky, sun, no cloud).
- ``cumulus``: blue sky with heaps of white cloud with grey bases, down to the skyline and behind it.
- ``overcast``: a grey sky with faint stratus texture, and banks of cloud that rest on the ridges,
  hiding the skyline and the slope below it down to the bank's base on 15-45 % of the azimuths; the
  base is diffuse (it fades over 1-2.5 deg).
- ``haze``: visibility 6-20 km (the terrain's contrast falls with its distance), and fog lying in
  the valleys: bright, with a soft top at most 1 deg above the horizontal and 0.6-2.5 deg below the
  skyline, on 30-80 % of the azimuths.
- ``low_sun``: the sun 0.3-4 deg above the skyline, its glow saturating the sky around it, a
  veiling glare over terrain and sky, and lens flare (ghosts on the line through the image centre
  and a streak along the sun's row) that moves with the camera, not with the scene.
- ``snow``: fresh snow on the terrain (white ground with dark rocks and trees showing through)
  under a pale sky with thin cloud: white against white, the ground often brighter than the sky.
- ``dusk``: the sun 2-7 deg below the horizon; a dim sky, warm towards the sun, dark terrain and a
  noisier sensor.

The skyline is hidden where a bank's opacity at the true skyline exceeds :data:`HIDDEN_OPACITY` or
where the haze leaves less than :data:`HIDDEN_TRANSMISSION` of the terrain's contrast.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace

import numpy as np

from appliance.errors import enum_member
from appliance.vision.camera import CameraPose, directions_to_pixels, pixels_to_directions
from appliance.vision.intrinsics import CameraIntrinsics
from appliance.vision.panorama import Panorama, Projection, full_circle_width
from appliance.vision.synth import SkylineFn, fbm, finish, render_directions, skyline_at, value_noise

HIDDEN_OPACITY = 0.3
HIDDEN_TRANSMISSION = 0.05
_SNOW = np.array([0.90, 0.92, 0.95])
_TERRAIN_GREEN = np.array([0.20, 0.30, 0.14])
_TERRAIN_BROWN = np.array([0.36, 0.30, 0.22])


class SkyCondition(enum.Enum):
    CLEAR = "clear"
    CUMULUS = "cumulus"
    OVERCAST = "overcast"
    HAZE = "haze"
    LOW_SUN = "low_sun"
    SNOW = "snow"
    DUSK = "dusk"

    @classmethod
    def parse(cls, name: str | SkyCondition) -> SkyCondition:
        return enum_member(cls, name, "weather class")


@dataclass(frozen=True)
class WeatherScene:
    """One drawn weather: the class, the seed of its textures and the drawn magnitudes (units in names)."""

    condition: SkyCondition
    seed: int
    sun_azimuth_deg: float
    sun_elevation_deg: float
    visibility_m: float = 80_000.0
    cloud_cover: float = 0.0  # cumulus: share of the sky under cloud
    drift_deg_per_frame: float = 0.0  # clouds move this much in azimuth between frames
    sky_grey: float = 0.0  # overcast: the sky's brightness
    bank_fraction: float = 0.0  # overcast: share of azimuths whose skyline a bank hides
    bank_depth_deg: float = 0.0  # overcast: how far below the skyline the deepest bank reaches
    bank_soft_deg: float = 1.0  # overcast: the bank's base fades over this many degrees
    fog_fraction: float = 0.0  # haze: share of azimuths with fog in the valleys
    fog_gap_deg: float = 0.0  # haze: the fog's top lies at least this far below the skyline
    dusk_level: float = 1.0  # dusk: the sky's brightness scale
    noise_sigma: float = 0.01  # sensor noise (fraction of full scale)


def draw_weather(condition: SkyCondition | str, seed: int, skyline_fn: SkylineFn) -> WeatherScene:
    """A weather of ``condition`` drawn from ``seed``; the sun is placed on the scene's skyline
    (``skyline_fn``) for the low sun."""
    c = SkyCondition.parse(condition)
    r = np.random.default_rng([seed, 7_000_003])
    sun_az = float(r.uniform(0.0, 360.0))
    sun_el = float(r.uniform(10.0, 45.0))
    base = WeatherScene(condition=c, seed=int(seed), sun_azimuth_deg=sun_az, sun_elevation_deg=sun_el)
    drift = float(r.uniform(0.2, 1.0)) * float(r.choice([-1.0, 1.0]))
    if c is SkyCondition.CUMULUS:
        return replace(base, cloud_cover=float(r.uniform(0.3, 0.6)), drift_deg_per_frame=drift,
                       visibility_m=float(r.uniform(30_000, 80_000)))
    if c is SkyCondition.OVERCAST:
        return replace(base, sky_grey=float(r.uniform(0.55, 0.85)), bank_fraction=float(r.uniform(0.15, 0.45)),
                       bank_depth_deg=float(r.uniform(1.5, 4.0)), bank_soft_deg=float(r.uniform(1.0, 2.5)),
                       drift_deg_per_frame=drift, visibility_m=float(r.uniform(15_000, 40_000)))
    if c is SkyCondition.HAZE:
        return replace(base, visibility_m=float(r.uniform(6_000, 20_000)), fog_fraction=float(r.uniform(0.3, 0.8)),
                       fog_gap_deg=float(r.uniform(0.6, 2.5)))
    if c is SkyCondition.LOW_SUN:
        el, _ = skyline_fn(np.array([sun_az]))
        ridge = float(el[0]) if np.isfinite(el[0]) else 0.0
        return replace(base, sun_elevation_deg=ridge + float(r.uniform(0.3, 4.0)),
                       visibility_m=float(r.uniform(20_000, 60_000)))
    if c is SkyCondition.SNOW:
        return replace(base, cloud_cover=float(r.uniform(0.1, 0.4)), drift_deg_per_frame=drift,
                       visibility_m=float(r.uniform(25_000, 80_000)))
    if c is SkyCondition.DUSK:
        return replace(base, sun_elevation_deg=-float(r.uniform(2.0, 7.0)), dusk_level=float(r.uniform(0.35, 0.9)),
                       noise_sigma=0.02, visibility_m=float(r.uniform(30_000, 80_000)))
    return base


# ----------------------------------------------------------------------------- geometry of the weather


def _noise1(az: np.ndarray, cell_deg: float, seed: int) -> np.ndarray:
    """Smooth noise in [0, 1] over azimuth alone (two octaves), stretched to spread over the range."""
    n = 0.67 * value_noise(az, np.zeros_like(az), cell_deg, seed) + 0.33 * value_noise(
        az, np.zeros_like(az), cell_deg / 2.0, seed + 1)
    return np.asarray(np.clip((n - 0.5) * 1.6 + 0.5, 0.0, 1.0))


def _threshold(fraction: float) -> float:
    return float(np.clip(1.0 - fraction, 0.0, 1.0))


def bank_base_deg(scene: WeatherScene, azimuth_deg: np.ndarray, skyline_deg: np.ndarray) -> np.ndarray:
    """The elevation (deg) of the cloud banks' base at each azimuth; +inf without banks.  Where the
    base is below the skyline the bank hides the ridge."""
    if scene.bank_fraction <= 0.0:
        return np.full(np.shape(azimuth_deg), np.inf)
    n = _noise1(np.asarray(azimuth_deg, dtype=np.float64), 30.0, scene.seed + 301)
    thr = _threshold(scene.bank_fraction)
    # above the threshold the base is below the ridge, by up to bank_depth_deg
    depth = scene.bank_depth_deg * (n - thr) / max(1.0 - thr, 1e-3)
    sky = np.where(np.isfinite(skyline_deg), skyline_deg, 0.0)
    return np.asarray(sky - np.where(depth > 0, depth, 2.0 * depth) + 0.5 * scene.bank_soft_deg)


def _bank_opacity(scene: WeatherScene, el: np.ndarray, base: np.ndarray) -> np.ndarray:
    t = (el - base) / scene.bank_soft_deg + 0.5
    t = np.clip(t, 0.0, 1.0)
    return np.asarray(0.95 * t * t * (3.0 - 2.0 * t))


def _fog_top_deg(scene: WeatherScene, az: np.ndarray, skyline_deg: np.ndarray) -> np.ndarray:
    """The fog's top (deg): a level between 3 deg below the horizontal and 1 deg above it where
    the azimuth has fog (0.8 deg lower where it has not), never nearer the skyline than the gap."""
    n = _noise1(az, 40.0, scene.seed + 401)
    thr = _threshold(scene.fog_fraction)
    level = -3.0 + 4.0 * np.clip((n - thr) / max(1.0 - thr, 1e-3), 0.0, 1.0) - 8.0 * np.clip((thr - n) / 0.15, 0.0, 1.0)
    return np.asarray(np.minimum(skyline_deg - scene.fog_gap_deg, level))


def weather_truth(scene: WeatherScene, skyline_fn: SkylineFn,
                  azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(true skyline elevation in degrees, visible) at each azimuth: not visible where a cloud bank
    covers the ridge or the haze leaves too little of its contrast (and where there is no terrain)."""
    az = np.mod(np.asarray(azimuth_deg, dtype=np.float64), 360.0)
    el, dist = skyline_fn(az)
    el = np.asarray(el, dtype=np.float64)
    visible = np.isfinite(el)
    if scene.bank_fraction > 0.0:
        opacity = _bank_opacity(scene, np.where(visible, el, 0.0), bank_base_deg(scene, az, el))
        visible &= opacity <= HIDDEN_OPACITY
    d = np.where(np.isfinite(dist), dist, 1.0e5)
    visible &= np.exp(-d / scene.visibility_m) >= HIDDEN_TRANSMISSION
    return el, visible


# ----------------------------------------------------------------------------- rendering


def _sun_angle_deg(scene: WeatherScene, az: np.ndarray, el: np.ndarray) -> np.ndarray:
    s_el, s_az = math.radians(scene.sun_elevation_deg), scene.sun_azimuth_deg
    e = np.radians(el)
    cos_ang = np.sin(e) * math.sin(s_el) + np.cos(e) * math.cos(s_el) * np.cos(np.radians(az - s_az))
    return np.asarray(np.degrees(np.arccos(np.clip(cos_ang, -1.0, 1.0))))


def _sky(scene: WeatherScene, az: np.ndarray, el: np.ndarray, frame_index: int) -> np.ndarray:
    c = scene.condition
    t = (np.clip(el / 40.0, 0.0, 1.0) ** 0.6)[..., None]
    ang = _sun_angle_deg(scene, az, el)
    az_c = az - scene.drift_deg_per_frame * frame_index
    if c is SkyCondition.OVERCAST:
        g = scene.sky_grey * (0.92 + 0.12 * t)
        texture = 0.05 * (fbm(az_c, el * 2.0, 8.0, 3, scene.seed + 501) - 0.5)[..., None]
        return np.asarray(g * np.array([0.98, 1.0, 1.03]) + texture)
    if c is SkyCondition.DUSK:
        warm = np.exp(-np.abs(np.mod(az - scene.sun_azimuth_deg + 180.0, 360.0) - 180.0) / 60.0)[..., None]
        low = np.exp(-np.clip(el, 0.0, None) / 8.0)[..., None]
        horizon = np.array([0.30, 0.33, 0.45]) * (1 - warm) + np.array([0.75, 0.45, 0.25]) * warm
        sky = (horizon * low + np.array([0.10, 0.13, 0.25]) * (1 - low)) * scene.dusk_level
        return np.asarray(sky)
    zenith, horizon = np.array([0.25, 0.45, 0.85]), np.array([0.72, 0.80, 0.90])
    if c is SkyCondition.SNOW:
        zenith, horizon = np.array([0.45, 0.60, 0.88]), np.array([0.76, 0.82, 0.90])
    sky = horizon * (1 - t) + zenith * t
    if c is SkyCondition.LOW_SUN:
        glow = 1.6 * np.exp(-ang / 1.5) + 0.5 * np.exp(-ang / 8.0) + 0.15 * np.exp(-ang / 40.0)
        sky = sky + glow[..., None] * np.array([1.0, 0.85, 0.6])
    else:
        glow = 0.45 * np.exp(-ang / 2.5) + 0.12 * np.exp(-ang / 15.0)
        sky = sky + glow[..., None] * np.array([1.0, 0.95, 0.85])
    if scene.cloud_cover > 0.0:
        el_c = el * 2.5
        density = fbm(az_c, el_c, 10.0, 4, scene.seed + 511)
        thr = float(np.quantile(np.linspace(0.3, 0.7, 101), 1.0 - scene.cloud_cover))
        cover = np.clip((density - thr) / 0.08, 0.0, 1.0)[..., None]
        # bright tops, grey bases: the density's rise upwards shades the cloud
        under = fbm(az_c, el_c - 1.5, 10.0, 4, scene.seed + 511)
        shade = np.clip(0.78 + 2.5 * (density - under), 0.55, 1.0)[..., None]
        if c is SkyCondition.SNOW:
            shade = 0.5 * shade + 0.45
        sky = sky * (1 - cover) + cover * shade * np.array([0.97, 0.98, 1.0])
    return np.asarray(sky)


def _terrain(scene: WeatherScene, az: np.ndarray, el: np.ndarray, sky_el: np.ndarray,
             sky_dist: np.ndarray) -> np.ndarray:
    c = scene.condition
    tex = fbm(az, el, 1.5, 5, scene.seed + 17)
    kind = value_noise(az, el, 20.0, scene.seed + 19)[..., None]
    ground = (_TERRAIN_GREEN * (1 - kind) + _TERRAIN_BROWN * kind) * (0.55 + 0.9 * tex[..., None])
    if c is SkyCondition.SNOW:
        rocks = np.clip((fbm(az, el, 2.0, 4, scene.seed + 23) - 0.6) / 0.06, 0.0, 1.0)[..., None]
        snow = _SNOW * (0.88 + 0.12 * tex[..., None])
        ground = snow * (1 - rocks) + ground * 0.6 * rocks
    if c is SkyCondition.DUSK:
        ground = ground * 0.18 * scene.dusk_level
    depth_deg = np.clip(sky_el - el, 0.0, None)
    dist = np.where(np.isfinite(sky_dist), sky_dist, 1.0e5) / (1.0 + depth_deg / 1.0)
    transmission = np.exp(-dist / scene.visibility_m)[..., None]
    air = np.array([0.72, 0.80, 0.90]) * 0.95
    if c is SkyCondition.OVERCAST:
        air = np.full(3, scene.sky_grey)
    elif c is SkyCondition.DUSK:
        air = np.array([0.30, 0.33, 0.45]) * scene.dusk_level
    ground = ground * transmission + air * (1 - transmission)
    if scene.fog_fraction > 0.0:
        top = _fog_top_deg(scene, az, np.where(np.isfinite(sky_el), sky_el, 0.0))
        f = np.clip((top - el) / 0.8 + 0.5, 0.0, 1.0)
        f = (0.9 * f * f * (3.0 - 2.0 * f))[..., None]
        ground = ground * (1 - f) + np.array([0.86, 0.88, 0.90]) * f
    return np.asarray(ground)


def render_weather_directions(azimuth_deg: np.ndarray, elevation_deg: np.ndarray, skyline_fn: SkylineFn,
                              scene: WeatherScene, frame_index: int = 0) -> np.ndarray:
    """The noiseless scene under ``scene``'s weather in each direction (HxW arrays, degrees), at
    frame ``frame_index`` of a capture (the clouds' drift): HxWx3 RGB floats in [0, 1]."""
    if scene.condition is SkyCondition.CLEAR:
        return render_directions(azimuth_deg, elevation_deg, skyline_fn, "clear", scene.seed)
    az = np.mod(np.asarray(azimuth_deg, dtype=np.float64), 360.0)
    el = np.asarray(elevation_deg, dtype=np.float64)
    sky_el, sky_dist = skyline_at(az, el, skyline_fn)
    sky = _sky(scene, az, el, frame_index)
    terrain = _terrain(scene, az, el, sky_el, sky_dist)
    step = np.abs(np.gradient(el, axis=0)) if el.ndim == 2 and el.shape[0] > 1 else np.full_like(el, 0.05)
    step = np.maximum(step, 1e-6)
    above = np.where(np.isfinite(sky_el), np.clip((el - sky_el) / step + 0.5, 0.0, 1.0), 1.0)[..., None]
    img = sky * above + terrain * (1 - above)
    if scene.bank_fraction > 0.0:
        base = bank_base_deg(scene, az, sky_el)
        op = _bank_opacity(scene, el, base)[..., None]
        tex = fbm(az - scene.drift_deg_per_frame * frame_index * 0.3, el * 2.0, 5.0, 3, scene.seed + 601)
        bank = scene.sky_grey * (0.94 + 0.12 * tex)[..., None] * np.array([0.98, 1.0, 1.03])
        img = img * (1 - op) + bank * op
    if scene.condition is SkyCondition.LOW_SUN:
        ang = _sun_angle_deg(scene, az, el)
        veil = (0.22 * np.exp(-ang / 10.0) + 0.08 * np.exp(-ang / 40.0))[..., None]
        img = img + veil * np.array([1.0, 0.9, 0.75])
    return np.asarray(np.clip(img, 0.0, 1.0))


def _flare(scene: WeatherScene, intrinsics: CameraIntrinsics, pose: CameraPose, u: np.ndarray,
           v: np.ndarray) -> np.ndarray:
    """Lens flare (HxWx3, added): ghosts on the line from the sun's image through the centre and a
    streak along its row; nothing when the sun is far outside the view."""
    su, sv = directions_to_pixels(intrinsics, pose, np.array([scene.sun_azimuth_deg]),
                                  np.array([scene.sun_elevation_deg]))
    out = np.zeros(u.shape + (3,))
    if not (np.isfinite(su[0]) and np.isfinite(sv[0])):
        return out
    su_px, sv_px = float(su[0]), float(sv[0])
    w, h = intrinsics.width, intrinsics.height
    if not (-0.5 * w <= su_px <= 1.5 * w and -0.5 * h <= sv_px <= 1.5 * h):
        return out
    cu, cv = (w - 1) / 2.0, (h - 1) / 2.0
    r = np.random.default_rng([scene.seed, 7_000_011])
    for k, radius, gain in ((0.5, 14.0, 0.10), (0.9, 30.0, 0.06), (1.4, 45.0, 0.05), (-0.35, 9.0, 0.12)):
        gu, gv = su_px + k * 2.0 * (cu - su_px), sv_px + k * 2.0 * (cv - sv_px)
        d = np.hypot(u - gu, v - gv)
        disc = np.clip((radius - d) / 3.0 + 0.5, 0.0, 1.0)
        tint = np.array([0.6, 0.9, 1.0]) * float(r.uniform(0.7, 1.3))
        out += (gain * disc)[..., None] * tint
    streak = 0.12 * np.exp(-np.abs(v - sv_px) / 2.5) * np.exp(-np.abs(u - su_px) / 250.0)
    out += streak[..., None] * np.array([1.0, 0.95, 0.85])
    return out


def render_weather_photo(skyline_fn: SkylineFn, pose: CameraPose, intrinsics: CameraIntrinsics,
                         rng: np.random.Generator, scene: WeatherScene, frame_index: int = 0) -> np.ndarray:
    """What a camera with ``intrinsics`` at ``pose`` sees under ``scene``'s weather at frame
    ``frame_index``: HxWx3 uint8 BGR (sensor noise, JPEG)."""
    v, u = np.mgrid[0 : intrinsics.height, 0 : intrinsics.width].astype(np.float64)
    az, el = pixels_to_directions(intrinsics, pose, u, v)
    rgb = render_weather_directions(az, el, skyline_fn, scene, frame_index)
    if scene.condition is SkyCondition.LOW_SUN:
        rgb = np.clip(rgb + _flare(scene, intrinsics, pose, u, v), 0.0, 1.0)
    if scene.noise_sigma != 0.01:
        rgb = np.clip(rgb + rng.normal(0.0, math.sqrt(scene.noise_sigma**2 - 0.01**2), rgb.shape), 0.0, 1.0)
    return finish(rgb, rng)


def render_weather_panorama(skyline_fn: SkylineFn, scene: WeatherScene, rng: np.random.Generator,
                            width_px: int, height_px: int = 240, px_per_deg: float = 9.67,
                            azimuth0_deg: float = 0.0) -> tuple[Panorama, np.ndarray, np.ndarray]:
    """A cylindrical panorama ``width_px`` columns wide (``px_per_deg`` at its horizon row, the
    capture ring's scale by default) under ``scene``'s weather, with the true skyline (deg) and its
    visibility at every column."""
    px_per_rad = px_per_deg * 180.0 / math.pi
    full = full_circle_width(px_per_rad)
    width = min(width_px, full)
    geom = Panorama(np.zeros((1, width, 3), np.uint8), Projection.CYLINDRICAL, px_per_rad, azimuth0_deg,
                    (height_px - 1) / 2.0, width == full)
    az_col = geom.column_azimuth_deg(np.arange(width, dtype=np.float64))
    el_row = geom.row_elevation_deg(np.arange(height_px, dtype=np.float64))
    az, el = np.meshgrid(az_col, el_row)
    img = finish(render_weather_directions(az, el, skyline_fn, scene), rng)
    true_el, visible = weather_truth(scene, skyline_fn, az_col)
    pano = Panorama(img, Projection.CYLINDRICAL, px_per_rad, azimuth0_deg, (height_px - 1) / 2.0, width == full)
    return pano, true_el, visible
