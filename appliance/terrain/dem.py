"""DEM ingest: every map the appliance reads becomes one :class:`~appliance.terrain.elevation.Dem`.

Formats go through rasterio/GDAL (GeoTIFF, USGS ASCII DEM, SRTM .hgt, PDS labels such as the LOLA
Moon DEM) plus two readers GDAL lacks: matplotlib's sample ``.npz`` grids (jacksboro, whose
``ymin``/``ymax`` are swapped, and topobathy) and ArcInfo ``.e00`` export grids.

Heights are metres above the body's reference (geoid on Earth, the 1737.4 km sphere on the Moon);
heights stored in feet are converted; nodata is NaN, never 0.
"""

from __future__ import annotations

import hashlib
import logging
import math
import re
import tokenize
import warnings
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from pyproj import CRS

from appliance.bodies import EARTH, MARS, MOON, Body
from appliance.errors import DemError
from appliance.inputs import check_regular, read_text_bounded
from appliance.native import native_messages
from appliance.terrain.elevation import Dem, affine_apply

log = logging.getLogger(__name__)
FEET_UNITS = {"ft", "feet", "foot", "us-ft", "us survey foot", "us_survey_foot"}
DEMO_DEM = "jacksboro"


def body_of_crs(crs: CRS) -> Body:
    ell = crs.ellipsoid
    a = ell.semi_major_metre if ell is not None else EARTH.semi_major_m
    for body in (MOON, MARS):
        if abs(a - body.semi_major_m) < 0.01 * body.semi_major_m:
            return body
    if abs(a - EARTH.semi_major_m) < 0.01 * EARTH.semi_major_m:
        return EARTH
    raise DemError(f"CRS with semi-major axis {a:.0f} m is not Earth, Moon or Mars")


def _sha256(path: Path, extra: bytes = b"") -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    h.update(extra)
    return h.hexdigest()


def demo_dem_path() -> Path:
    """matplotlib's sample DEM (Jacksboro fault, Tennessee): the appliance's embedded default map."""
    import matplotlib.cbook

    return Path(matplotlib.cbook.get_sample_data("jacksboro_fault_dem.npz", asfileobj=False))


