"""``viper demo``: the README's main command, a whole simulated field session on the jacksboro map.

Level, calibrate the compass, GPS ground truth, capture, estimate, on the simulated platform (the
real drivers over the twins) at a random position; prints the estimate against the GPS truth and
leaves the MCAP log and the report in ``--out``.  ``--skyline-only`` is the quicker synthetic-skyline
demo (:func:`appliance.sim.demo.run_demo`).  ``--traverse N`` is a rover's traverse: N such sessions
at stops a few hundred metres apart along a random path, the rover twin reporting each leg over its
odometry line, each stop's estimate fused with the previous stop's; it prints every stop's error
alone and fused, and the report shows the track.  With ``--mavlink`` the odometry comes from the
autopilot twin over MAVLink (UDP, :mod:`appliance.sim.autopilot_twin`) and every estimate that says ok
goes back to it as GPS_INPUT.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

from appliance.atomic import check_output_folder
from appliance.config import (
    CameraDeviceConfig,
    Config,
    DevicesConfig,
    LogbookConfig,
    LogEncoding,
    OdometryDeviceConfig,
    OdometryKind,
    PositionOutput,
    SessionConfig,
    SimConfig,
)
from appliance.errors import InputError

if TYPE_CHECKING:
    from appliance.terrain.database import SkylineDatabase
    from appliance.terrain.dem import Dem

LOG = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="a whole simulated field session on the embedded jacksboro map")
    p.add_argument("--out", default="viper-demo", help="folder for the log and the report (default ./viper-demo)")
    p.add_argument("--seed", type=int, help="random seed (default: a new position each run)")
    p.add_argument("--skyline-only", action="store_true",
                   help="only locate a synthetic noisy skyline (no platform, no images)")
    p.add_argument("--traverse", type=int, metavar="N",
                   help="a rover's traverse of N stops (legs of 200-400 m), each fused with the last")
    p.add_argument("--mavlink", action="store_true",
                   help="with --traverse: the rover's odometry from a simulated autopilot over MAVLink (UDP), "
                        "each estimate sent back to it as GPS_INPUT")
    p.add_argument("--time-rate", type=float, default=20.0, help="simulated seconds per real second (default 20)")
    p.add_argument("--log-encoding", choices=[e.value for e in LogEncoding], default=LogEncoding.PROTOBUF.value,
                   help="messages of the MCAP log: Foxglove protobuf (default) or standard ROS 2 messages")
    p.set_defaults(func=run)


def demo_config(out: Path, time_rate: float, mavlink: bool = False,
                encoding: str = LogEncoding.PROTOBUF.value) -> Config:
    """The demo's configuration; ``mavlink``: the rover's odometry over MAVLink, estimates sent back as GPS_INPUT;
    ``encoding``: the log's messages (protobuf or ros2)."""
    odometry = OdometryDeviceConfig()
    if mavlink:
        # the link's timeout in simulated seconds: five real ones, as a busy machine stalls the twin's thread
        odometry = OdometryDeviceConfig(kind=OdometryKind.MAVLINK, output=PositionOutput.GPS_INPUT,
                                        read_timeout_s=0.1, link_timeout_s=5.0 * time_rate)
    return Config(
        logbook=LogbookConfig(log_dir=out, encoding=LogEncoding(encoding)),
        session=SessionConfig(level_tolerance_deg=0.3),
        devices=DevicesConfig(camera=CameraDeviceConfig(width=640, height=480), odometry=odometry),
        sim=SimConfig(time_rate=time_rate),
    )


def demo_map(out: Path) -> tuple[Dem, SkylineDatabase]:
    """The embedded jacksboro map and its skyline database in ``out`` (built there the first time)."""
    # the library (seconds of imports) loads only when a demo runs, not for `viper demo --help`
    from appliance.sim.demo import DEMO_DEM, demo_database
    from appliance.terrain.dem import load_dem

    t0 = time.monotonic()
    dem = load_dem(DEMO_DEM)
    db = demo_database(dem, out)
    print(f"  setup      skyline database {db.path} ready in {time.monotonic() - t0:.0f} s")
    return dem, db


