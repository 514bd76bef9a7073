"""Several DEM files (adjacent tiles) read as one map, through a GDAL VRT.

A VRT is a small XML file that GDAL reads as one raster made of its sources: a windowed read of it
reads only the files under the window, so a tiled build's task never loads more than its own share
of a map larger than memory, and the whole mosaic still loads as one :class:`Dem` for a
single-process build.

The tiles must share one CRS and one pixel size, on one pixel lattice.  Adjacent SRTM tiles repeat
their edge row or column: on the common lattice both copies land on the same pixel, which appears
once (N43E006 + N43E007 make 1201 rows x 2401 columns).  Where a source is void (nodata) another
source's value at that pixel shows through; a pixel void in every source stays nodata (NaN).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.sax.saxutils import escape

import numpy as np

from appliance.atomic import atomic_output
from appliance.errors import DemError
from appliance.terrain.dem import DEMO_DEM, Dem, _load_gdal, _sha256, demo_dem_path, load_dem

#: the VRT a tiled build writes into its output folder for a DEM given as several files
MOSAIC_VRT = "mosaic.vrt"
_NON_GDAL = (".npz", ".e00")


@dataclass(frozen=True)
class MapSource:
    """The raster a build reads (one DEM file, a VRT given by the user, or one written for several
    files), with the identity of the files it was given: their names and SHA-256s, and one SHA-256
    for the map as a whole (the file's own for a single file)."""

    path: str
    crs: str | None
    sources: tuple[tuple[str, str], ...]
    sha256: str

    @property
    def name(self) -> str:
        return "+".join(name for name, _ in self.sources)

    @property
    def gdal(self) -> bool:
        """True when the map is read through GDAL, so that windows of it can be read alone."""
        return Path(self.path).suffix.lower() not in _NON_GDAL

    def load(self) -> Dem:
        """The whole map as one :class:`Dem` (its identity that of the files given)."""
        dem = load_dem(self.path, crs=self.crs)
        return Dem(dem.elevation_m, dem.transform, dem.crs, dem.body, self._source(dem), self.sha256,
                   dem.metadata)

    def header(self) -> Dem:
        """The map's georeferencing and shape without its heights, to plan grids over it."""
        if not self.gdal:
            return self.load()
        dem = _load_gdal(Path(self.path), self.crs, sha256=self.sha256, shape_only=True)
        return Dem(dem.elevation_m, dem.transform, dem.crs, dem.body, self._source(dem), self.sha256,
                   dem.metadata)

    def window(self, row0: int, col0: int, n_rows: int, n_cols: int) -> Dem:
        """Rows row0.. and columns col0.. of the map, read alone where the format allows."""
        if self.gdal:
            dem = _load_gdal(Path(self.path), self.crs, (row0, col0, n_rows, n_cols), sha256=self.sha256)
        else:
            whole = self.load()
            sub = np.array(whole.elevation_m[row0 : row0 + n_rows, col0 : col0 + n_cols])
            transform = whole.transform * whole.transform.translation(col0, row0)
            dem = Dem(sub, transform, whole.crs, whole.body, whole.source, whole.sha256, whole.metadata)
        return Dem(dem.elevation_m, dem.transform, dem.crs, dem.body, self._source(dem), self.sha256,
                   dem.metadata)

    def _source(self, dem: Dem) -> str:
        return dem.source if len(self.sources) == 1 else self.name


def open_map(paths: list[str], vrt_path: str | Path | None, crs: str | None = None) -> MapSource:
    """The map made of ``paths``: one file as it is, several as a VRT written (atomically) at
    ``vrt_path``."""
    if not paths:
        raise DemError("no DEM file given")
    if len(paths) == 1:
        p = demo_dem_path() if paths[0] == DEMO_DEM else Path(paths[0])
        if not p.is_file():
            load_dem(p, crs=crs)  # the one-line error for a missing file or a folder
        sha = _sha256(p)
        return MapSource(str(p), crs, ((p.name, sha),), sha)
    if vrt_path is None:
        raise DemError("several DEM files need a folder for their mosaic")
    files = [Path(p) for p in paths]
    write_vrt(files, vrt_path, crs)
    sources = tuple((f.name, _sha256(f)) for f in files)
    whole = hashlib.sha256("\n".join(f"{n} {s}" for n, s in sources).encode()).hexdigest()
    return MapSource(str(vrt_path), crs, sources, whole)


def write_vrt(paths: list[Path], vrt_path: str | Path, crs: str | None = None) -> Path:
    """Write the VRT of adjacent DEM files; refuses different CRSs or pixel lattices in one line."""
    infos = [_source_info(p, crs) for p in paths]
    offsets = _lattice_offsets(infos)
    with atomic_output(vrt_path) as tmp:
        tmp.write_text("\n".join(_vrt_lines(infos, offsets)))
    return Path(vrt_path)


def _source_info(p: Path, crs: str | None) -> dict[str, Any]:
    """The size, georeferencing and sample type of one source of a mosaic (``crs`` in place of its own)."""
    import rasterio
    import rasterio.crs
    from rasterio.errors import RasterioError

    if not p.is_file():
        load_dem(p)  # the one-line error for a missing file or a folder
    if p.suffix.lower() in _NON_GDAL:
        raise DemError(f"{p}: a mosaic is made of GDAL rasters (GeoTIFF, .hgt, VRT...), not {p.suffix} grids")
    try:
        with rasterio.open(p) as ds:
            info = {
                "path": p, "width": ds.width, "height": ds.height, "transform": ds.transform,
                "crs": rasterio.crs.CRS.from_user_input(crs) if crs else ds.crs, "dtype": ds.dtypes[0],
                "nodata": ds.nodata, "scale": ds.scales[0], "offset": ds.offsets[0], "units": ds.units[0],
            }
    except RasterioError as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DemError(f"{p}: not a readable DEM ({reason})") from None
    if info["crs"] is None:
        raise DemError(f"{p}: the file carries no CRS (give one with --crs, e.g. EPSG:32632)")
    return info


def _lattice_offsets(infos: list[dict[str, Any]]) -> list[tuple[int, int]]:
    """The (row, col) of each source on the first one's pixel lattice; refuses sources of another
    CRS, pixel size, height scale or lattice."""
    first = infos[0]
    t0 = first["transform"]
    for info in infos[1:]:
        p, t = info["path"], info["transform"]
        if info["crs"] != first["crs"]:
            raise DemError(f"{first['path']} ({_crs_name(first['crs'])}) and {p} ({_crs_name(info['crs'])}) "
                           "have different CRSs: a mosaic needs one CRS")
        if t.b or t.d or abs(t.a - t0.a) > 1e-9 * abs(t0.a) or abs(t.e - t0.e) > 1e-9 * abs(t0.e):
            raise DemError(f"{first['path']} and {p} have different pixel sizes or orientations: "
                           "a mosaic needs one pixel grid")
        for key in ("scale", "offset", "units"):
            if info[key] != first[key]:
                raise DemError(f"{first['path']} and {p} have different height {key}s")
    offsets = []
    for info in infos:
        t = info["transform"]
        col, row = (t.c - t0.c) / t0.a, (t.f - t0.f) / t0.e
        if abs(col - round(col)) > 1e-3 or abs(row - round(row)) > 1e-3:
            raise DemError(f"{first['path']} and {info['path']} are not on one pixel lattice "
                           f"(offset {col:.4f} x {row:.4f} pixels)")
        offsets.append((round(row), round(col)))
    return offsets


def _vrt_lines(infos: list[dict[str, Any]], offsets: list[tuple[int, int]]) -> list[str]:
    """The lines of the VRT placing each source at its offset on the common lattice."""
    first = infos[0]
    t0 = first["transform"]
    r_min = min(r for r, _ in offsets)
    c_min = min(c for _, c in offsets)
    height = max(r + info["height"] for (r, _), info in zip(offsets, infos)) - r_min
    width = max(c + info["width"] for (_, c), info in zip(offsets, infos)) - c_min
    same = all(i["dtype"] == first["dtype"] and _same_nodata(i["nodata"], first["nodata"]) for i in infos)
    keep = same and first["nodata"] is not None and first["dtype"] in _GDAL_TYPES
    dtype, nodata = (first["dtype"], first["nodata"]) if keep else ("float32", math.nan)
    gt = (t0.c + c_min * t0.a, t0.a, 0.0, t0.f + r_min * t0.e, 0.0, t0.e)
    lines = [
        f'<VRTDataset rasterXSize="{width}" rasterYSize="{height}">',
        f"  <SRS>{escape(first['crs'].to_wkt())}</SRS>",
        "  <GeoTransform>" + ", ".join(repr(float(v)) for v in gt) + "</GeoTransform>",
        f'  <VRTRasterBand dataType="{_GDAL_TYPES[dtype]}" band="1">',
        f"    <NoDataValue>{_nodata_text(nodata)}</NoDataValue>",
    ]
    if first["units"]:
        lines.append(f"    <UnitType>{escape(first['units'])}</UnitType>")
    if first["scale"] not in (None, 1.0):
        lines.append(f"    <Scale>{first['scale']!r}</Scale>")
    if first["offset"] not in (None, 0.0):
        lines.append(f"    <Offset>{first['offset']!r}</Offset>")
    for (r, c), info in zip(offsets, infos):
        w, h = info["width"], info["height"]
        lines += [
            "    <ComplexSource>",
            f'      <SourceFilename relativeToVRT="0">{escape(str(Path(info["path"]).resolve()))}</SourceFilename>',
            "      <SourceBand>1</SourceBand>",
            f'      <SrcRect xOff="0" yOff="0" xSize="{w}" ySize="{h}"/>',
            f'      <DstRect xOff="{c - c_min}" yOff="{r - r_min}" xSize="{w}" ySize="{h}"/>',
        ]
        if info["nodata"] is not None:
            # a void of this source lets another source's value at that pixel through
            lines.append(f"      <NODATA>{_nodata_text(info['nodata'])}</NODATA>")
        lines.append("    </ComplexSource>")
    lines += ["  </VRTRasterBand>", "</VRTDataset>", ""]
    return lines


_GDAL_TYPES = {"uint8": "Byte", "int8": "Int8", "uint16": "UInt16", "int16": "Int16", "uint32": "UInt32",
               "int32": "Int32", "float32": "Float32", "float64": "Float64"}


def _same_nodata(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is b
    return a == b or (math.isnan(a) and math.isnan(b))


def _nodata_text(v: float) -> str:
    if math.isnan(v):
        return "nan"
    return repr(int(v)) if float(v).is_integer() else repr(float(v))


def _crs_name(crs: object) -> str:
    epsg = getattr(crs, "to_epsg", lambda: None)()
    return f"EPSG:{epsg}" if epsg else str(crs)
