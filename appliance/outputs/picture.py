"""The pictures of the reports: an estimate's map in latitude and longitude with a zoom around the
estimate and the truth and its skylines (:func:`estimate_figure`), a traverse's track
(:func:`track_figure`) and a panorama with its skylines (:func:`panorama_figure`).

The figures are matplotlib figures with labelled axes (``map``, ``zoom``, ``skyline``, ``track``), so a
test can read limits and tick labels; :mod:`appliance.outputs.files` saves them.  Every grid node is
drawn at its own longitude and latitude (``pcolormesh``), so the axes are exact for a geographic grid
and for a projected one alike; the aspect ratio makes a metre east as long as a metre north at the
map's centre, and the scale bars are measured on the database's body.  matplotlib is imported by the
functions that draw, so that the modules importing this one start without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from appliance.bodies import body_named, geodesic_distance_m
from appliance.estimator import resample_to_grid
from appliance.locating.position import Position, truth_error_m
from appliance.outputs.features import region_mask, rendered_skyline
from appliance.outputs.styles import KIND_STYLES

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from appliance.skyline import Skyline
    from appliance.terrain.database import SkylineDatabase
    from appliance.vision.panorama import Panorama

#: the posterior's colour scale: log10 of the lower posterior per cell over the best cell's, down to this many
#: decades below it
POSTERIOR_DECADES = 20.0
POSTERIOR_LABEL = "log10 posterior, relative to the best (0 = the most probable cell)"
#: the zoom spans at least this much (m), so the cells around a small error show
MIN_ZOOM_SPAN_M = 400.0
#: and at least this many node spacings
MIN_ZOOM_CELLS = 6.0


@dataclass(frozen=True)
class MapScale:
    """Metres per degree of latitude and of longitude at a point of a body."""

    lat_deg: float
    lon_deg: float
    m_per_deg_lat: float
    m_per_deg_lon: float

    @property
    def aspect(self) -> float:
        """Display length of a degree of latitude over a degree of longitude (equal metres)."""
        return self.m_per_deg_lat / self.m_per_deg_lon


def map_scale(db: SkylineDatabase, lat_deg: float, lon_deg: float) -> MapScale:
    body = body_named(db.header["body"])
    step = 0.01
    north = geodesic_distance_m(lat_deg - step / 2, lon_deg, lat_deg + step / 2, lon_deg, body) / step
    east = geodesic_distance_m(lat_deg, lon_deg - step / 2, lat_deg, lon_deg + step / 2, body) / step
    return MapScale(lat_deg, lon_deg, north, east)


def nice_length_m(span_m: float) -> float:
    """A round length (1, 2 or 5 times a power of ten, in metres) near a quarter of ``span_m``."""
    target = max(span_m / 4.0, 1e-3)
    power = 10.0 ** math.floor(math.log10(target))
    return max(f * power for f in (1.0, 2.0, 5.0) if f * power <= target)


def length_label(length_m: float) -> str:
    return f"{length_m / 1000:g} km" if length_m >= 1000 else f"{length_m:g} m"


def degree_label(value: float, positive: str, negative: str, decimals: int) -> str:
    hemisphere = positive if value >= 0 else negative
    return f"{abs(value):.{decimals}f}°{hemisphere}"


def tick_decimals(ticks: Any) -> int:
    """The fewest decimals (up to 6) that write every tick value exactly."""
    values = np.asarray(ticks, float)
    for d in range(7):
        if np.all(np.abs(np.round(values, d) - values) < 1e-9):
            return d
    return 6


def geographic_axes(ax: Axes, scale: MapScale) -> None:
    """Longitude and latitude tick labels (degrees with the hemisphere) and equal metres on both axes."""
    from matplotlib.ticker import FuncFormatter, MaxNLocator  # matplotlib loads only to draw (module docstring)

    x_ticks, y_ticks = MaxNLocator(5), MaxNLocator(6)
    dx = tick_decimals(x_ticks.tick_values(*ax.get_xlim()))
    dy = tick_decimals(y_ticks.tick_values(*ax.get_ylim()))
    ax.xaxis.set_major_locator(x_ticks)
    ax.yaxis.set_major_locator(y_ticks)
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: degree_label(v, "E", "W", dx)))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: degree_label(v, "N", "S", dy)))
    ax.set_xlabel("longitude")
    ax.set_ylabel("latitude")
    ax.set_aspect(scale.aspect, adjustable="box")
    ax.grid(alpha=0.25, color="white", lw=0.5)


def add_scale_bar(ax: Axes, scale: MapScale) -> float:
    """A bar of a round length in the lower left corner; returns its length (m)."""
    # matplotlib loads only to draw (module docstring)
    from matplotlib.font_manager import FontProperties
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    x0, x1 = ax.get_xlim()
    length_m = nice_length_m(abs(x1 - x0) * scale.m_per_deg_lon)
    bar = AnchoredSizeBar(ax.transData, length_m / scale.m_per_deg_lon, length_label(length_m), "lower left",
                          pad=0.5, borderpad=0.6, sep=4, color="black", frameon=True, size_vertical=0,
                          fontproperties=FontProperties(size=10))
    bar.patch.set_alpha(0.8)
    ax.add_artist(bar)
    return length_m


def zoom_window(scale: MapScale, points: list[tuple[float, float]], cell_m: float,
                map_span_m: tuple[float, float]) -> tuple[tuple[float, float], tuple[float, float]]:
    """(lon limits, lat limits) of a square zoom around ``points`` (lat, lon): at least
    :data:`MIN_ZOOM_SPAN_M` and :data:`MIN_ZOOM_CELLS` node spacings, 2.5 times the points' spread,
    and less than the map's smaller side."""
    lats = np.array([p[0] for p in points])
    lons = np.array([p[1] for p in points])
    lat_c, lon_c = float(lats.mean()), float(lons.mean())
    spread_m = max(float(np.ptp(lats)) * scale.m_per_deg_lat, float(np.ptp(lons)) * scale.m_per_deg_lon)
    span_m = max(MIN_ZOOM_SPAN_M, MIN_ZOOM_CELLS * cell_m, 2.5 * spread_m)
    span_m = min(span_m, 0.9 * min(map_span_m))
    half_lon = span_m / 2 / scale.m_per_deg_lon
    half_lat = span_m / 2 / scale.m_per_deg_lat
    return (lon_c - half_lon, lon_c + half_lon), (lat_c - half_lat, lat_c + half_lat)


