"""In-process cost of an estimate on several checkouts, and whether their answers are the same.

The skylines are made once, by the checkout this file is run from, and kept in one file; each
checkout then estimates the same skylines in its own process, with the database its own code
built (CHECKOUT/bench/cache), and records the CPU time (``time.process_time``: the whole process,
every thread) of each estimate and, with ``--answers``, every field of each answer.

    python bench/in_process_cost.py cases --out CASES.npz [--chain]
    python bench/in_process_cost.py alternate --cases CASES.npz --rounds 2 base=DIR main=DIR branch=DIR
    python bench/in_process_cost.py run --cases CASES.npz --case NAME --out OUT.pkl [--answers]  # cwd: checkout
    python bench/in_process_cost.py compare A.pkl B.pkl          # exit 1 if any answer differs

Cases (bench/estimator_accuracy.py's skylines, seed 5, and bench/session_chain.py's):

- ``jacksboro-no-compass``: 40 skylines, 0.5 deg noise, 25 % missing, any heading; ``estimate(grid,
  az, el, (0.3, 0.8), None)`` with the checkout's other defaults.
- ``jacksboro-compass`` and ``white-mountains-compass``: 60 skylines each, 0.2 deg noise, 10 %
  missing, a compass good to 4 deg; ``estimate(..., 4.0)``.
- ``chain`` (with ``--chain``): the skylines the demo session detects for seeds 1001-1030, located with
  ``locate()`` and ``EstimatorConfig()`` as bench/session_chain.py does (on the demo's database).

``alternate`` runs each checkout in turn on each case, in each round, and prints the medians and
their ratios to the first checkout with the load (``os.getloadavg``) met by each run; with
``--answers-dir`` it keeps every run's answers there for ``compare``.  ``compare`` checks every field
of every answer for exact equality (NaN equal to NaN; arrays by dtype, shape and value), all but the
estimate's wall time.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import math
import os
import pickle
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "data"
MAPS = {
    "jacksboro": ("jacksboro", None),
    "white-mountains": (str(SHARED / "dem_srtm_hgt" / "N44W072.hgt"), (-71.40, 44.20, -71.20, 44.35)),
}
#: case: (map, trials, no compass)
ACCURACY_CASES = {
    "jacksboro-no-compass": ("jacksboro", 40, True),
    "jacksboro-compass": ("jacksboro", 60, False),
    "white-mountains-compass": ("white-mountains", 60, False),
}
CASE_SEED = 5
CHAIN_SEEDS = range(1001, 1031)
SIGMA_DEG = (0.3, 0.8)
COMPASS_DEG = 4.0
#: fields left out of the comparison: the estimate's own wall time
UNCOMPARED = {"elapsed_s"}


def make_cases(out: Path, chain: bool) -> None:
    """The skylines of every case, made by this checkout."""
    sys.path.insert(0, str(HERE.parent))
    from appliance.locating.position import skyline_grid
    from bench.estimator_accuracy import between_nodes, map_database, measured_skyline
    from tests.reference_render import reference_skyline

    arrays: dict[str, np.ndarray] = {}
    for name, (map_name, trials, no_compass) in ACCURACY_CASES.items():
        noise, missing, compass = (0.5, 0.25, 180.0) if no_compass else (0.2, 0.10, COMPASS_DEG)
        dem, db = map_database(map_name)
        grid = skyline_grid(db)
        rng = np.random.default_rng(CASE_SEED)
        rows = []
        for _ in range(trials):
            _, _, lat, lon = between_nodes(db, grid, rng)
            truth = reference_skyline(dem, float(lat), float(lon), 1.5)
            az, el, _ = measured_skyline(truth, rng, noise, missing, compass)
            rows.append(el)
        arrays[f"{name}/azimuth_deg"] = az
        arrays[f"{name}/elevation_deg"] = np.array(rows)
        print(f"{name}: {trials} skylines", file=sys.stderr)
    if chain:
        from bench import session_chain

        session_chain._setup()
        st = session_chain._STATE
        rows, azs = [], []
        for seed in CHAIN_SEEDS:
            _, _, sky = session_chain.session_skyline(seed, st["dem"], st["db"], st["intr"], st["ses"])
            azs.append(np.asarray(sky.azimuth_deg, dtype=float))
            rows.append(np.asarray(sky.elevation_deg, dtype=float))
        if any(a.shape != azs[0].shape or not np.array_equal(a, azs[0]) for a in azs):
            sys.exit("the chain's skylines do not share one azimuth grid")
        arrays["chain/azimuth_deg"] = azs[0]
        arrays["chain/elevation_deg"] = np.array(rows)
        print(f"chain: {len(rows)} skylines", file=sys.stderr)
    np.savez(out, **arrays)


def _database(map_name: str) -> Any:
    """The map's database as this checkout builds it, kept in its bench/cache."""
    from appliance.terrain.database import build_database, load_database
    from appliance.terrain.dem import load_dem

    dem_path, bounds = MAPS[map_name]
    dem = load_dem(dem_path)
    path = Path.cwd() / "bench" / "cache" / f"{map_name}-native.viperdb"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        build_database(dem, path, search_bounds=bounds, progress=None)
    return load_database(path, dem)


