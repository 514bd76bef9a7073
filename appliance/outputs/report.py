"""The HTML report, ``report.html`` with the pictures and files it shows: of estimates from skyline files
(``viper estimate --report``: :func:`write_estimate_files` per skyline, then
:func:`write_estimate_report`), of session logs replayed (``viper replay``) or of a session that has just
run (``viper demo``) (:func:`write_replay_report`), and of a traverse (``viper demo --traverse`` and
``viper replay`` of a traverse's log: :func:`write_traverse_report`, its stop table as CSV
:func:`write_stop_table`).

Every page has the same build: the title, the skyline database, a table with a row per estimate that
links to the estimate's own section further down (its heading, facts, pictures and files); the look
and the escaping are :mod:`appliance.outputs.html`'s.  The session logs and the traverse come from the
acquisition's results; this module knows them by what it reads of them (:class:`ReplayedLog`,
:class:`Traversed`), which the results of :mod:`appliance.acquisition.replay` and
:mod:`appliance.acquisition.traverse` have.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from appliance.atomic import check_output_folder, write_text_atomic
from appliance.bodies import BodyName
from appliance.locating.position import Position, estimate_status, status_text, truth_error_m
from appliance.outputs import html as rp
from appliance.outputs.files import MAP_LAYER_SUFFIXES, save_png, write_map_layers, write_png
from appliance.outputs.grid_refs import mgrs_ref
from appliance.outputs.picture import TrackStop, panorama_figure, track_figure
from appliance.outputs.status import position_facts, status_banner

if TYPE_CHECKING:
    from appliance.skyline import Skyline
    from appliance.terrain.database import SkylineDatabase
    from appliance.vision.panorama import Panorama

#: the page's name in its folder
PAGE = "report.html"
#: the files of each skyline of ``viper estimate --report``, after its number and name: its picture and
#: its map's layers
ESTIMATE_FILES = (".png", *MAP_LAYER_SUFFIXES)


def _write_page(db: SkylineDatabase, folder: Path, title: str, parts: Sequence[str], into: Path | None = None,
                top: Sequence[str] = ()) -> Path:
    """``report.html`` in ``folder``: ``title``, the ``top`` fragments (the status banners), the skyline
    database, then ``parts``; returns its path.  ``into``: the folder it is written in instead (a staging
    folder that becomes ``folder``)."""
    page = folder / PAGE
    db_line = rp.paragraph(rp.shown_path(db.path, folder), "Skyline database:")
    write_text_atomic((into or folder) / PAGE, rp.page(title, [*top, db_line, *parts]))
    return page


def answer_banner(db: SkylineDatabase, pos: Position, truth: tuple[float, float] | None, name: str) -> str:
    """The status banner of one answer (:func:`appliance.outputs.status.status_banner` of its record),
    named ``name``, with its latitude, longitude and MGRS."""
    b = status_banner(pos.to_json(db, truth, max_cells=0))
    mgrs = mgrs_ref(pos.lat, pos.lon) if str(db.header["body"]) == BodyName.EARTH.value else None
    where = f"{name}: {pos.lat:.6f}, {pos.lon:.6f}" + ("" if mgrs is None else f" · MGRS {mgrs}")
    return rp.banner(b.headline, b.ok, where, b.reasons)


def position_table(db: SkylineDatabase, pos: Position, truth: tuple[float, float] | None) -> str:
    """Where the answer is (latitude and longitude, UTM, MGRS, altitude) as a facts table."""
    return rp.facts_table(position_facts(pos.to_json(db, truth, max_cells=0), str(db.header["body"])))


def _layer_links(files: Sequence[Path], folder: Path) -> str:
    return "<p><b>map layers</b> " + " · ".join(rp.link(f, folder) for f in files) + "</p>"


# ----------------------------------------------------------------------------------- viper estimate
@dataclass(frozen=True)
class ReportEntry:
    """One skyline of ``viper estimate --report``: its name, estimate, truth (lat, lon) and files."""

    name: str
    pos: Position
    skyline: Skyline
    truth: tuple[float, float] | None
    picture: Path
    files: tuple[Path, ...]


def _stem(i: int, skyline: str | Path) -> str:
    return f"{i + 1:02d}-{Path(skyline).stem}"


def estimate_report_names(skylines: Sequence[str | Path]) -> list[str]:
    """What ``viper estimate --report`` writes for ``skylines``: each one's files, then the page."""
    return [*(f"{_stem(i, s)}{e}" for i, s in enumerate(skylines) for e in ESTIMATE_FILES), PAGE]