def _node_lonlat(db: SkylineDatabase) -> tuple[np.ndarray, np.ndarray]:
    g = db.grid
    rows, cols = np.mgrid[0:g.n_rows, 0:g.n_cols]
    lon, lat = g.xy_to_lonlat(*g.rc_to_xy(rows.astype(float), cols.astype(float)))
    return np.asarray(lon).reshape(g.n_rows, g.n_cols), np.asarray(lat).reshape(g.n_rows, g.n_cols)


def cell_polygons(db: SkylineDatabase, nodes: np.ndarray) -> np.ndarray:
    """The cells of ``nodes`` (half a spacing around each node) as (n, 4, 2) corners in lon, lat."""
    g = db.grid
    row, col = np.divmod(np.asarray(nodes, int), g.n_cols)
    rows = row[:, None] + np.array([-0.5, -0.5, 0.5, 0.5])
    cols = col[:, None] + np.array([-0.5, 0.5, 0.5, -0.5])
    lon, lat = g.xy_to_lonlat(*g.rc_to_xy(rows.ravel(), cols.ravel()))
    return np.stack([np.ravel(lon), np.ravel(lat)], axis=-1).reshape(-1, 4, 2)


def _hillshade(db: SkylineDatabase) -> np.ndarray:
    """The map's hillshade (light from the north-west, 45 degrees up), nodata filled with the lowest ground."""
    from matplotlib.colors import LightSource  # matplotlib loads only to draw (module docstring)

    g = db.grid
    ground = np.asarray(db.ground_m, float).reshape(g.n_rows, g.n_cols)
    filled = np.where(np.isfinite(ground), ground, np.nanmin(ground))
    return LightSource(azdeg=315, altdeg=45).hillshade(filled, vert_exag=2.0, dx=g.dx_m, dy=g.dy_m)