def run(args: argparse.Namespace) -> int:
    if not args.time_rate > 0:
        raise InputError(f"--time-rate {args.time_rate}: must be a positive number")
    if args.traverse is not None:
        if args.skyline_only:
            raise InputError("--traverse runs whole sessions; it cannot be combined with --skyline-only")
        if not 1 <= args.traverse <= 1000:
            raise InputError(f"--traverse {args.traverse}: expected a number of stops in 1..1000")
        return run_traverse(args)
    if args.mavlink:
        raise InputError("--mavlink goes with --traverse N (the rover's odometry over MAVLink)")
    if args.skyline_only:
        if args.log_encoding != LogEncoding.PROTOBUF.value:
            raise InputError(f"--log-encoding {args.log_encoding}: --skyline-only writes no log")
        return run_skyline_only(args)
    # the library (seconds of imports) loads only when a demo runs, and only what this demo needs
    from appliance.acquisition.replay import session_report
    from appliance.locating.position import area_text, fix_status, truth_error_m
    from appliance.outputs.files import MAP_LAYER_SUFFIXES
    from appliance.sim.field_session import run_field_session

    out = check_output_folder(args.out)
    print("Viper demo: a simulated field session on the jacksboro DEM (Cumberland Mountains, Tennessee)")
    dem, db = demo_map(out)
    t1 = time.monotonic()

    def status(text: str) -> None:
        print(f"  {time.monotonic() - t1:6.1f} s  {text}", flush=True)

    config = demo_config(out, args.time_rate, encoding=args.log_encoding)
    r, sim_truth = run_field_session(config, out, seed=args.seed, dem=dem, db=db, on_status=status)
    lat, lon = sim_truth.lat_deg, sim_truth.lon_deg
    print(f"  session    {r.status.value}: " + ", ".join(f"{k} {v}" for k, v in r.outcomes.items()))
    for problem in r.problems:
        print(f"  problem    {problem}")
    if r.log_error is not None:
        LOG.error("%s", r.log_error)
    print(f"  true       {lat:.6f}, {lon:.6f}  (simulated; camera {sim_truth.mast_height_m} m above the ground)")
    if r.truth is not None and r.truth.lat_deg is not None and r.truth.lon_deg is not None:
        print(f"  GPS truth  {r.truth.lat_deg:.6f}, {r.truth.lon_deg:.6f}  ({r.truth.used} fixes, "
              f"sigma {r.truth.sigma_m:.1f} m)")
    if r.estimate is not None:
        p = r.estimate
        cell = (p.cell_size_m[0] * p.cell_size_m[1]) ** 0.5
        err = "no GPS truth" if r.error_m is None else f"{r.error_m:.0f} m from the GPS truth"
        true_m = truth_error_m(db, p, (lat, lon))
        print(f"  estimate   {p.lat:.6f}, {p.lon:.6f}  {fix_status(p)}: {err} ({true_m:.0f} m "
              f"from the true position; database nodes {cell:.0f} m apart)")
        for note in p.result.notes:
            print(f"  note       {note}")
        print(f"  region     {area_text(p.result.region_area_m2)} (95 %; {p.result.region_nodes.size} cells), "
              f"heading correction {p.result.heading_correction_deg:+.1f} deg, "
              f"{360 - p.result.n_valid} of 360 azimuths missing")
        page = session_report(r, db, out, "Viper demo: a simulated field session on the jacksboro map")
        print(f"  report     {page}")
        print(f"  layers     {r.log_path.stem}{MAP_LAYER_SUFFIXES[0]}, {', '.join(MAP_LAYER_SUFFIXES[1:])}")
    print(f"  log        {r.log_path}  (open in Foxglove; 'viper log info', 'viper replay')")
    print(f"  time       {time.monotonic() - t1:.0f} s for the session after setup")
    return 0 if r.estimate is not None else 1