def _skyline_grid() -> Any:
    try:
        from appliance.locating.position import skyline_grid
    except ImportError:  # older checkouts
        from appliance.position import skyline_grid  # type: ignore[no-redef]
    return skyline_grid


def _answer(res: Any) -> dict[str, Any]:
    """Every field of an answer (dataclasses, recursively), but its wall time."""
    if dataclasses.is_dataclass(res) and not isinstance(res, type):
        return {f.name: _answer(getattr(res, f.name)) for f in dataclasses.fields(res) if f.name not in UNCOMPARED}
    if isinstance(res, (list, tuple)):
        return type(res)(_answer(v) for v in res)  # type: ignore[return-value]
    return res


def _chain_runner() -> Any:
    """locate() on the demo's database as bench/session_chain.py calls it (the arguments this
    checkout's ``locate`` takes)."""
    from appliance.config import EstimatorConfig
    from appliance.skyline import Skyline
    from appliance.terrain.dem import load_dem

    try:
        from appliance.locating.position import locate
    except ImportError:
        from appliance.position import locate  # type: ignore[no-redef]
    from appliance.sim.demo import demo_database

    dem = load_dem("jacksboro")
    cache = Path.cwd() / "bench" / "cache" / "demo-db"
    cache.mkdir(parents=True, exist_ok=True)
    db = demo_database(dem, cache)
    grid = _skyline_grid()(db)
    est = EstimatorConfig()
    wanted = {"grid": grid, "occlusion_weight": est.occlusion_weight, "map_sigma_m": est.map_vertical_sigma_m,
              "sigma_floor_deg": getattr(est, "sigma_floor_deg", None)}
    takes = inspect.signature(locate).parameters
    kwargs = {k: v for k, v in wanted.items() if k in takes}

    def run(az: np.ndarray, el: np.ndarray) -> Any:
        return locate(db, Skyline(az, el), est.sigma_deg, est.heading_tolerance_deg, **kwargs)

    return run


def run_case(cases: Path, name: str, out: Path, answers: bool) -> None:
    """This checkout (the working folder) on one case: CPU time of each estimate, and its answers."""
    sys.path.insert(0, str(Path.cwd()))
    import appliance

    where = Path(appliance.__file__).resolve()
    if Path.cwd().resolve() not in where.parents:
        sys.exit(f"appliance is imported from {where}, not from the working folder {Path.cwd()}")
    data = np.load(cases)
    az = data[f"{name}/azimuth_deg"]
    els = data[f"{name}/elevation_deg"]
    if name == "chain":
        one = _chain_runner()
    else:
        from appliance.estimator import estimate

        map_name, _, no_compass = ACCURACY_CASES[name]
        grid = _skyline_grid()(_database(map_name))
        compass = None if no_compass else COMPASS_DEG

        def one(a: np.ndarray, e: np.ndarray) -> Any:
            return estimate(grid, a, e, SIGMA_DEG, compass)

    one(az, els[0])  # compiled kernels loaded, lazy tables made
    load = [os.getloadavg()[0]]
    cpu_s, kept = [], []
    for el in els:
        t = time.process_time()
        res = one(az, el)
        cpu_s.append(time.process_time() - t)
        if answers:
            kept.append(_answer(res))
    load.append(os.getloadavg()[0])
    with out.open("wb") as fh:
        pickle.dump({"case": name, "cpu_s": cpu_s, "load": load, "answers": kept if answers else None}, fh)