def _new_figure(figsize: tuple[float, float]) -> Figure:
    """An empty figure drawn by the Agg backend (no display needed)."""
    import matplotlib  # matplotlib loads only to draw (module docstring)

    matplotlib.use("Agg")
    from matplotlib.figure import Figure  # after the backend is chosen

    return Figure(figsize=figsize)


def _draw_map_layers(ax: Axes, lon: np.ndarray, lat: np.ndarray, shade: np.ndarray, posterior: Any,
                     top: float) -> Any:
    ax.pcolormesh(lon, lat, shade, cmap="gray", shading="nearest", rasterized=True)
    return ax.pcolormesh(lon, lat, posterior, cmap="magma", alpha=0.6, vmin=top - POSTERIOR_DECADES, vmax=top,
                         shading="nearest", rasterized=True)


@dataclass(frozen=True)
class _MapLayers:
    """What the map and the zoom of :func:`estimate_figure` both draw: the nodes' longitudes and
    latitudes, the hillshade and the lower posterior (log10 relative to its peak, so ``top`` is 0, masked
    :data:`POSTERIOR_DECADES` below it)."""

    lon: np.ndarray
    lat: np.ndarray
    shade: np.ndarray
    posterior: Any
    top: float
    scale: MapScale


def _draw_map(fig: Figure, ax: Axes, db: SkylineDatabase, pos: Position, layers: _MapLayers,
              truth: tuple[float, float] | None) -> None:
    """The whole map: layers, region outline, estimate and truth, a colour bar and a scale bar."""
    r, lon, lat = pos.result, layers.lon, layers.lat
    mesh = _draw_map_layers(ax, lon, lat, layers.shade, layers.posterior, layers.top)
    ax.contour(lon, lat, region_mask(db, pos), levels=[0.5], colors="cyan", linewidths=1.0)
    fig.colorbar(mesh, ax=ax, fraction=0.046, pad=0.02, label=POSTERIOR_LABEL)
    ax.plot(pos.lon, pos.lat, "+", color=KIND_STYLES["estimate"].colour, ms=14, mew=2, label="estimate")
    if truth is not None:
        ax.plot(truth[1], truth[0], "x", color=KIND_STYLES["truth"].colour, ms=12, mew=2, label="truth")
    ax.set_xlim(float(lon.min()), float(lon.max()))
    ax.set_ylim(float(lat.min()), float(lat.max()))
    geographic_axes(ax, layers.scale)
    add_scale_bar(ax, layers.scale)
    ax.set_title(f"map: region {r.region_area_m2 / 1e6:.3f} km², {r.region_nodes.size} cells")
    ax.legend(loc="upper right")


def _draw_zoom(ax: Axes, db: SkylineDatabase, pos: Position, layers: _MapLayers,
               truth: tuple[float, float] | None) -> tuple[tuple[float, float], tuple[float, float]]:
    """The zoom around the estimate and the truth, region cells marked; returns its (lon, lat) limits."""
    # matplotlib loads only to draw (module docstring)
    from matplotlib.collections import PolyCollection
    from matplotlib.patches import Patch

    g, r, scale = db.grid, pos.result, layers.scale
    points = [(pos.lat, pos.lon)] + ([truth] if truth is not None else [])
    map_span_m = (float(np.ptp(layers.lon)) * scale.m_per_deg_lon, float(np.ptp(layers.lat)) * scale.m_per_deg_lat)
    cell_m = math.sqrt(g.dx_m * g.dy_m)
    (zx0, zx1), (zy0, zy1) = zoom_window(scale, points, cell_m, map_span_m)
    _draw_map_layers(ax, layers.lon, layers.lat, layers.shade, layers.posterior, layers.top)
    fill = (0.0, 1.0, 1.0, 0.35)
    ax.add_collection(PolyCollection(list(cell_polygons(db, r.region_nodes)), facecolors=fill,
                                     edgecolors="cyan", linewidths=1.0))
    handles: list[Any] = [Patch(facecolor=fill, edgecolor="cyan", label=f"region cells ({r.region_nodes.size})")]
    handles += ax.plot(pos.lon, pos.lat, "+", color=KIND_STYLES["estimate"].colour, ms=18, mew=2.5, label="estimate")
    title = "zoom"
    if truth is not None:
        err = truth_error_m(db, pos, truth)
        ax.plot([pos.lon, truth[1]], [pos.lat, truth[0]], "-", color="yellow", lw=1.5)
        handles += ax.plot(truth[1], truth[0], "x", color=KIND_STYLES["truth"].colour, ms=14, mew=2.5, label="truth")
        title = f"zoom: estimate {err:.1f} m from the truth" if err < 100 else \
            f"zoom: estimate {err:.0f} m from the truth"
    ax.set_xlim(zx0, zx1)
    ax.set_ylim(zy0, zy1)
    geographic_axes(ax, scale)
    add_scale_bar(ax, scale)
    ax.set_title(f"{title} (nodes {cell_m:.0f} m apart)")
    ax.legend(handles=handles, loc="upper right")
    return (zx0, zx1), (zy0, zy1)