def load_dem(path: str | Path | None = None, crs: str | None = None) -> Dem:
    """Read a DEM; ``None`` or ``"jacksboro"`` gives the embedded demo map.

    ``crs`` overrides (or supplies) the coordinate reference system, for files that carry none.
    """
    if path is None or str(path) == DEMO_DEM:
        path = demo_dem_path()
    p = Path(path)
    if not p.exists():
        raise DemError(f"{p}: DEM file not found")
    if p.is_dir():
        raise DemError(f"{p}: is a folder, not a DEM file")
    try:
        check_regular(p, "DEM", DemError)
    except OSError as exc:
        if isinstance(exc, DemError):
            raise
        raise DemError(f"{p}: cannot read DEM: {exc.strerror or exc}") from None
    suffix = p.suffix.lower()
    try:
        if suffix == ".npz":
            dem = _load_npz(p)
        elif suffix == ".e00":
            dem = _load_e00(p)
        else:
            try:
                dem = _load_gdal(p, crs)
            except DemError:
                tile = _srtm_size(p)
                if tile is None:
                    raise
                dem = _load_srtm_raw(p, tile)
    except DemError:
        raise
    except (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DemError(f"{p}: cannot read DEM: {first}") from None
    if crs is not None and suffix in (".npz", ".e00"):
        dem = Dem(dem.elevation_m, dem.transform, _parse_crs(crs, p), dem.body, dem.source, dem.sha256)
    if not np.isfinite(dem.elevation_m).any():
        raise DemError(f"{p}: every cell is nodata")
    if min(dem.shape) < 2:
        raise DemError(f"{p}: a DEM needs at least 2x2 cells, got {dem.shape[0]}x{dem.shape[1]}")
    _check_extent(dem, p)
    return dem


def _check_extent(dem: Dem, p: Path) -> None:
    """Latitudes within the poles and a finite, positive ground resolution."""
    rows, cols = dem.shape
    c = np.array([0.5, cols - 0.5, 0.5, cols - 0.5, cols / 2.0])
    r = np.array([0.5, 0.5, rows - 0.5, rows - 0.5, rows / 2.0])
    x, y = affine_apply(dem.transform, c, r)
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise DemError(f"{p}: the georeferencing gives non-finite coordinates")
    if dem.is_geographic:
        lat = y
        if np.max(np.abs(lat)) > 90.0 + 1e-9:
            worst = float(lat[np.argmax(np.abs(lat))])
            raise DemError(f"{p}: pixel centres reach latitude {worst:.6g} deg, beyond the pole (|lat| <= 90)")
    try:
        res = dem.resolution_m()
    except Exception as exc:  # pyproj raises ProjError, a plain Exception subclass
        raise DemError(f"{p}: the georeferencing cannot be turned into ground distances: {exc}") from None
    if not all(math.isfinite(v) and v > 0 for v in res):
        raise DemError(f"{p}: the georeferencing gives no ground resolution ({res[0]} x {res[1]} m)")


#: SRTM tiles: samples per side by file size (int16 big-endian, rows north to south).
SRTM_SIDES = {1201 * 1201 * 2: 1201, 3601 * 3601 * 2: 3601}
_TILE_NAME = re.compile(r"([NS])(\d{2})([EW])(\d{3})", re.IGNORECASE)


def _srtm_size(p: Path) -> int | None:
    """Samples per side when ``p`` has the size of an SRTM tile (and is not a TIFF), else None."""
    try:
        side = SRTM_SIDES.get(p.stat().st_size)
        if side is None:
            return None
        with p.open("rb") as fh:
            magic = fh.read(4)
    except OSError:
        return None
    return None if magic in (b"II*\0", b"MM\0*") else side


def _load_srtm_raw(p: Path, side: int) -> Dem:
    """An SRTM tile under another file name: the tile's corner from an N44W072-like part of the name."""
    spacing = "3 arc-second" if side == 1201 else "1 arc-second"
    match = _TILE_NAME.search(p.name)
    if match is None:
        raise DemError(
            f"{p}: has the size of a {spacing} SRTM tile ({side}x{side} int16) but its name gives no tile"
            " corner: name it after the tile, e.g. N44W072.hgt"
        )
    ns, lat_s, ew, lon_s = match.groups()
    lat = int(lat_s) * (1 if ns.upper() == "N" else -1)
    lon = int(lon_s) * (1 if ew.upper() == "E" else -1)
    if lat >= 90 or lat < -90 or lon >= 180 or lon < -180:
        raise DemError(f"{p}: tile corner {match.group(0)} is not on the Earth")
    raw = np.fromfile(p, dtype=">i2").reshape(side, side)
    data = raw.astype(np.float64)
    data[raw == -32768] = np.nan
    d = 1.0 / (side - 1)
    transform = Affine(d, 0.0, lon - d / 2.0, 0.0, -d, lat + 1.0 + d / 2.0)
    return Dem(data, transform, CRS.from_epsg(4326), EARTH, str(p), _sha256(p), {"driver": "SRTMHGT", "units": "m"})


def _parse_crs(text: str, p: Path) -> CRS:
    try:
        return CRS.from_user_input(text)
    except Exception as exc:  # pyproj raises CRSError, a plain Exception subclass
        raise DemError(f"{p}: unknown CRS {text!r}: {exc}") from None


def _load_gdal(p: Path, crs_override: str | None, window: tuple[int, int, int, int] | None = None,
               sha256: str | None = None, shape_only: bool = False) -> Dem:
    """Read a GDAL raster: the whole of it, or the (row0, col0, n_rows, n_cols) ``window`` (a tile's
    share of a large map, read without the rest); ``shape_only`` reads no heights at all (a map's
    georeferencing, to plan a grid over it) and ``sha256`` spares hashing a file already hashed."""
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioError
    from rasterio.windows import Window

    open_path = p
    if p.suffix.lower() == ".img":
        for label in (p.with_suffix(".LBL"), p.with_suffix(".lbl")):
            if label.exists():
                open_path = label
                break
    try:
        with native_messages() as said, warnings.catch_warnings():
            # a missing transform is this reader's own error below, not a library warning
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(open_path) as ds:
                _check_raw_size(p, ds)
                if window is None and not shape_only:
                    _check_pixels(p, int(ds.width), int(ds.height))
                win = None if window is None else Window(window[1], window[0], window[3], window[2])
                if shape_only:
                    band = np.ma.masked_all((1, 1))
                    shape = (int(ds.height), int(ds.width))
                else:
                    band = ds.read(1, masked=True, window=win)
                    shape = band.shape
                scale = float(ds.scales[0] or 1.0)
                offset = float(ds.offsets[0] or 0.0)
                units = (ds.units[0] or ds.tags(1).get("UNITTYPE") or ds.tags().get("ZUNITS") or "").strip()
                transform = ds.transform if win is None else ds.window_transform(win)
                crs_wkt = ds.crs.to_wkt() if ds.crs else None
                driver = ds.driver
    except RasterioError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        first = first.replace(" See previous exception for details.", "").strip()
        raise DemError(f"{p}: not a readable DEM ({first}: the file is damaged or truncated)") from None
    for line in said:
        log.debug("%s: %s", p, line)
    if crs_override is not None:
        crs = _parse_crs(crs_override, p)
    elif crs_wkt is None:
        raise DemError(f"{p}: the file carries no CRS (give one with --crs, e.g. EPSG:32632)")
    else:
        crs = _parse_crs(crs_wkt, p)
    if transform.is_identity:
        raise DemError(f"{p}: the file carries no georeferencing")
    body = body_of_crs(crs)
    meta = {"driver": driver, "units": units or "m"}
    if shape_only:
        # a read-only array of the map's shape holding no memory: the georeferencing alone
        empty = np.broadcast_to(np.float64(np.nan), shape)
        return Dem(empty, transform, crs, body, str(p), sha256 or "", meta)
    with np.errstate(invalid="ignore", over="ignore"):
        data = np.ma.filled(band.astype(np.float64), np.nan)
    data[~(np.abs(data) <= 1e30)] = np.nan
    # PDS planetary DEMs store radius = raw * scale + reference radius: keep height above the sphere.
    if offset > 1e5:
        offset = 0.0
    data = data * scale + offset
    if units.lower() in FEET_UNITS:
        data *= 0.3048
    sha = sha256 or _sha256(p)
    return Dem(data, transform, crs, body, str(p), sha, meta)


#: Pixels of a map read whole (800 MB of heights); a larger map is built tile by tile (precompute --tiles).
MAX_DEM_PIXELS = 100_000_000


def _check_pixels(p: Path, width: int, height: int) -> None:
    """Refuse, before reading it, a map too large to hold whole."""
    if width * height > MAX_DEM_PIXELS:
        raise DemError(f"{p}: {width} x {height} pixels, more than the {MAX_DEM_PIXELS:,} a map read whole may have "
                       "(build its database with precompute --tiles, which reads it tile by tile)")


def _check_raw_size(p: Path, ds: Any) -> None:
    """A raw image (PDS, SRTM, ENVI...) shorter than its samples: say so before GDAL fails to read it."""
    driver = ds.driver
    if driver not in ("PDS", "PDS4", "ISIS3", "SRTMHGT", "EHdr", "ENVI"):
        return
    width, height = int(ds.width), int(ds.height)
    need = width * height * np.dtype(ds.dtypes[0]).itemsize
    image = p
    if p.suffix.lower() == ".lbl":
        for alt in (p.with_suffix(".IMG"), p.with_suffix(".img")):
            if alt.exists():
                image = alt
                break
    have = image.stat().st_size
    if have < need:
        raise DemError(
            f"{image}: truncated: {have} bytes, but its {width}x{height} samples need at least {need}"
        )


def _load_npz(p: Path) -> Dem:
    # zipfile raises NotImplementedError for a compression method, encryption or zip version it does not
    # read and RuntimeError for an encrypted member; numpy's .npy header parser TokenError or SyntaxError for
    # a header that is not a Python literal
    try:
        return _read_npz(p)
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError, NotImplementedError, RuntimeError,
            tokenize.TokenError, SyntaxError) as exc:
        if isinstance(exc, DemError):
            raise
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DemError(f"{p}: not a readable .npz grid ({first}): the file is damaged or truncated") from None