def same(a: Any, b: Any, where: str, diffs: list[str]) -> None:
    """Exact equality, NaN equal to NaN; the places that differ appended to ``diffs``."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            diffs.append(f"{where}: fields {sorted(a.keys() ^ b.keys())} in one only")
        for k in a.keys() & b.keys():
            same(a[k], b[k], f"{where}.{k}", diffs)
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype
                and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")):
            diffs.append(f"{where}: arrays differ")
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if type(a) is not type(b) or len(a) != len(b):
            diffs.append(f"{where}: {a!r} != {b!r}")
        else:
            for i, (x, y) in enumerate(zip(a, b)):
                same(x, y, f"{where}[{i}]", diffs)
    elif isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        pass
    elif type(a) is not type(b) or a != b:
        diffs.append(f"{where}: {a!r} != {b!r}")


def compare(a_path: Path, b_path: Path) -> int:
    a, b = (pickle.loads(p.read_bytes()) for p in (a_path, b_path))
    if a["answers"] is None or b["answers"] is None or len(a["answers"]) != len(b["answers"]):
        print(f"{a_path} and {b_path}: not the same case with answers")
        return 2
    diffs: list[str] = []
    for i, (x, y) in enumerate(zip(a["answers"], b["answers"])):
        same(x, y, f"{a['case']}[{i}]", diffs)
    n_fields = sum(len(x) for x in a["answers"])
    for d in diffs[:20]:
        print(f"  {d}")
    print(f"{a['case']}: {len(a['answers'])} answers, {n_fields} top-level fields: "
          + ("all equal" if not diffs else f"{len(diffs)} differences"))
    return 0 if not diffs else 1


def alternate(cases: Path, checkouts: list[tuple[str, Path]], rounds: int, names: list[str],
              answers_dir: Path | None) -> None:
    script = Path(__file__).resolve()
    med: dict[tuple[str, str], list[float]] = {}
    loads: dict[tuple[str, str], list[float]] = {}
    tmp = Path(os.environ.get("TMPDIR", "/tmp"))
    for r in range(rounds):
        for name in names:
            for label, folder in checkouts:
                keep = answers_dir is not None and r == 0
                out = (answers_dir / f"{label}-{name}.pkl") if keep else tmp / f"in_process_cost-{os.getpid()}.pkl"
                cmd = [sys.executable, str(script), "run", "--cases", str(cases.resolve()), "--case", name,
                       "--out", str(out)] + (["--answers"] if keep else [])
                subprocess.run(cmd, cwd=folder, env={**os.environ, "PYTHONPATH": str(folder)}, check=True)
                got = pickle.loads(out.read_bytes())
                if not keep:
                    out.unlink()
                m = 1e3 * statistics.median(got["cpu_s"])
                med.setdefault((name, label), []).append(m)
                loads.setdefault((name, label), []).extend(got["load"])
                print(f"round {r + 1} {name} {label}: {m:.1f} ms (load {got['load'][0]:.1f}-{got['load'][1]:.1f})",
                      flush=True)
    labels = [label for label, _ in checkouts]
    heads = ["in-process cost (CPU ms, median)", *labels, *(f"{x}/{labels[0]}" for x in labels[1:]), "load"]
    print("\n| " + " | ".join(heads) + " |\n" + "|---" * len(heads) + "|")
    for name in names:
        cells = [", ".join(f"{v:.1f}" for v in med[(name, x)]) for x in labels]
        ratios = [", ".join(f"{v / b:.2f}" for v, b in zip(med[(name, x)], med[(name, labels[0])])) for x in labels[1:]]
        ld = [v for x in labels for v in loads[(name, x)]]
        row = [f"{name} ({rounds} rounds)", *cells, *ratios, f"{min(ld):.1f}-{max(ld):.1f}"]
        print("| " + " | ".join(row) + " |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("cases")
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--chain", action="store_true")
    r = sub.add_parser("run")
    r.add_argument("--cases", type=Path, required=True)
    r.add_argument("--case", required=True)
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--answers", action="store_true")
    a = sub.add_parser("alternate")
    a.add_argument("--cases", type=Path, required=True)
    a.add_argument("--rounds", type=int, default=2)
    a.add_argument("--case", action="append", help="cases to run (default: every case in the file)")
    a.add_argument("--answers-dir", type=Path, help="keep each checkout's answers of the first round here")
    a.add_argument("checkouts", nargs="+", help="LABEL=FOLDER, the first the base of the ratios")
    k = sub.add_parser("compare")
    k.add_argument("a", type=Path)
    k.add_argument("b", type=Path)
    args = ap.parse_args()
    if args.cmd == "cases":
        make_cases(args.out, args.chain)
    elif args.cmd == "run":
        run_case(args.cases, args.case, args.out, args.answers)
    elif args.cmd == "alternate":
        with np.load(args.cases) as data:
            present = sorted({k.split("/")[0] for k in data.files})
        names = args.case or [n for n in [*ACCURACY_CASES, "chain"] if n in present]
        checkouts = [(lab, Path(f).resolve()) for lab, f in (x.split("=", 1) for x in args.checkouts)]
        if args.answers_dir is not None:
            args.answers_dir.mkdir(parents=True, exist_ok=True)
        alternate(args.cases, checkouts, args.rounds, names, args.answers_dir)
    else:
        return compare(args.a, args.b)
    return 0


if __name__ == "__main__":
    sys.exit(main())