def _draw_skylines(ax: Axes, db: SkylineDatabase, pos: Position, skyline: Skyline) -> None:
    """The measured skyline (heading corrected) over the one rendered at the estimate."""
    r = pos.result
    az = db.azimuths_deg
    measured = resample_to_grid((skyline.azimuth_deg + r.heading_correction_deg) % 360.0,
                                skyline.elevation_deg, db.n_azimuths)
    ax.plot(az, db.skylines_deg(r.node), color="tab:orange", lw=1.5, label="rendered at the estimate")
    ax.plot(az, measured, color="tab:blue", lw=1.0, label="measured (heading corrected)")
    ax.set_xlim(0, 360)
    ax.set_xticks(np.arange(0, 361, 45))
    ax.set_xlabel("azimuth (deg, clockwise from true north)")
    ax.set_ylabel("elevation (deg)")
    ax.set_title(f"estimate {pos.lat:.6f}, {pos.lon:.6f}; heading correction "
                 f"{r.heading_correction_deg:+.1f} deg; residual {r.rms_residual_deg:.2f} deg RMS")
    ax.legend()
    ax.grid(alpha=0.3)


def estimate_figure(db: SkylineDatabase, pos: Position, skyline: Skyline,
                    truth: tuple[float, float] | None = None) -> Figure:
    """The map (hillshade, lower posterior, region outline, estimate, truth) in longitude and latitude
    with a scale bar, a zoom around the estimate and the truth (region cells marked), and the measured
    and rendered skylines.  ``truth`` is (lat, lon)."""
    from matplotlib.patches import Rectangle  # matplotlib loads only to draw (module docstring)

    g = db.grid
    lon, lat = _node_lonlat(db)
    shade = _hillshade(db)
    lower = np.asarray(pos.result.log_lower_map, float).reshape(g.n_rows, g.n_cols) / np.log(10.0)
    relative = np.where(np.isfinite(lower), lower - float(np.nanmax(lower)), -np.inf)
    posterior = np.ma.masked_less(relative, -POSTERIOR_DECADES)
    layers = _MapLayers(lon, lat, shade, posterior, 0.0, map_scale(db, float(np.mean(lat)), float(np.mean(lon))))

    fig = _new_figure((15, 12.5))
    grid = fig.add_gridspec(2, 2, height_ratios=[1.55, 1], width_ratios=[1, 1])
    ax_map = fig.add_subplot(grid[0, 0], label="map")
    ax_zoom = fig.add_subplot(grid[0, 1], label="zoom")
    ax_sky = fig.add_subplot(grid[1, :], label="skyline")
    _draw_map(fig, ax_map, db, pos, layers, truth)
    (zx0, zx1), (zy0, zy1) = _draw_zoom(ax_zoom, db, pos, layers, truth)
    ax_map.add_patch(Rectangle((zx0, zy0), zx1 - zx0, zy1 - zy0, fill=False, ec="yellow", lw=1.5))
    _draw_skylines(ax_sky, db, pos, skyline)
    fig.tight_layout()
    return fig


@dataclass(frozen=True)
class TrackStop:
    """One stop of a traverse as the track picture draws it: (lat, lon) of its estimates and truth."""

    label: str
    position: tuple[float, float] | None  # the stop's (fused) estimate
    alone: tuple[float, float] | None  # from its own skyline alone
    truth: tuple[float, float] | None