def _npz_shapes(p: Path) -> dict[str, tuple[int, ...]]:
    """Each array's shape in the .npz archive, from its .npy header, without reading the data."""
    shapes: dict[str, tuple[int, ...]] = {}
    with zipfile.ZipFile(p) as zf:
        for name in zf.namelist():
            if not name.endswith(".npy"):
                continue
            with zf.open(name) as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    shape, _, _ = np.lib.format.read_array_header_1_0(fh)
                elif version == (2, 0):
                    shape, _, _ = np.lib.format.read_array_header_2_0(fh)
                else:
                    raise DemError(f"{p}: {name} is a .npy of format version {version}, not 1.0 or 2.0")
            shapes[name[:-4]] = tuple(int(v) for v in shape)
    return shapes


def _read_npz(p: Path) -> Dem:
    for name, shape in _npz_shapes(p).items():
        if len(shape) == 2:
            _check_pixels(p, shape[1], shape[0])
        elif int(np.prod(shape, dtype=np.float64)) > MAX_DEM_PIXELS:
            raise DemError(f"{p}: array {name} holds {int(np.prod(shape, dtype=np.float64)):,} values, more than "
                           f"the {MAX_DEM_PIXELS:,} a map read whole may have")
    with np.load(p) as z:
        keys = set(z.files)
        if {"elevation", "dx", "dy", "xmin", "xmax", "ymin", "ymax"} <= keys:
            elev = z["elevation"].astype(np.float64)
            dx, dy = float(z["dx"]), float(z["dy"])
            west = min(float(z["xmin"]), float(z["xmax"]))
            # The sample file's ymin and ymax are swapped: take the larger as the north edge.
            north = max(float(z["ymin"]), float(z["ymax"]))
            transform = Affine(dx, 0.0, west, 0.0, -dy, north)
        elif {"topo", "longitude", "latitude"} <= keys:
            topo = z["topo"].astype(np.float64)
            lon = z["longitude"].astype(np.float64)
            lat = z["latitude"].astype(np.float64)
            lon = np.where(lon > 180.0, lon - 360.0, lon)
            elev, transform = _regularise(topo, lon, lat)
        else:
            raise DemError(f"{p}: unknown .npz layout (keys: {', '.join(sorted(keys))})")
    return Dem(elev, transform, CRS.from_epsg(4326), EARTH, str(p), _sha256(p), {"driver": "npz"})


