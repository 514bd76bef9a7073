"""The report of a traverse: the track on the map, a table of the stops (odometry, the estimate alone
and fused, their errors against the GPS truth and their statuses) and each stop's picture, in the
look of the other reports (:mod:`appliance.outputs.html`), with the session facts of the log."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from appliance.atomic import atomic_output, check_output_folder, write_text_atomic

if TYPE_CHECKING:
    from appliance.acquisition.traverse import StopResult, TraverseResult
    from appliance.terrain.database import SkylineDatabase


def _latlon(pos: object) -> tuple[float, float] | None:
    return None if pos is None else (float(pos.lat), float(pos.lon))  # type: ignore[attr-defined]


def _err(value: float | None) -> str:
    return "" if value is None else f"{value:.1f}"


def stop_rows(db: SkylineDatabase, stops: list[StopResult]) -> list[dict[str, str]]:
    from appliance.acquisition.traverse import estimate_flag

    rows = []
    for s in stops:
        odo = s.odometry
        alone, pos = s.alone, s.position
        moved = "" if odo is None else f"{odo.east_m:.0f}, {odo.north_m:.0f} ± {odo.sigma_m:.0f}"
        rows.append({
            "stop": str(s.stop),
            "odometry east, north ± σ (m)": moved,
            "alone: error (m)": _err(s.error_alone_m),
            "alone: status": "" if alone is None else estimate_flag(db, alone, s.truth),
            "fused: error (m)": _err(s.error_m) if s.fused else "",
            "fused: status": "" if pos is None or not s.fused else estimate_flag(db, pos, s.truth),
            "region (cells)": "" if pos is None else str(pos.result.region_nodes.size),
            **_stop_facts(s),
            "note": s.fusion_note,
        })
    return rows


def _stop_facts(s: StopResult) -> dict[str, str]:
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


def write_traverse_report(result: TraverseResult, db: SkylineDatabase, out_dir: Path, title: str) -> Path:
    """``report.html`` in ``out_dir`` with ``track.png`` and a picture per stop; returns the page's path."""
    from appliance.acquisition.session_facts import read_session_facts
    from appliance.outputs import html as rp
    from appliance.outputs.picture import TrackStop, track_figure
    from appliance.outputs.records import write_png

    check_output_folder(out_dir)
    track = [TrackStop(str(s.stop), _latlon(s.position), _latlon(s.alone), s.truth) for s in result.stops]
    track_png = out_dir / "track.png"
    fig = track_figure(db, track, f"traverse {result.session_id}: {len(result.stops)} stops")
    with atomic_output(track_png) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    pictures: list[Path | None] = []
    for s in result.stops:
        if s.position is None or s.session.skyline is None:
            pictures.append(None)
            continue
        png = out_dir / f"stop-{s.stop:02d}.png"
        write_png(db, s.position, s.session.skyline, png, s.truth)
        pictures.append(png)
    parts = [rp.paragraph(rp.shown_path(db.path, out_dir), "Skyline database:"),
             f"<p><b>Log:</b> {rp.link(result.log_path, out_dir)}</p>",
             rp.image(track_png, out_dir, "the track"),
             rp.table(stop_rows(db, result.stops), {i: f"#stop-{s.stop}" for i, s in enumerate(result.stops)}),
             rp.facts_table(read_session_facts(result.log_path).rows(one_session=False))]
    for s, picture in zip(result.stops, pictures, strict=True):
        parts.append(rp.heading(f"stop {s.stop}", anchor=f"stop-{s.stop}"))
        if s.position is not None:
            flag = estimate_flag_text(db, s)
            parts.append(rp.paragraph(f"{s.position.lat:.6f}, {s.position.lon:.6f} {flag}", "estimate"))
        if picture is not None:
            parts.append(rp.image(picture, out_dir, picture.stem))
    page = out_dir / "report.html"
    write_text_atomic(page, rp.page(title, parts))
    return page


def estimate_flag_text(db: SkylineDatabase, s: StopResult) -> str:
    from appliance.acquisition.traverse import estimate_flag

    assert s.position is not None
    how = "fused with the previous stop" if s.fused else f"alone ({s.fusion_note})"
    err = "" if s.error_m is None else f", {s.error_m:.1f} m from the GPS truth"
    return f"{estimate_flag(db, s.position, s.truth)}, {how}{err}"