def track_figure(db: SkylineDatabase, stops: list[TrackStop], title: str = "traverse") -> Figure:
    """The traverse on the map's hillshade in longitude and latitude with a scale bar: the line through
    the GPS truths, the line through the stops' estimates (fused), and each stop's estimate from its
    skyline alone; the view spans the track with a margin."""
    g = db.grid
    lon, lat = _node_lonlat(db)
    shade = _hillshade(db)
    points = [p for s in stops for p in (s.position, s.alone, s.truth) if p is not None]
    if not points:
        points = [(float(np.mean(lat)), float(np.mean(lon)))]
    scale = map_scale(db, float(np.mean([p[0] for p in points])), float(np.mean([p[1] for p in points])))
    map_span_m = (float(np.ptp(lon)) * scale.m_per_deg_lon, float(np.ptp(lat)) * scale.m_per_deg_lat)
    cell_m = math.sqrt(g.dx_m * g.dy_m)
    (x0, x1), (y0, y1) = zoom_window(scale, points, cell_m, map_span_m)

    fig = _new_figure((10, 9))
    ax = fig.add_subplot(1, 1, 1, label="track")
    ax.pcolormesh(lon, lat, shade, cmap="gray", shading="nearest", rasterized=True)
    truth = [s.truth for s in stops if s.truth is not None]
    if truth:
        ax.plot([p[1] for p in truth], [p[0] for p in truth], "-x", color="lime", lw=2, ms=10, mew=2,
                label="GPS truth")
    fused = [s.position for s in stops if s.position is not None]
    if fused:
        ax.plot([p[1] for p in fused], [p[0] for p in fused], "-+", color="blue", lw=1.5, ms=16, mew=2.5,
                label="estimate (fused)")
    alone = [s.alone for s in stops if s.alone is not None]
    if alone:
        ax.plot([p[1] for p in alone], [p[0] for p in alone], "o", mfc="none", color="orange", ms=11, mew=1.8,
                label="estimate alone")
    for s in stops:
        where = s.position or s.truth
        if where is not None:
            ax.annotate(s.label, (where[1], where[0]), textcoords="offset points", xytext=(8, 8), color="white",
                        fontsize=11, fontweight="bold")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    geographic_axes(ax, scale)
    add_scale_bar(ax, scale)
    ax.set_title(f"{title} (nodes {cell_m:.0f} m apart)")
    ax.legend(loc="upper right")
    fig.tight_layout()
    return fig


def panorama_figure(db: SkylineDatabase, pos: Position, panorama: Panorama, skyline: Skyline, name: str) -> Figure:
    """The panorama ``name`` with the skyline detected in it and the one rendered at the estimate (heading
    corrected), in the panorama's columns and rows."""
    import cv2  # OpenCV loads only to draw a panorama: `viper estimate --report` draws none

    rendered = rendered_skyline(db, pos)
    h, w = panorama.image.shape[:2]
    fig = _new_figure((16, 16 * h / w + 1.0))
    ax = fig.add_subplot(1, 1, 1)
    ax.imshow(cv2.cvtColor(panorama.image, cv2.COLOR_BGR2RGB), aspect="auto")
    ok = np.isfinite(skyline.elevation_deg)
    ax.plot(panorama.azimuth_to_column(skyline.azimuth_deg[ok]), panorama.elevation_to_row(skyline.elevation_deg[ok]),
            ".", color="cyan", ms=2, label="detected skyline")
    # the measured azimuth a sees the map's a + correction
    az = (rendered.azimuth_deg - pos.result.heading_correction_deg) % 360.0
    order = np.argsort(az)
    ax.plot(panorama.azimuth_to_column(az[order]), panorama.elevation_to_row(rendered.elevation_deg[order]), "-",
            color="orange", lw=1.0, label="rendered at the estimate")
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_xlabel("column (azimuth clockwise from true north)")
    ax.set_title(f"{name}: heading correction {pos.result.heading_correction_deg:+.1f} deg")
    ax.legend(loc="lower right")
    fig.tight_layout()
    return fig