def write_estimate_files(db: SkylineDatabase, folder: Path, i: int, name: str, pos: Position, skyline: Skyline,
                         truth: tuple[float, float] | None) -> ReportEntry:
    """The files of skyline number ``i`` (from 0) in ``folder``: its picture and its map's layers
    (posteriors, GeoJSON and their styles)."""
    picture = folder / f"{_stem(i, name)}{ESTIMATE_FILES[0]}"
    write_png(db, pos, skyline, picture, truth)
    layers = write_map_layers(db, pos, folder, _stem(i, name), truth)
    return ReportEntry(Path(name).name, pos, skyline, truth, picture, (picture, *layers))


def _estimate_row(db: SkylineDatabase, e: ReportEntry, err: float | None, valid: str) -> dict[str, str]:
    r = e.pos.result
    return {
        "skyline": e.name,
        "status": status_text(db, e.pos, e.truth),
        "lat": f"{e.pos.lat:.6f}",
        "lon": f"{e.pos.lon:.6f}",
        "truth_lat": "" if e.truth is None else f"{e.truth[0]:.6f}",
        "truth_lon": "" if e.truth is None else f"{e.truth[1]:.6f}",
        "error_m": "" if err is None else f"{err:.1f}",
        "region_km2": f"{r.region_area_m2 / 1e6:.4f}",
        "heading_correction_deg": f"{r.heading_correction_deg:+.2f}",
        "valid_azimuths": valid,
    }


def write_estimate_report(db: SkylineDatabase, entries: Sequence[ReportEntry], folder: Path,
                          title: str = "Viper estimate") -> Path:
    """``report.html`` in ``folder``: a table of the estimates, then per skyline its facts, picture and
    files; returns the page's path."""
    rows, sections, banners = [], [], []
    for i, e in enumerate(entries):
        r = e.pos.result
        err = None if e.truth is None else truth_error_m(db, e.pos, e.truth)
        valid = f"{int(e.skyline.valid.sum())} of {e.skyline.elevation_deg.size}"
        rows.append(_estimate_row(db, e, err, valid))
        banners.append(answer_banner(db, e.pos, e.truth, e.name))
        facts = [*position_facts(e.pos.to_json(db, e.truth, max_cells=0), str(db.header["body"])),
                 ("error", "no truth given" if err is None else f"{err:.1f} m from the truth"),
                 ("region", f"{r.region_area_m2 / 1e6:.4f} km², {r.region_nodes.size} cells"),
                 ("valid azimuths", valid),
                 ("residual", f"{r.rms_residual_deg:.2f} deg RMS")]
        sections += [rp.heading(e.name, anchor=f"skyline-{i + 1}"), rp.facts_table(facts),
                     "<p>" + " · ".join(rp.link(f, folder) for f in e.files) + "</p>",
                     rp.image(e.picture, folder, e.picture.stem)]
    table = rp.table(rows, {i: f"#skyline-{i + 1}" for i in range(len(entries))})
    return _write_page(db, folder, title, [table, *sections], top=banners)


# ----------------------------------------------------------------------- viper replay and viper demo
class LogFacts(Protocol):
    """What a session log says of its session, as (name, value) rows
    (:class:`appliance.acquisition.session_facts.SessionFacts`)."""

    def rows(self, one_session: bool = True) -> list[tuple[str, str]]: ...