def _regularise(topo: np.ndarray, lon: np.ndarray, lat: np.ndarray) -> tuple[np.ndarray, Affine]:
    """Resample a grid with irregular axes onto a regular north-up grid of the mean spacing."""
    from scipy.interpolate import RegularGridInterpolator

    if lat[0] > lat[-1]:
        lat, topo = lat[::-1], topo[::-1]
    dlon = (lon[-1] - lon[0]) / (len(lon) - 1)
    dlat = (lat[-1] - lat[0]) / (len(lat) - 1)
    interp = RegularGridInterpolator((lat, lon), topo, bounds_error=False, fill_value=np.nan)
    glat = lat[-1] - dlat * np.arange(len(lat))
    glon = lon[0] + dlon * np.arange(len(lon))
    mlat, mlon = np.meshgrid(glat, glon, indexing="ij")
    elev = interp(np.stack([mlat.ravel(), mlon.ravel()], axis=1)).reshape(mlat.shape)
    transform = Affine(dlon, 0.0, lon[0] - dlon / 2, 0.0, -dlat, lat[-1] + dlat / 2)
    return elev, transform


#: The largest .e00 text read (about 16 million heights at 16 characters each).
MAX_E00_BYTES = 256 << 20

_E00_FLOAT = re.compile(r"[-+]?\d*\.\d+E[-+]\d+")