def run_skyline_only(args: argparse.Namespace) -> int:
    # the library (seconds of imports) loads only when a demo runs, and only what this demo needs
    from appliance.locating.position import area_text, fix_status
    from appliance.sim.demo import run_demo

    check_output_folder(args.out)
    r = run_demo(args.out, args.seed)
    p = r.position
    cell = (p.cell_size_m[0] * p.cell_size_m[1]) ** 0.5
    print("Viper demo on the jacksboro DEM (Cumberland Mountains, Tennessee)")
    print(f"  truth      {r.truth_lat:.6f}, {r.truth_lon:.6f}  (camera 1.5 m above the ground)")
    print(f"  skyline    {r.skyline_path}: noise 0.2 deg, {360 - p.result.n_valid} of 360 azimuths missing, "
          f"compass error {r.compass_error_deg:+.1f} deg")
    print(f"  estimate   {p.lat:.6f}, {p.lon:.6f}  {fix_status(p)}"
          f"  heading correction {p.result.heading_correction_deg:+.1f} deg"
          f"  in {p.result.elapsed_s * 1e3:.0f} ms over {p.result.candidates} candidates")
    print(f"  error      {r.error_m:.0f} m ({r.error_m / cell:.2f} cells of {cell:.0f} m)")
    print(f"  region     {area_text(p.result.region_area_m2)} (95 %; {p.result.region_nodes.size} cells)"
          f"  lower {p.result.lower:.3g} upper {p.result.upper:.3g}")
    for note in p.result.notes:
        print(f"  note       {note}")
    print(f"  picture    {r.picture_path}")
    print(f"  layers     {', '.join(p.name for p in r.layer_paths)}  (GeoTIFF, GeoJSON; QGIS styles)")
    return 0


def run_traverse(args: argparse.Namespace) -> int:
    # the library (seconds of imports) loads only when a demo runs, and only what this demo needs
    from appliance.acquisition.session_facts import read_session_facts
    from appliance.locating.position import truth_error_m
    from appliance.outputs.report import write_traverse_report
    from appliance.sim.field_session import run_field_traverse

    out = check_output_folder(args.out)
    print(f"Viper demo: a rover's traverse of {args.traverse} stops on the jacksboro DEM "
          "(Cumberland Mountains, Tennessee)" + (", odometry over MAVLink from a simulated autopilot"
                                                 if args.mavlink else ""))
    dem, db = demo_map(out)
    t1 = time.monotonic()

    def status(text: str) -> None:
        if not text.startswith("capture "):
            print(f"  {time.monotonic() - t1:6.1f} s  {text}", flush=True)

    config = demo_config(out, args.time_rate, mavlink=args.mavlink, encoding=args.log_encoding)
    r, truths = run_field_traverse(config, out, args.traverse, seed=args.seed, dem=dem, db=db, on_status=status)
    print(f"  traverse   {r.status.value}: {len(r.stops)} of {args.traverse} stops")
    for problem in r.problems:
        print(f"  problem    {problem}")
    if r.log_error is not None:
        LOG.error("%s", r.log_error)
    print("  stop  odometry E, N +- sigma (m)   alone: error (m)  status     fused: error (m)  status     "
          "true error fused (m)")
    for s, tr in zip(r.stops, truths, strict=True):
        odo = "start" if s.odometry is None else \
            f"{s.odometry.east_m:7.0f}, {s.odometry.north_m:7.0f} +- {s.odometry.sigma_m:.0f}"
        alone = s.alone
        a_err = "-" if s.error_alone_m is None else f"{s.error_alone_m:.1f}"
        a_flag = "-" if alone is None else _flag(db, alone, s.truth)
        if s.fused and s.position is not None:
            f_err = "-" if s.error_m is None else f"{s.error_m:.1f}"
            f_flag = _flag(db, s.position, s.truth)
        else:
            f_err, f_flag = "-", f"({s.fusion_note})"
        true_err = "-" if s.position is None else f"{truth_error_m(db, s.position, (tr.lat_deg, tr.lon_deg)):.1f}"
        print(f"  {s.stop:4d}  {odo:>28}   {a_err:>16}  {a_flag:<9}  {f_err:>16}  {f_flag:<9}  {true_err:>10}")
    page = write_traverse_report(r, db, out, f"Viper demo: a rover's traverse of {len(r.stops)} stops on the "
                                             "jacksboro map", read_session_facts(r.log_path))
    print(f"  report     {page}")
    print(f"  log        {r.log_path}  (open in Foxglove: /traverse/track, /estimate/fix, /gps/truth)")
    print(f"  time       {time.monotonic() - t1:.0f} s for the traverse after setup")
    return 0 if r.stops and all(s.position is not None for s in r.stops) else 1


def _flag(db: object, pos: object, truth: tuple[float, float] | None) -> str:
    """AMBIGUOUS (the region is large, or the GPS truth lies outside it) or ok, as every output says."""
    from appliance.acquisition.traverse import estimate_flag  # the library loads only when a demo runs

    return "AMBIGUOUS" if estimate_flag(db, pos, truth) == "ambiguous" else "ok"  # type: ignore[arg-type]