class LogData(Protocol):
    """What the page reads of a session log (:class:`appliance.acquisition.replay.SessionData`)."""

    path: Path
    truth: tuple[float, float] | None
    complete: bool
    onboard_error_m: float | None

    @property
    def frame_count(self) -> int: ...

    @property
    def facts(self) -> LogFacts: ...


class ReplayedLog(Protocol):
    """One session log and its estimate (:class:`appliance.acquisition.replay.ReplayResult`); the page
    sets its ``pictures``."""

    name: str
    panorama: Panorama | None
    skyline: Skyline | None
    position: Position | None
    error_m: float | None
    notes: list[str]
    failure: str | None
    results_log: Path | None
    pictures: list[Path]

    @property
    def data(self) -> LogData: ...


def _fmt(v: float | None, spec: str = ".1f") -> str:
    return "" if v is None or not math.isfinite(v) else format(v, spec)


def summary_rows(results: Sequence[ReplayedLog], db: SkylineDatabase, out_dir: Path) -> list[dict[str, str]]:
    """One row per log; logs are named relative to ``out_dir``, where the table is written."""
    rows = []
    for r in results:
        p = r.position
        rows.append({
            "log": Path(os.path.relpath(os.path.abspath(r.data.path), os.path.abspath(out_dir))).as_posix(),
            "status": "" if p is None else estimate_status(db, p, r.data.truth),
            "frames": str(r.data.frame_count),
            "complete": "yes" if r.data.complete else "no",
            "lat": "" if p is None else f"{p.lat:.6f}",
            "lon": "" if p is None else f"{p.lon:.6f}",
            "truth_lat": "" if r.data.truth is None else f"{r.data.truth[0]:.6f}",
            "truth_lon": "" if r.data.truth is None else f"{r.data.truth[1]:.6f}",
            "error_m": _fmt(r.error_m),
            "onboard_error_m": _fmt(r.data.onboard_error_m),
            "region_km2": "" if p is None else f"{p.result.region_area_m2 / 1e6:.4f}",
            "valid_azimuths": "" if r.skyline is None else str(int(r.skyline.valid.sum())),
            "heading_correction_deg": "" if p is None else f"{p.result.heading_correction_deg:+.2f}",
            "failure": r.failure or "",
        })
    return rows


def _write_summary_csv(rows: list[dict[str, str]], path: Path) -> None:
    table = io.StringIO(newline="")
    writer = csv.DictWriter(table, fieldnames=list(rows[0]) if rows else ["log"])
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, table.getvalue())


def _shown(text: str, r: ReplayedLog, db: SkylineDatabase, out_dir: Path) -> str:
    """``text`` with the log, the database and the results log named as the page names them."""
    return rp.without_folders(text, [r.data.path, db.path, *([r.results_log] if r.results_log else [])], out_dir)


def _log_section(r: ReplayedLog, i: int, db: SkylineDatabase, out_dir: Path,
                 layers: Sequence[Path] = ()) -> list[str]:
    """The log's heading, notes, failure, estimate (where it is, its map layers), results log, facts and
    pictures."""
    parts = [rp.heading(r.name, anchor=f"log-{i + 1}")]
    for note in r.notes:
        parts.append(rp.paragraph(_shown(note, r, db, out_dir), "note:"))
    if r.failure:
        parts.append(rp.paragraph(_shown(r.failure, r, db, out_dir), "no estimate:"))
    if r.position is not None:
        err = "no GPS truth" if r.error_m is None else f"{r.error_m:.1f} m from the GPS truth"
        status = estimate_status(db, r.position, r.data.truth)
        parts.append(rp.paragraph(f"{r.position.lat:.6f}, {r.position.lon:.6f} {status}: {err}", "estimate"))
        parts.append(position_table(db, r.position, r.data.truth))
    if layers:
        parts.append(_layer_links(layers, out_dir))
    if r.results_log is not None:
        parts.append(f"<p><b>results log</b> {rp.link(r.results_log, out_dir)}</p>")
    parts.append(rp.facts_table(r.data.facts.rows()))
    for pic in r.pictures:
        parts.append(rp.image(pic, out_dir, pic.stem))
    return parts


