"""Synthetic photos no one tuned on, located by `viper locate` (issue 31).

Each seed places a camera at random on the map, inside the skyline database's valid area and at least
1.5 km from its edges, 1.5 m above the WORLD's surface, and points it at random: yaw uniform 0-360 deg,
pitch uniform +-5, roll uniform +-3.  The photo (1280 x 720 px, 16:9, horizontal field of view --fov,
default 60 deg, no distortion) is rendered by appliance.vision.synth.render_photo_from from the world's
DEM (dem_skyline_fn), weather "cloudy" on even seeds and "mixed" (clouds and 12 km haze) on odd ones,
with 1-3 near objects the map lacks: over 1-4 deg of azimuth at a random place in the view the skyline
is raised by 2-10 deg, either over the whole width (a pole or a mast) or as an elliptical crown (a
tree), 10-40 m away.  The JPEG carries EXIF FocalLengthIn35mmFilm = round(f35 * (1 + u)), u uniform
+-3 % (f35 on the 43.27 mm frame diagonal: f35 = f_px * 43.2666 / hypot(w, h)) and nothing else about
the lens; no camera file is given.  Position, pose, occluders and focal error depend on the seed only,
so the photos of one seed at different fields of view are taken from the same place in the same
direction.

Worlds:
  jacksboro  world = map = shared/data/dem_other/jacksboro_fault_dem.npz; database
             bench/cache/jacksboro-native.viperdb (made as bench/estimator_accuracy.py makes it).
  forest     the White Mountains forest of bench/world_gap.py (world seed 1): world = SRTM tile N44W072 +
             canopy 15-25 m + clearings + 4 m correlated noise; map = the bare tile, its database
             the one bench/world_gap.py builds.  Cameras stand where world_gap's do, in the mix
             clearing, clearing, summit, open by seed (a camera 1.5 m above a forest canopy, or
             under it, sees no skyline that a photographer would take).

Search area: `--near LAT,LON,1784` (a circle of 10 km^2) whose centre lies 0-60 % of the radius from
the camera in a random direction.  `viper locate PHOTO --map DB --near ... --json --truth LAT,LON` runs
as a subprocess (--viper, default REPO/.venv/bin/viper, so other checkouts can be measured).

Figures per world and field of view (cell = geometric mean of the database's node spacing): share
within two cells, median error, share with status ok, wrong-and-ok (more than two cells off and not
flagged ambiguous by the locator itself: its "ambiguous" field when the JSON has one, since with
--truth the status also turns ambiguous when the truth lies outside the region), right-but-ambiguous
share, truth in region and in the 95 % ellipse (the JSON's truth block), median |yaw|, |pitch|,
|roll| and |focal| errors of the answers within two cells, median and 90th percentile of timing.total_s.
Targets (issue 31): >= 90 % within two cells at 60 deg, wrong-and-ok = 0; success against the field of
view (30, 45, 60, 90) is reported with --fov-sweep.
Each seed's row also carries near_share: the share of the view (yaw +- half the field of view) whose
skyline is terrain within 150 m of the camera, from the world's render at the truth; the printed
summary gives the within-two-cells share of the photos with at most 25 % of it ("near-slope photos"
have more: their skyline moves by degrees within a node's cell).

Seeds 1000-1059 are the reported set: they were not used while the locator was developed, which used
seeds 1-20.  A row per (world, fov) is appended to bench/results/photo_locate.md; per-seed JSON lines
go to WORK/runs/, rendered photos (cached by world, seed and fov) to WORK/photos/.

    python bench/photo_locate.py [--world jacksboro,forest] [--seeds 1000-1059] [--fov 60 | --fov-sweep]
                                 [--viper PATH] [--work DIR] [--timeout S] [--dry-run] [--no-record]

--dry-run renders the photos and prints the commands it would run (e.g. --dry-run --seeds 1-2).
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import date
from pathlib import Path

import numpy as np
from PIL import ExifTags, Image
from pyproj import Geod

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO))

from appliance.atomic import write_bytes_atomic, write_text_atomic  # noqa: E402
from appliance.terrain.database import SkylineDatabase  # noqa: E402
from appliance.terrain.dem import Dem, load_dem  # noqa: E402
from appliance.vision.camera import CameraPose, pixels_to_directions  # noqa: E402
from appliance.vision.intrinsics import CameraIntrinsics  # noqa: E402
from appliance.vision.synth import (  # noqa: E402
    JPEG_QUALITY,
    MAX_SKYLINE_SAMPLES,
    SkylineFn,
    dem_skyline_fn,
    render_photo_from,
)
from bench import world_gap  # noqa: E402
from bench.estimator_accuracy import map_database  # noqa: E402
from bench.results_file import append_result, checkout_commit  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
JACKSBORO = SHARED / "dem_other" / "jacksboro_fault_dem.npz"
VIPER = REPO / ".venv" / "bin" / "viper"
RESULTS = HERE / "results" / "photo_locate.md"
WORK = Path(tempfile.gettempdir()) / "viper-photo-locate"

ISSUE = 31  # part of every random stream's seed
GENERATOR = 2  # bump when the photos change, so cached ones are rendered again
WIDTH_PX, HEIGHT_PX = 1280, 720
CAMERA_HEIGHT_M = 1.5
PITCH_DEG, ROLL_DEG = 5.0, 3.0
FOCAL_ERROR = 0.03  # EXIF focal length: uniform within +-3 % of the truth, then rounded to 1 mm
FRAME_DIAGONAL_MM = 43.2666  # the 35 mm frame's diagonal, on which FocalLengthIn35mmFilm is defined
SEARCH_AREA_M2 = 10.0e6
SEARCH_RADIUS_M = round(math.sqrt(SEARCH_AREA_M2 / math.pi))  # 1784 m
CENTRE_OFFSET = 0.6  # the circle's centre lies up to this share of the radius from the camera
EDGE_MARGIN_M = 1500.0  # cameras stand at least this far inside the database's node grid
OCCLUDERS = (1, 3)
OCCLUDER_WIDTH_DEG = (1.0, 4.0)
OCCLUDER_RAISE_DEG = (2.0, 10.0)
OCCLUDER_DISTANCE_M = (10.0, 40.0)
OCCLUDER_VIEW_SHARE = 0.45  # occluder centres within +-45 % of the field of view about the yaw
FOREST_WORLD_SEED = 1
FOREST_SITES = ("clearing", "clearing", "summit", "open")
FOV_SWEEP = (30.0, 45.0, 60.0, 90.0)
TARGET_WITHIN_2 = 0.90  # at 60 deg
REPORTED_SEEDS = "1000-1059"
WORLD_KEYS = {"jacksboro": 1, "forest": 2}
SKYLINE_STEP_DEG = 360.0 / MAX_SKYLINE_SAMPLES  # how finely the renderer samples the skyline
NO_SKYLINE = 0.5  # a photo whose skyline crosses fewer columns than this share "has no skyline"
NEAR_RANGE_M = 150.0  # terrain this close forms a "near" skyline: it moves by degrees within a node's cell
NEAR_VIEW_SHARE = 0.25  # a photo whose view has more than this share of near skyline is a "near-slope" photo
NEAR_STEP_DEG = 0.5  # the azimuth step of the view's skyline ranges


# ----------------------------------------------------------------------------- the photo


@dataclass(frozen=True)
class Occluder:
    """A near object the map lacks: the skyline raised by ``raise_deg`` over ``width_deg`` of azimuth."""

    azimuth_deg: float  # centre
    width_deg: float
    raise_deg: float
    distance_m: float
    kind: str  # "pole": raised over the whole width; "tree": an elliptical crown

    def raise_at_deg(self, azimuth_deg: np.ndarray) -> np.ndarray:
        """How much the skyline is raised at each azimuth (deg; 0 outside the object)."""
        x = (np.mod(np.asarray(azimuth_deg, dtype=np.float64) - self.azimuth_deg + 180.0, 360.0) - 180.0) / (
            0.5 * self.width_deg
        )
        inside = np.abs(x) < 1.0
        shape = np.ones_like(x) if self.kind == "pole" else np.sqrt(np.clip(1.0 - x * x, 0.0, 1.0))
        return np.where(inside, self.raise_deg * shape, 0.0)


@dataclass(frozen=True)
class PhotoSpec:
    """Everything a synthetic photo is made from, and its truth."""

    world: str
    seed: int
    fov_deg: float  # horizontal
    site: str
    lat: float
    lon: float
    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    weather: str
    occluders: tuple[Occluder, ...]
    focal_error: float  # u: the EXIF focal length is round(f35 * (1 + u))
    near_lat: float
    near_lon: float
    near_radius_m: float
    width_px: int = WIDTH_PX
    height_px: int = HEIGHT_PX

    @property
    def name(self) -> str:
        return f"{self.world}-fov{self.fov_deg:g}-seed{self.seed}"

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics.from_fov(self.width_px, self.height_px, self.fov_deg)

    @property
    def pose(self) -> CameraPose:
        return CameraPose(self.yaw_deg, self.pitch_deg, self.roll_deg)

    @property
    def f35_mm(self) -> float:
        return f35_from_px(self.intrinsics.fx, self.width_px, self.height_px)

    @property
    def exif_f35_mm(self) -> int:
        return int(round(self.f35_mm * (1.0 + self.focal_error)))

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "generator": GENERATOR, "f_px": self.intrinsics.fx,
                "f35_mm": self.f35_mm, "exif_f35_mm": self.exif_f35_mm}

    @classmethod
    def from_json(cls, data: dict) -> PhotoSpec:
        fields = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in data.items() if k in fields}
        kw["occluders"] = tuple(Occluder(**o) for o in data["occluders"])
        return cls(**kw)


def f35_from_px(f_px: float, width_px: int, height_px: int) -> float:
    """The 35 mm equivalent focal length (mm, on the frame diagonal) of a focal length in pixels."""
    return f_px * FRAME_DIAGONAL_MM / math.hypot(width_px, height_px)


def px_from_f35(f35_mm: float, width_px: int, height_px: int) -> float:
    """The focal length in pixels of a 35 mm equivalent focal length (mm, on the frame diagonal)."""
    return f35_mm * math.hypot(width_px, height_px) / FRAME_DIAGONAL_MM


def occluded_skyline_fn(fn: SkylineFn, occluders: Sequence[Occluder]) -> SkylineFn:
    """``fn`` with the near objects in front: the higher of the terrain and each object's top, and
    the object's distance where it stands (NaN terrain counts as 0 deg under an object)."""

    def wrapped(azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        az = np.asarray(azimuth_deg, dtype=np.float64)
        el, dist = fn(az)
        el_out = np.array(el, dtype=np.float64)
        dist_out = np.array(dist, dtype=np.float64)
        base = np.where(np.isfinite(el_out), el_out, 0.0)
        for o in occluders:
            lift = o.raise_at_deg(az)
            hit = lift > 0.0
            el_out = np.where(hit, np.fmax(el_out, base + lift), el_out)
            dist_out = np.where(hit, np.fmin(dist_out, o.distance_m), dist_out)
        return el_out, dist_out

    return wrapped


def photo_skyline_fn(world_dem: Dem, spec: PhotoSpec) -> SkylineFn:
    """What the camera of ``spec`` sees: the world's skyline 1.5 m above its surface, objects in front."""
    return occluded_skyline_fn(dem_skyline_fn(world_dem, spec.lat, spec.lon, CAMERA_HEIGHT_M), spec.occluders)


class RecordedSkylineFn:
    """A skyline function that keeps what it returned, so the skyline the renderer drew can be read
    again (:meth:`table`) without ray-marching the DEM twice."""

    def __init__(self, fn: SkylineFn) -> None:
        self.fn = fn
        self._az: list[np.ndarray] = []
        self._el: list[np.ndarray] = []
        self._dist: list[np.ndarray] = []

    def __call__(self, azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        az = np.mod(np.asarray(azimuth_deg, dtype=np.float64), 360.0)
        el, dist = self.fn(az)
        self._az.append(az.ravel())
        self._el.append(np.asarray(el, dtype=np.float64).ravel())
        self._dist.append(np.asarray(dist, dtype=np.float64).ravel())
        return el, dist

    def table(self) -> SkylineFn:
        """The samples returned so far, linear between them as the renderer interpolates them (NaN
        where the nearer sample has no terrain); raises when nothing was sampled yet."""
        if not self._az:
            raise ValueError("the skyline function was never called")
        az, i = np.unique(np.concatenate(self._az), return_index=True)
        el = np.concatenate(self._el)[i]
        dist = np.concatenate(self._dist)[i]
        missing = ~np.isfinite(el)

        def fn(azimuth_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            a = np.mod(np.asarray(azimuth_deg, dtype=np.float64), 360.0)
            e = np.interp(a, az, np.where(missing, -90.0, el), period=360.0)
            d = np.interp(a, az, np.where(np.isfinite(dist), dist, 1.0e5), period=360.0)
            gap = np.interp(a, az, missing.astype(np.float64), period=360.0) > 0.5
            return np.where(gap, np.nan, e), d

        return fn


def render_photo_bgr(world_dem: Dem, spec: PhotoSpec, skyline_fn: SkylineFn | None = None) -> np.ndarray:
    """The photo of ``spec`` before compression: HxWx3 uint8 BGR with sensor noise (``skyline_fn``
    defaults to :func:`photo_skyline_fn`)."""
    fn = photo_skyline_fn(world_dem, spec) if skyline_fn is None else skyline_fn
    rng = np.random.default_rng([ISSUE, WORLD_KEYS.get(spec.world, 0), spec.seed, 2, round(100 * spec.fov_deg)])
    return render_photo_from(fn, spec.pose, spec.intrinsics, rng, spec.weather, scene_seed=spec.seed,
                             jpeg_quality=None)


def jpeg_with_exif(image_bgr: np.ndarray, f35_mm: int, quality: int = JPEG_QUALITY) -> bytes:
    """JPEG bytes of ``image_bgr`` whose EXIF says FocalLengthIn35mmFilm = ``f35_mm`` (and the maker)."""
    exif = Image.Exif()
    exif[ExifTags.Base.Make] = "viper bench"
    exif[ExifTags.Base.Model] = "photo_locate synthetic"
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = int(f35_mm)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image_bgr[..., ::-1])).save(buf, "JPEG", quality=quality, exif=exif)
    return buf.getvalue()


def exif_f35_mm(path: Path) -> int | None:
    """FocalLengthIn35mmFilm of a JPEG, or None when it has none."""
    with Image.open(path) as img:
        value = img.getexif().get_ifd(ExifTags.IFD.Exif).get(ExifTags.Base.FocalLengthIn35mmFilm)
    return None if value is None else int(value)


def write_photo(path: Path, world_dem: Dem, spec: PhotoSpec, skyline_fn: SkylineFn | None = None) -> np.ndarray:
    """Render ``spec`` and write it as a JPEG with its EXIF; returns the image as written (BGR, decoded)."""
    data = jpeg_with_exif(render_photo_bgr(world_dem, spec, skyline_fn), spec.exif_f35_mm)
    write_bytes_atomic(path, data)
    with Image.open(io.BytesIO(data)) as img:
        return np.asarray(img.convert("RGB"))[..., ::-1]


def skyline_rows_px(skyline_fn: SkylineFn, spec: PhotoSpec, step_deg: float | None = SKYLINE_STEP_DEG) -> np.ndarray:
    """Where appliance.vision.camera puts the skyline in each column of the photo: the fractional row
    at which a pixel's elevation crosses the skyline at its azimuth; NaN where the column does not
    cross it (the skyline above or below the frame).  The skyline is sampled every ``step_deg``
    (by default as often as the renderer samples it), linear between; ``None`` evaluates
    ``skyline_fn`` at every pixel's azimuth (for a cheap one, e.g. :meth:`RecordedSkylineFn.table`)."""
    v, u = np.mgrid[0 : spec.height_px, 0 : spec.width_px].astype(np.float64)
    az, el = pixels_to_directions(spec.intrinsics, spec.pose, u, v)
    if step_deg is None:
        sky, _ = skyline_fn(az)
    else:
        rel = np.mod(az - spec.yaw_deg + 180.0, 360.0) - 180.0
        samples = np.arange(math.floor(rel.min() / step_deg) - 1, math.ceil(rel.max() / step_deg) + 2) * step_deg
        s_el, _ = skyline_fn(np.mod(samples + spec.yaw_deg, 360.0))
        sky = np.interp(rel, samples, np.where(np.isfinite(s_el), s_el, -90.0))
    sky = np.where(np.isfinite(sky), sky, -90.0)
    d = el - sky  # > 0 in the sky, falling down each column
    cross = (d[:-1] >= 0.0) & (d[1:] < 0.0)
    has = cross.any(axis=0)
    k = np.argmax(cross, axis=0)
    cols = np.arange(spec.width_px)
    d0, d1 = d[k, cols], d[k + 1, cols]
    return np.where(has, k + d0 / (d0 - d1), np.nan)


def skyline_offsets_px(image_bgr: np.ndarray, rows_px: np.ndarray, search_px: int = 12) -> np.ndarray:
    """Per column, the sky-to-ground edge found in the image (the strongest fall of brightness within
    ``search_px`` of ``rows_px``, to a fraction of a pixel) minus ``rows_px``; NaN where the expected
    row is missing or too near the border."""
    grey = np.asarray(image_bgr, dtype=np.float64).mean(axis=2)
    h, w = grey.shape
    fall = grey[:-1] - grey[1:]  # between rows v and v + 1, i.e. at v + 0.5
    out = np.full(w, np.nan)
    r = np.asarray(rows_px, dtype=np.float64)
    ok = np.isfinite(r) & (r >= search_px + 2) & (r <= h - search_px - 3)
    cols = np.nonzero(ok)[0]
    if cols.size == 0:
        return out
    top = np.floor(r[cols]).astype(int) - search_px
    idx = top[:, None] + np.arange(2 * search_px + 1)[None, :]
    window = fall[idx, cols[:, None]]
    k = np.argmax(window, axis=1)
    k = np.clip(k, 1, window.shape[1] - 2)
    a, b, c = (window[np.arange(cols.size), k + j] for j in (-1, 0, 1))
    denom = a - 2 * b + c
    frac = np.where(denom < 0, 0.5 * (a - c) / np.where(denom < 0, denom, -1.0), 0.0)
    out[cols] = top + k + 0.5 + np.clip(frac, -0.5, 0.5) - r[cols]
    return out


def skyline_check(image_bgr: np.ndarray, skyline_fn: SkylineFn, spec: PhotoSpec,
                  step_deg: float | None = SKYLINE_STEP_DEG) -> dict[str, float | None]:
    """How well the skyline in the image lies where the camera model puts it: the share of columns
    the skyline crosses, and over the columns checked (away from the top and bottom) the median
    absolute offset (px) and the share within 1.5 px; None where no column could be checked."""
    rows = skyline_rows_px(skyline_fn, spec, step_deg)
    off = skyline_offsets_px(image_bgr, rows)
    fin = off[np.isfinite(off)]
    in_frame = round(float(np.mean(np.isfinite(rows))), 3)
    if fin.size == 0:
        return {"skyline_in_frame": in_frame, "columns": 0, "median_abs_px": None, "within_1_5_px": None}
    return {"skyline_in_frame": in_frame, "columns": int(fin.size),
            "median_abs_px": round(float(np.median(np.abs(fin))), 3),
            "within_1_5_px": round(float(np.mean(np.abs(fin) <= 1.5)), 3)}


def near_share(world_dem: Dem, spec: PhotoSpec) -> float:
    """The share of the photo's horizontal view (yaw +- half the field of view) whose skyline is
    terrain within NEAR_RANGE_M of the camera, from the world's own render at the truth (no objects)."""
    half = 0.5 * spec.fov_deg
    az = np.mod(spec.yaw_deg + np.arange(-half, half + NEAR_STEP_DEG / 2, NEAR_STEP_DEG), 360.0)
    _, dist = dem_skyline_fn(world_dem, spec.lat, spec.lon, CAMERA_HEIGHT_M)(az)
    d = np.asarray(dist, dtype=np.float64)
    return round(float(np.mean(np.isfinite(d) & (d < NEAR_RANGE_M))), 3)


# ----------------------------------------------------------------------------- worlds and seeds


@dataclass
class BenchWorld:
    """A world to render from and the map's skyline database the locator searches."""

    name: str
    world: Dem
    db: SkylineDatabase
    db_path: Path
    map_path: Path  # the DEM file the locator is given: it builds each search area's database into its cache
    gap: world_gap.World | None = None  # the forest world's sites

    @property
    def cell_m(self) -> float:
        return math.sqrt(self.db.grid.dx_m * self.db.grid.dy_m)


def make_world(name: str) -> BenchWorld:
    if name == "jacksboro":
        _, db = map_database("jacksboro")
        return BenchWorld(name, load_dem(JACKSBORO), db, Path(db.path), JACKSBORO)
    if name == "forest":
        gap = world_gap.forest_world(FOREST_WORLD_SEED)
        db = world_gap.skyline_database(gap)
        return BenchWorld(name, gap.world, db, Path(db.path), world_gap.TILE, gap)
    raise SystemExit(f"world {name!r} unknown; expected jacksboro or forest")


def inside_database(db: SkylineDatabase, lat: float, lon: float, margin_m: float = EDGE_MARGIN_M) -> bool:
    """Whether (lat, lon) lies ``margin_m`` inside the node grid, its four nearest nodes valid."""
    g = db.grid
    r, c = (float(v) for v in g.xy_to_rc(*g.lonlat_to_xy(lon, lat)))
    if not (margin_m / g.dy_m <= r <= g.n_rows - 1 - margin_m / g.dy_m
            and margin_m / g.dx_m <= c <= g.n_cols - 1 - margin_m / g.dx_m):
        return False
    r0, c0 = int(r), int(c)
    nodes = [(r0 + i) * g.n_cols + c0 + j for i in (0, 1) for j in (0, 1)]
    return bool(np.all(db.valid_nodes[nodes]))


def choose_site(world: BenchWorld, seed: int, rng: np.random.Generator) -> tuple[str, float, float]:
    """(kind, lat, lon) of the camera of ``seed``."""
    g = world.db.grid
    for _ in range(1000):
        if world.gap is None:
            r = rng.uniform(0.0, g.n_rows - 1.0)
            c = rng.uniform(0.0, g.n_cols - 1.0)
            lon, lat = (float(v) for v in g.xy_to_lonlat(*g.rc_to_xy(r, c)))
            kind = "random"
        else:
            kind = FOREST_SITES[seed % len(FOREST_SITES)]
            [(kind, row, col)] = world_gap.choose_sites_rc(world.gap, 1, [kind], rng)
            site = world_gap.site_of(world.gap, kind, row, col)
            lat, lon = site.lat, site.lon
        if inside_database(world.db, lat, lon):
            return kind, lat, lon
    raise SystemExit(f"{world.name}: no camera site {EDGE_MARGIN_M:.0f} m inside the database in 1000 draws")


def draw_spec(world: BenchWorld, seed: int, fov_deg: float) -> PhotoSpec:
    """The photo of ``seed`` in ``world``: the same place, pose, objects and focal error at every fov."""
    key = WORLD_KEYS[world.name]
    kind, lat, lon = choose_site(world, seed, np.random.default_rng([ISSUE, key, seed, 0]))
    rng = np.random.default_rng([ISSUE, key, seed, 1])
    yaw = float(rng.uniform(0.0, 360.0))
    pitch = float(rng.uniform(-PITCH_DEG, PITCH_DEG))
    roll = float(rng.uniform(-ROLL_DEG, ROLL_DEG))
    n_occ = int(rng.integers(OCCLUDERS[0], OCCLUDERS[1] + 1))
    drawn = []
    for _ in range(OCCLUDERS[1]):  # always as many draws, so the stream does not depend on the count
        share = float(rng.uniform(-OCCLUDER_VIEW_SHARE, OCCLUDER_VIEW_SHARE))
        drawn.append(Occluder(
            azimuth_deg=(yaw + share * fov_deg) % 360.0,
            width_deg=float(rng.uniform(*OCCLUDER_WIDTH_DEG)),
            raise_deg=float(rng.uniform(*OCCLUDER_RAISE_DEG)),
            distance_m=float(rng.uniform(*OCCLUDER_DISTANCE_M)),
            kind="pole" if rng.uniform() < 0.5 else "tree",
        ))
    u = float(rng.uniform(-FOCAL_ERROR, FOCAL_ERROR))
    offset_m = float(rng.uniform(0.0, CENTRE_OFFSET)) * SEARCH_RADIUS_M
    bearing = float(rng.uniform(0.0, 360.0))
    near_lon, near_lat, _ = Geod(ellps="WGS84").fwd(lon, lat, bearing, offset_m)
    return PhotoSpec(world.name, seed, float(fov_deg), kind, lat, lon, yaw, pitch, roll,
                     "cloudy" if seed % 2 == 0 else "mixed", tuple(drawn[:n_occ]), u,
                     float(near_lat), float(near_lon), float(SEARCH_RADIUS_M))


def cached_photo(work: Path, world: BenchWorld, spec: PhotoSpec) -> tuple[Path, dict]:
    """The photo of ``spec`` under ``work``/photos, rendered unless a photo of the same generator and
    spec is there; returns its path and its truth record (spec, skyline check, render time)."""
    folder = work / "photos"
    folder.mkdir(parents=True, exist_ok=True)
    photo = folder / f"{spec.name}.jpg"
    truth_path = folder / f"{spec.name}.truth.json"  # not PHOTO.json: a sidecar the locator would read
    want = spec.to_json()
    if photo.is_file() and truth_path.is_file():
        try:
            have = json.loads(truth_path.read_text())
        except (OSError, ValueError):
            have = {}
        if have.get("spec") == json.loads(json.dumps(want)):
            return photo, have
    t0 = time.perf_counter()
    recorded = RecordedSkylineFn(photo_skyline_fn(world.world, spec))
    image = write_photo(photo, world.world, spec, recorded)
    render_s = time.perf_counter() - t0
    check = skyline_check(image, recorded.table(), spec, step_deg=None)
    record = {"spec": want, "render_s": round(render_s, 2), "skyline_check": check}
    write_text_atomic(truth_path, json.dumps(record, indent=1) + "\n")
    return photo, json.loads(json.dumps(record))


# ----------------------------------------------------------------------------- locating and scoring


def locate_command(viper: Path, photo: Path, world: BenchWorld, spec: PhotoSpec, cache: Path) -> list[str]:
    """The locator as a user runs it: the DEM as the map, its database for the search area built into
    ``cache`` (a user's first photo of an area pays the build; ``build_s`` in the answer)."""
    return [str(viper), "locate", str(photo), "--map", str(world.map_path), "--cache", str(cache),
            "--near", f"{spec.near_lat:.7f},{spec.near_lon:.7f},{spec.near_radius_m:.0f}",
            "--json", "--truth", f"{spec.lat:.7f},{spec.lon:.7f}"]


def parse_answer(stdout: str) -> dict | None:
    """The JSON object the locator printed (the whole output, else its last line that parses)."""
    try:
        out = json.loads(stdout)
        return out if isinstance(out, dict) else None
    except ValueError:
        pass
    for line in reversed(stdout.strip().splitlines()):
        try:
            out = json.loads(line)
        except ValueError:
            continue
        if isinstance(out, dict):
            return out
    return None


def angle_diff_deg(a: float, b: float) -> float:
    return float((a - b + 180.0) % 360.0 - 180.0)


def score(spec: PhotoSpec, world: BenchWorld, answer: dict | None, exit_code: int, wall_s: float,
          stderr: str, skyline_in_frame: float | None = None, near: float | None = None) -> dict:
    """One seed's row: the answer against the truth (``skyline_in_frame``: the share of the photo's
    columns the skyline crosses; ``near``: :func:`near_share`)."""
    row: dict = {"world": spec.world, "seed": spec.seed, "fov_deg": spec.fov_deg, "site": spec.site,
                 "weather": spec.weather, "occluders": len(spec.occluders), "exif_f35_mm": spec.exif_f35_mm,
                 "f35_mm": round(spec.f35_mm, 3), "exif_focal_err": round(spec.exif_f35_mm / spec.f35_mm - 1.0, 4),
                 "skyline_in_frame": skyline_in_frame, "near_share": near, "exit": exit_code,
                 "wall_s": round(wall_s, 2)}
    if answer is None or "lat" not in answer or "lon" not in answer:
        row["failed"] = stderr.strip().splitlines()[-1] if stderr.strip() else f"exit {exit_code}, no JSON answer"
        return row
    az_deg, _, d_m = Geod(ellps="WGS84").inv(float(answer["lon"]), float(answer["lat"]), spec.lon, spec.lat)
    truth = answer.get("truth") or {}
    timing = answer.get("timing") or {}
    orient = answer.get("orientation") or {}
    row.update({
        "lat": answer["lat"], "lon": answer["lon"], "error_m": round(float(d_m), 2),
        "error_cells": round(float(d_m) / world.cell_m, 3), "status": answer.get("status"),
        "node_cell_m": _node_cell_m(answer),
        "ambiguous": answer.get("ambiguous"), "radius95_m": answer.get("radius95_m"),
        "region_cells": (answer.get("region") or {}).get("n_cells"),
        "truth_error_m": truth.get("error_m"), "in_region": truth.get("in_region"),
        "in_ellipse": truth.get("in_ellipse"), "build_s": timing.get("build_s"), "total_s": timing.get("total_s"),
        "mahalanobis2": _mahalanobis2(answer.get("covariance_m2"), float(d_m), float(az_deg)),
    })
    if orient:
        true_f = spec.intrinsics.fx
        row.update({
            "yaw_err_deg": round(angle_diff_deg(float(orient["yaw_deg"]), spec.yaw_deg), 3),
            "pitch_err_deg": round(float(orient["pitch_deg"]) - spec.pitch_deg, 3),
            "roll_err_deg": round(float(orient["roll_deg"]) - spec.roll_deg, 3),
            "focal_err": round(float(orient["focal_px"]) / true_f - 1.0, 4),
        })
    return row


def _mahalanobis2(cov_m2: list | None, distance_m: float, azimuth_deg: float) -> float | None:
    """The truth's squared Mahalanobis distance from the answer under its covariance (east, north):
    chi-square with 2 degrees of freedom when the covariance is right (5.99 at 95 %)."""
    if not cov_m2:
        return None
    cov = np.asarray(cov_m2, dtype=float)
    e = distance_m * np.array([math.sin(math.radians(azimuth_deg)), math.cos(math.radians(azimuth_deg))])
    try:
        return round(float(e @ np.linalg.solve(cov, e)), 3)
    except np.linalg.LinAlgError:
        return None


def _node_cell_m(answer: dict) -> float | None:
    """The node spacing (m) of the database the locator searched (geometric mean), from its record."""
    size = (answer.get("region") or {}).get("cell_size_m")
    return round(math.sqrt(float(size[0]) * float(size[1])), 2) if size else None


def said_ok(row: dict) -> bool:
    """Whether the locator itself vouched for the answer: its own ambiguity flag where the JSON has
    one (the status, under --truth, also knows where the truth is), else the status."""
    if isinstance(row.get("ambiguous"), bool):
        return not row["ambiguous"]
    return row.get("status") == "ok"


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")


def summarise(rows: list[dict]) -> dict[str, float]:
    n = len(rows)
    answered = [r for r in rows if "error_cells" in r]
    right = [r for r in answered if r["error_cells"] <= 2.0]
    times = [float(r["total_s"] if r.get("total_s") is not None else r["wall_s"]) for r in answered]

    def share(items: list[dict], key: str) -> float:
        return sum(1 for r in items if r.get(key) is True) / n if n else float("nan")

    def med_abs(key: str) -> float:
        return _median([abs(float(r[key])) for r in right if r.get(key) is not None])

    sky = [r for r in rows if (r.get("skyline_in_frame") or 0.0) >= NO_SKYLINE]
    far = [r for r in rows if r.get("near_share") is not None and r["near_share"] <= NEAR_VIEW_SHARE]
    return {
        "near_slope_photos": sum(1 for r in rows if (r.get("near_share") or 0.0) > NEAR_VIEW_SHARE),
        "within_2_cells_not_near": (sum(1 for r in far if r.get("error_cells", math.inf) <= 2.0) / len(far)
                                    if far else float("nan")),
        "photos": n, "failed": n - len(answered), "no_skyline": n - len(sky),
        "within_2_cells": len(right) / n if n else float("nan"),
        "within_2_cells_with_skyline": (sum(1 for r in sky if r.get("error_cells", math.inf) <= 2.0) / len(sky)
                                        if sky else float("nan")),
        "median_error_m": _median([r["error_m"] for r in answered]),
        "median_error_cells": _median([r["error_cells"] for r in answered]),
        "status_ok": sum(1 for r in answered if r.get("status") == "ok") / n if n else float("nan"),
        "wrong_and_ok": sum(1 for r in answered if r["error_cells"] > 2.0 and said_ok(r)),
        "right_but_ambiguous": sum(1 for r in right if r.get("status") != "ok") / n if n else float("nan"),
        "truth_in_region": share(answered, "in_region"), "truth_in_ellipse": share(answered, "in_ellipse"),
        "yaw_deg": med_abs("yaw_err_deg"), "pitch_deg": med_abs("pitch_err_deg"),
        "roll_deg": med_abs("roll_err_deg"), "focal": med_abs("focal_err"),
        "exif_focal_max": max((abs(float(r["exif_focal_err"])) for r in rows), default=float("nan")),
        "time_median_s": _median(times),
        "time_p90_s": float(np.percentile(times, 90)) if times else float("nan"),
    }


COLUMNS = ["date", "commit", "world", "fov (deg)", "seeds (photos)", "within 2 cells (target >= 90 % at 60)",
           "no skyline: photos, within 2 cells of the others", "median error (m, cells)", "status ok",
           "wrong and ok (target 0)", "right but ambiguous", "truth in region", "truth in ellipse",
           "median abs yaw / pitch / roll (deg)", "median abs focal (largest EXIF focal error)",
           "time median / p90 (s)", "failed", "load", "note"]
HEADER = """# Synthetic photos located by `viper locate` (bench/photo_locate.py, issue 31)

One photo per seed, 1280 x 720 px, no distortion: a random camera 1.5 m above the world's surface (at
least 1.5 km inside the database), yaw uniform 0-360 deg, pitch +-5, roll +-3, rendered by
appliance.vision.synth (weather cloudy / mixed alternating) with 1-3 near objects the map lacks (the
skyline raised by 2-10 deg over 1-4 deg of azimuth). The lens comes only from EXIF
FocalLengthIn35mmFilm, off by up to +-3 % and then rounded to 1 mm (up to about +-5 % in all at 90
deg). Search area: a 10 km^2 circle (r 1784 m) whose centre is 0-60 % of the radius from the camera.

- **jacksboro**: world = map = jacksboro_fault_dem.npz (database bench/cache/jacksboro-native.viperdb).
- **forest**: world = SRTM N44W072 + canopy, clearings and 4 m noise (bench/world_gap.py, world seed 1);
  map = the bare tile. Cameras in clearings, on summits and on open ground.

Seeds 1000-1059 are the reported set, not used in development (which used seeds 1-20). Cell = geometric
mean of the database's node spacing. "Wrong and ok": more than two cells off and not flagged
ambiguous by the locator (its own "ambiguous" field when present). Orientation and focal errors are
medians over the answers within two cells. "No skyline": photos whose skyline crosses fewer than half
the columns (the frame all ground or all sky; they stay in the other figures). Commit: the checkout
of the viper that ran.

"""


def record(world: str, fov: float, seeds: str, s: dict[str, float], commit: str, load: str, note: str) -> None:
    target = f" (target {100 * TARGET_WITHIN_2:.0f} %)" if fov == 60.0 else ""
    cells = [
        str(date.today()), commit, world, f"{fov:g}", f"{seeds} ({s['photos']})",
        f"{100 * s['within_2_cells']:.0f} %{target}",
        f"{s['no_skyline']}, {100 * s['within_2_cells_with_skyline']:.0f} %",
        f"{s['median_error_m']:.0f} ({s['median_error_cells']:.2f})",
        f"{100 * s['status_ok']:.0f} %", str(s["wrong_and_ok"]), f"{100 * s['right_but_ambiguous']:.0f} %",
        f"{100 * s['truth_in_region']:.0f} %", f"{100 * s['truth_in_ellipse']:.0f} %",
        f"{s['yaw_deg']:.2f} / {s['pitch_deg']:.2f} / {s['roll_deg']:.2f}",
        f"{100 * s['focal']:.1f} % ({100 * s['exif_focal_max']:.1f} %)",
        f"{s['time_median_s']:.1f} / {s['time_p90_s']:.1f}", str(s["failed"]), load,
        f"{note} {platform.machine()}".strip(),
    ]
    header = HEADER + "| " + " | ".join(COLUMNS) + " |\n" + "|---" * len(COLUMNS) + "|\n"
    append_result(RESULTS, header, "| " + " | ".join(cells) + " |\n")


def seed_range(text: str) -> list[int]:
    a, sep, b = text.partition("-")
    try:
        lo, hi = int(a), int(b) if sep else int(a)
    except ValueError:
        raise SystemExit(f"--seeds {text!r}: expected A-B, e.g. 1000-1059") from None
    if hi < lo:
        raise SystemExit(f"--seeds {text!r}: the end comes before the start")
    return list(range(lo, hi + 1))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--world", default="jacksboro,forest", help="comma-separated: jacksboro, forest")
    ap.add_argument("--seeds", default=REPORTED_SEEDS, help="A-B (reported set 1000-1059; development 1-20)")
    ap.add_argument("--fov", type=float, default=60.0, help="horizontal field of view (deg)")
    ap.add_argument("--fov-sweep", action="store_true", help="fields of view 30, 45, 60 and 90 deg")
    ap.add_argument("--viper", type=Path, default=VIPER, help="the viper executable to measure")
    ap.add_argument("--work", type=Path, default=WORK, help="photos and per-seed answers (default: %(default)s)")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds allowed per locate")
    ap.add_argument("--dry-run", action="store_true", help="render the photos, print the commands, run nothing")
    ap.add_argument("--no-record", action="store_true", help="do not append to bench/results/photo_locate.md")
    ap.add_argument("--note", default="", help="free text for the results rows")
    args = ap.parse_args()
    seeds = seed_range(args.seeds)
    fovs = list(FOV_SWEEP) if args.fov_sweep else [args.fov]
    names = [w.strip() for w in args.world.split(",") if w.strip()]
    unknown = sorted(set(names) - set(WORLD_KEYS))
    if unknown:
        raise SystemExit(f"--world: unknown {', '.join(unknown)}; expected jacksboro, forest")
    if not args.dry_run and not args.viper.exists():
        raise SystemExit(f"--viper {args.viper}: not found")
    commit = checkout_commit(args.viper) if args.viper.exists() else "unknown"
    load_start = os.getloadavg()[0]
    for name in names:
        t0 = time.perf_counter()
        world = make_world(name)
        print(f"world {name}: cell {world.cell_m:.1f} m, database {world.db_path.name}, "
              f"{time.perf_counter() - t0:.1f} s", file=sys.stderr)
        for fov in fovs:
            rows: list[dict] = []
            runs = args.work / "runs" / commit / f"{name}-fov{fov:g}-seeds{seeds[0]}-{seeds[-1]}.jsonl"
            for seed in seeds:
                spec = draw_spec(world, seed, fov)
                photo, truth = cached_photo(args.work, world, spec)
                check = truth["skyline_check"]
                cmd = locate_command(args.viper, photo, world, spec, args.work / "cache")
                print(f"{spec.name}: {spec.site} {spec.lat:.5f},{spec.lon:.5f} yaw {spec.yaw_deg:6.1f} "
                      f"pitch {spec.pitch_deg:+.1f} roll {spec.roll_deg:+.1f} {spec.weather}, "
                      f"{len(spec.occluders)} objects, EXIF {spec.exif_f35_mm} mm (true {spec.f35_mm:.1f}); "
                      f"skyline crosses {check.get('skyline_in_frame')} of the columns, lies where the camera "
                      f"model says: median {check['median_abs_px']} px, {check['within_1_5_px']} within 1.5 px",
                      flush=True)
                if args.dry_run:
                    print("$", " ".join(cmd), flush=True)
                    continue
                t1 = time.perf_counter()
                try:
                    out = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
                    code, stdout, stderr = out.returncode, out.stdout, out.stderr
                except subprocess.TimeoutExpired:
                    code, stdout, stderr = -1, "", f"timed out after {args.timeout:.0f} s"
                row = score(spec, world, parse_answer(stdout) if code == 0 else None, code,
                            time.perf_counter() - t1, stderr, check.get("skyline_in_frame"),
                            near_share(world.world, spec))
                rows.append(row)
                runs.parent.mkdir(parents=True, exist_ok=True)
                write_text_atomic(runs, "".join(json.dumps(r) + "\n" for r in rows))
                print(f"  near-slope share of the view {row['near_share']}", flush=True)
                if "failed" in row:
                    print(f"  failed: {row['failed']}", flush=True)
                else:
                    print(f"  error {row['error_m']:7.1f} m ({row['error_cells']:5.2f} cells) {row['status']} "
                          f"in region {row['in_region']} in ellipse {row['in_ellipse']} "
                          f"yaw {row.get('yaw_err_deg')} pitch {row.get('pitch_err_deg')} "
                          f"roll {row.get('roll_err_deg')} focal {row.get('focal_err')} "
                          f"total {row['total_s']} s", flush=True)
            if args.dry_run or not rows:
                continue
            s = summarise(rows)
            print(json.dumps({"world": name, "fov_deg": fov, "seeds": args.seeds, "commit": commit,
                              **{k: round(v, 3) if isinstance(v, float) else v for k, v in s.items()}}))
            load = f"{load_start:.1f}-{os.getloadavg()[0]:.1f}"
            if not args.no_record:
                record(name, fov, args.seeds, s, commit, load, args.note)
            print(f"answers in {runs}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