def _load_e00(p: Path) -> Dem:
    """ArcInfo uncompressed export grid (``GRD`` section, ``PRJ`` block for the CRS)."""
    lines = read_text_bounded(p, MAX_E00_BYTES, "DEM", DemError, encoding="latin-1").splitlines()
    try:
        start = next(i for i, ln in enumerate(lines) if ln.startswith("GRD "))
    except StopIteration:
        raise DemError(f"{p}: no GRD section (compressed or non-grid .e00 files are not supported)") from None
    head = lines[start + 1].split()
    ncols, nrows = int(head[0]), int(head[1])
    if ncols < 1 or nrows < 1:
        raise DemError(f"{p}: the GRD header gives {ncols} x {nrows} cells")
    _check_pixels(p, ncols, nrows)
    nodata_match = _E00_FLOAT.findall(lines[start + 1])
    nodata = float(nodata_match[-1]) if nodata_match else -3.4028234663853e38
    cell = [float(v) for v in _E00_FLOAT.findall(lines[start + 2])]
    ll = [float(v) for v in _E00_FLOAT.findall(lines[start + 3])]
    per_row = math.ceil(ncols / 5)
    body = lines[start + 5 : start + 5 + nrows * per_row]
    if len(body) < nrows * per_row:
        raise DemError(f"{p}: grid truncated ({len(body)} of {nrows * per_row} lines)")
    elev = np.empty((nrows, ncols))
    for r in range(nrows):
        row = _E00_FLOAT.findall("".join(body[r * per_row : (r + 1) * per_row]))
        if len(row) < ncols:
            raise DemError(f"{p}: row {r} has {len(row)} values, expected {ncols}")
        elev[r] = [float(v) for v in row[:ncols]]
    elev[(elev == nodata) | (np.abs(elev) > 1e30)] = np.nan
    transform = Affine(cell[0], 0.0, ll[0], 0.0, -cell[1], ll[1] + nrows * cell[1])
    prj = {}
    for i in range(start, len(lines)):
        if lines[i].startswith("PRJ "):
            for ln in lines[i + 1 :]:
                if ln.startswith("EOP"):
                    break
                parts = ln.split(None, 1)
                if len(parts) == 2:
                    prj[parts[0].lower()] = parts[1].strip()
            break
    crs = _e00_crs(prj, p)
    return Dem(elev, transform, crs, EARTH, str(p), _sha256(p), {"driver": "e00"})


def _e00_crs(prj: dict[str, str], p: Path) -> CRS:
    proj = prj.get("projection", "").upper()
    datum = prj.get("datum", "").upper()
    if proj == "UTM" and "zone" in prj:
        zone = int(prj["zone"])
        base = {"NAD83": 26900, "NAD27": 26700, "WGS84": 32600}.get(datum)
        if base is not None and 1 <= zone <= 60:
            return CRS.from_epsg(base + zone)
    if proj == "GEOGRAPHIC":
        return CRS.from_epsg(4326)
    raise DemError(f"{p}: unknown CRS in the PRJ block (projection {proj!r}, datum {datum!r})")