def write_replay_report(results: Sequence[ReplayedLog], db: SkylineDatabase, out_dir: Path,
                        title: str | None = None, into: Path | None = None) -> Path:
    """PNG pictures and the map's layers (:func:`appliance.outputs.files.write_map_layers`) per log,
    ``summary.csv`` and ``report.html`` (titled ``title``, by default "Viper replay of N logs"); returns
    the HTML page's path.  ``into``: the folder the files are written in instead of ``out_dir`` (a staging
    folder that becomes ``out_dir``); the page names them as in ``out_dir``."""
    folder = check_output_folder(into or out_dir)
    layers: dict[int, list[Path]] = {}
    banners = []
    for i, r in enumerate(results):
        if r.position is None:
            continue
        written = write_map_layers(db, r.position, folder, r.name, r.data.truth)
        layers[i] = [out_dir / p.name for p in written]
        banners.append(answer_banner(db, r.position, r.data.truth, r.name))
        if r.skyline is None:
            continue
        map_png = out_dir / f"{r.name}.map.png"
        write_png(db, r.position, r.skyline, folder / map_png.name, truth=r.data.truth)
        pano_png = out_dir / f"{r.name}.panorama.png"
        assert r.panorama is not None
        save_png(panorama_figure(db, r.position, r.panorama, r.skyline, r.name), folder / pano_png.name, dpi=80)
        r.pictures = [map_png, pano_png]
    rows = summary_rows(results, db, out_dir)
    csv_path = out_dir / "summary.csv"
    _write_summary_csv(rows, folder / csv_path.name)
    if title is None:
        title = f"Viper replay of {len(results)} log{'s' if len(results) != 1 else ''}"
    parts = []
    errors = [r.error_m for r in results if r.error_m is not None]
    if errors:
        parts.append(f"<p>Error against the GPS truth: median {np.median(errors):.1f} m, max {max(errors):.1f} m "
                     f"over {len(errors)} estimate{'s' if len(errors) != 1 else ''} "
                     f"({rp.link(csv_path, out_dir, 'CSV')})</p>")
    shown_rows = [{k: rp.shown_path(r.data.path, out_dir) if k == "log" else _shown(v, r, db, out_dir)
                   for k, v in row.items()} for row, r in zip(rows, results, strict=True)]
    parts.append(rp.table(shown_rows, {i: f"#log-{i + 1}" for i in range(len(results))}))
    for i, r in enumerate(results):
        parts += _log_section(r, i, db, out_dir, layers.get(i, []))
    return _write_page(db, out_dir, title, parts, into=folder, top=banners)


# ----------------------------------------------------------------------------- viper demo --traverse
class StopOdometry(Protocol):
    """The odometry line that announced a stop (:class:`appliance.drivers.odometry.OdometryReport`)."""

    @property
    def east_m(self) -> float: ...

    @property
    def north_m(self) -> float: ...

    @property
    def sigma_m(self) -> float: ...


class StopTruth(Protocol):
    """A stop's GPS truth (:class:`appliance.acquisition.procedures.TruthResult`)."""

    @property
    def used(self) -> int: ...

    @property
    def sigma_m(self) -> float | None: ...


class StopSession(Protocol):
    """A stop's session (:class:`appliance.acquisition.session.SessionResult`)."""

    @property
    def outcomes(self) -> Mapping[str, str]: ...

    @property
    def truth(self) -> StopTruth | None: ...

    @property
    def frames(self) -> int: ...

    @property
    def skyline(self) -> Skyline | None: ...


