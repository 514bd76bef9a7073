"""Shared fixtures: the real data set beside the project (../shared/data), skipped where absent."""

from __future__ import annotations

from pathlib import Path

import pytest

from appliance.config import CameraDeviceConfig, Config, DevicesConfig, SessionConfig, SimConfig

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session", autouse=True)
def own_cache_folder(tmp_path_factory):
    """The appliance's cache folder (records of verified databases) is the test run's own, for this
    process and the commands it starts; and they run in process."""
    folder = tmp_path_factory.mktemp("viper-cache")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("VIPER_CACHE_DIR", str(folder))
        # commands run in process: a `viper serve` of the user running the tests takes none of them
        mp.setenv("VIPER_SOCKET", "")
        yield folder


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it lives beside the project in CI)")
    return SHARED_DATA


def data_file(relpath: str) -> Path:
    """Path of a file in ../shared/data; skips the calling test with a reason if it is absent."""
    p = SHARED_DATA / relpath
    if not p.exists():
        pytest.skip(f"real data file {p} is absent")
    return p


# a 7 km x 8 km window of the jacksboro map: its database builds in seconds
WINDOW = (-84.30, 36.55, -84.22, 36.62)


@pytest.fixture(scope="session")
def dem():
    """The jacksboro DEM (matplotlib's sample data)."""
    from appliance.terrain.dem import load_dem

    return load_dem("jacksboro")


@pytest.fixture(scope="session")
def window_db(dem, tmp_path_factory):
    """The skyline database of :data:`WINDOW`, built once for the whole test run."""
    from appliance.terrain.database import build_database, load_database

    path = tmp_path_factory.mktemp("db") / "window.viperdb"
    build_database(dem, path, search_bounds=WINDOW, progress=None)
    return load_database(path, dem)


@pytest.fixture(scope="session")
def field_traverse(tmp_path_factory, dem, window_db):
    """A rover's traverse of three stops on the simulated platform (what ``viper demo --traverse 3`` runs, at
    :func:`small_config`'s settings on :data:`WINDOW`): its result, the true stops and its folder; shared by
    the traverse's tests and its replay's, which only read it."""
    from appliance.sim.field_session import run_field_traverse

    out = tmp_path_factory.mktemp("traverse")
    result, truths = run_field_traverse(small_config(), out, 3, seed=3, dem=dem, db=window_db)
    return result, truths, out


def rover_config_text(db_path: Path, stops: int = 2) -> str:
    """A configuration (TOML) of a rover's traverse on the simulated platform: ``stops`` stops on the
    database ``db_path``, small frames and fast simulated time."""
    return ('[platform]\nkind = "sim"\n'
            f'[session]\ndatabase = "{db_path}"\ntruth_duration_s = 10.0\nsettle_s = 0.2\n'
            "[devices.camera]\nwidth = 320\nheight = 240\n"
            f"[traverse]\nstops = {stops}\n"
            "[sim]\ntime_rate = 50.0\n")


def small_config(time_rate: float = 50.0) -> Config:
    """A quick simulated session: short GPS averaging, short settling, a 320x240 camera."""
    return Config(
        session=SessionConfig(truth_duration_s=10.0, settle_s=0.2),
        devices=DevicesConfig(camera=CameraDeviceConfig(width=320, height=240)),
        sim=SimConfig(time_rate=time_rate),
    )


@pytest.fixture(scope="module")
def client():
    """A real Dask cluster on this machine: two single-threaded worker processes, one per module."""
    import distributed

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=50) as cluster, distributed.Client(cluster) as c:
        yield c


def one_line_error(out, *words: str) -> str:
    """A finished command (``subprocess.CompletedProcess``) that failed with exactly one line on stderr
    holding every one of ``words``: that line."""
    assert out.returncode != 0
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]