class Stop(Protocol):
    """One stop of a traverse (:class:`appliance.acquisition.traverse.StopResult`)."""

    @property
    def stop(self) -> int: ...

    @property
    def session(self) -> StopSession: ...

    @property
    def odometry(self) -> StopOdometry | None: ...

    @property
    def fusion_note(self) -> str: ...

    @property
    def fused(self) -> bool: ...

    @property
    def position(self) -> Position | None: ...

    @property
    def alone(self) -> Position | None: ...

    @property
    def error_m(self) -> float | None: ...

    @property
    def error_alone_m(self) -> float | None: ...

    @property
    def truth(self) -> tuple[float, float] | None: ...


class Traversed(Protocol):
    """A whole traverse (:class:`appliance.acquisition.traverse.TraverseResult`)."""

    session_id: str
    log_path: Path

    @property
    def stops(self) -> Sequence[Stop]: ...


def _latlon(pos: Position | None) -> tuple[float, float] | None:
    return None if pos is None else (float(pos.lat), float(pos.lon))


def _err(value: float | None) -> str:
    return "" if value is None else f"{value:.1f}"


def _coords(pos: tuple[float, float] | None) -> tuple[str, str]:
    return ("", "") if pos is None else (f"{pos[0]:.6f}", f"{pos[1]:.6f}")


def stop_rows(db: SkylineDatabase, stops: Sequence[Stop],
              onboard_error_m: Sequence[float | None] | None = None) -> list[dict[str, str]]:
    """A row per stop: its odometry, its estimates alone and fused (errors, statuses, the position's
    coordinates beside the GPS truth's), its session facts; with ``onboard_error_m`` (a replay), the
    error the stop's estimate had on board."""
    rows = []
    for k, s in enumerate(stops):
        odo = s.odometry
        alone, pos = s.alone, s.position
        moved = "" if odo is None else f"{odo.east_m:.0f}, {odo.north_m:.0f} ± {odo.sigma_m:.0f}"
        lat, lon = _coords(_latlon(pos))
        truth_lat, truth_lon = _coords(s.truth)
        row = {
            "stop": str(s.stop),
            "odometry east, north ± σ (m)": moved,
            "alone: error (m)": _err(s.error_alone_m),
            "alone: status": "" if alone is None else estimate_status(db, alone, s.truth),
            "fused: error (m)": _err(s.error_m) if s.fused else "",
            "fused: status": "" if pos is None or not s.fused else estimate_status(db, pos, s.truth),
            "lat": lat, "lon": lon, "truth_lat": truth_lat, "truth_lon": truth_lon,
            "region (cells)": "" if pos is None else str(pos.result.region_nodes.size),
        }
        if onboard_error_m is not None:
            row["onboard: error (m)"] = _err(onboard_error_m[k] if k < len(onboard_error_m) else None)
        rows.append({**row, **_stop_facts(s), "note": s.fusion_note})
    return rows


def write_stop_table(db: SkylineDatabase, stops: Sequence[Stop], path: Path, into: Path | None = None,
                     onboard_error_m: Sequence[float | None] | None = None) -> Path:
    """The stop table (:func:`stop_rows`) as CSV at ``path`` (written in the folder ``into`` instead,
    where given); returns ``path``."""
    _write_summary_csv(stop_rows(db, stops, onboard_error_m), (into or path.parent) / path.name)
    return path


def _stop_facts(s: Stop) -> dict[str, str]:
    """The stop's own session facts: how its procedures ended, its GPS truth, its frames and skyline."""
    sr = s.session
    facts = {name: sr.outcomes.get(name, "") for name in ("level", "compass", "truth")}
    tr = sr.truth
    facts["GPS fixes averaged, σ (m)"] = ("" if tr is None or tr.sigma_m is None
                                         else f"{tr.used}, {tr.sigma_m:.1f}")
    facts["frames"] = str(sr.frames)
    el = None if sr.skyline is None else np.asarray(sr.skyline.elevation_deg)
    facts["valid azimuths"] = "" if el is None else f"{int(np.count_nonzero(np.isfinite(el)))} of {el.size}"
    return facts


def estimate_flag_text(db: SkylineDatabase, s: Stop) -> str:
    assert s.position is not None
    how = "fused with the previous stop" if s.fused else f"alone ({s.fusion_note})"
    err = "" if s.error_m is None else f", {s.error_m:.1f} m from the GPS truth"
    return f"{estimate_status(db, s.position, s.truth)}, {how}{err}"


def write_traverse_report(result: Traversed, db: SkylineDatabase, out_dir: Path, title: str,
                          log_facts: LogFacts, into: Path | None = None,
                          onboard_error_m: Sequence[float | None] | None = None, results_log: Path | None = None,
                          notes: Sequence[str] = ()) -> Path:
    """``report.html`` in ``out_dir`` with ``track.png`` and a picture per stop, and the facts of the
    traverse's whole log (``log_facts``); returns the page's path.  A replay gives the folder the files
    are written in (``into``, a staging folder that becomes ``out_dir``), the onboard errors per stop,
    its results log and its notes."""
    folder = check_output_folder(into or out_dir)
    track = [TrackStop(str(s.stop), _latlon(s.position), _latlon(s.alone), s.truth) for s in result.stops]
    track_png = out_dir / "track.png"
    save_png(track_figure(db, track, f"traverse {result.session_id}: {len(result.stops)} stops"),
             folder / track_png.name, dpi=90)
    pictures: list[Path | None] = []
    layers: dict[int, tuple[Path, ...]] = {}
    for s in result.stops:
        if s.position is not None:
            written = write_map_layers(db, s.position, folder, f"stop-{s.stop:02d}", s.truth)
            layers[s.stop] = tuple(out_dir / q.name for q in written)
        if s.position is None or s.session.skyline is None:
            pictures.append(None)
            continue
        png = out_dir / f"stop-{s.stop:02d}.png"
        write_png(db, s.position, s.session.skyline, folder / png.name, s.truth)
        pictures.append(png)
    located = [s for s in result.stops if s.position is not None]
    top = []
    if located:
        last = located[-1]
        assert last.position is not None
        top = [answer_banner(db, last.position, last.truth, f"stop {last.stop} (the last located)"),
               position_table(db, last.position, last.truth)]
    fused = sum(1 for s in result.stops if s.fused)
    parts = [rp.paragraph(f"a traverse of {len(result.stops)} stops in one log, {fused} of them fused with the "
                          "stop before through the rover's odometry", "Traverse:"),
             f"<p><b>Log:</b> {rp.link(result.log_path, out_dir)}</p>"]
    if results_log is not None:
        parts.append(f"<p><b>Results log:</b> {rp.link(results_log, out_dir)}</p>")
    parts += [rp.paragraph(rp.without_folders(n, [result.log_path, db.path], out_dir), "note:") for n in notes]
    parts += [rp.image(track_png, out_dir, "the track"),
              rp.table(stop_rows(db, result.stops, onboard_error_m),
                       {i: f"#stop-{s.stop}" for i, s in enumerate(result.stops)}),
              rp.facts_table(log_facts.rows(one_session=False))]
    for s, picture in zip(result.stops, pictures, strict=True):
        parts.append(rp.heading(f"stop {s.stop}", anchor=f"stop-{s.stop}"))
        if s.position is not None:
            flag = estimate_flag_text(db, s)
            parts.append(rp.paragraph(f"{s.position.lat:.6f}, {s.position.lon:.6f} {flag}", "estimate"))
            parts.append(position_table(db, s.position, s.truth))
            parts.append(_layer_links(layers[s.stop], out_dir))
        if picture is not None:
            parts.append(rp.image(picture, out_dir, picture.stem))
    return _write_page(db, out_dir, title, parts, into=folder, top=top)
