"""The live view during a whole simulated session, seen by real WebSocket clients speaking the Foxglove
protocol; the session's log read back by the independent ``mcap`` reader: every message of the log
received once by a client connected from the start, none twice when a second one joins, every JSON
message against its channel's schema, and the Foxglove frames (camera_optical, the posterior grid
placed in world)."""

from __future__ import annotations

import json
import math
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from mcap.reader import make_reader

from appliance.cli.main import main
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.live import LiveServer, parse_address
from appliance.logbook.live_channels import session_channels
from appliance.sim.field_session import run_field_session
from tests.conftest import small_config
from tests.live_client import StrictClient

jsonschema = pytest.importorskip("jsonschema")
#: every topic a session may write, advertised from the start
ALL_TOPICS = {spec.topic for spec in session_channels()}
#: the second client joins once the first has received this many camera frames
JOIN_AFTER_FRAMES = 3


@dataclass
class LiveRun:
    result: Any
    db: Any
    first: StrictClient  # connected before the session's first message
    second: StrictClient  # joined mid-session
    logged: dict[str, list[bytes]]  # the log's payloads per topic, in the order written


def _wait(condition: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.02)
    return condition()


def _by_topic(pairs) -> dict[str, list[bytes]]:
    payloads: dict[str, list[bytes]] = {}
    for topic, data in pairs:
        payloads.setdefault(topic, []).append(bytes(data))
    return payloads


@pytest.fixture(scope="module")
def live_run(tmp_path_factory, dem, window_db):
    """A whole simulated session served live: one strict client (it subscribes once to each channel as
    advertised, never again) connected and subscribed before the first message, a second one joining
    after the third camera frame; the server closed as the commands close it, right after the session."""
    out = tmp_path_factory.mktemp("live")
    server = LiveServer("127.0.0.1", 0, linger_s=30.0)
    first, second = StrictClient(server.port), StrictClient(server.port)
    first.start()
    assert _wait(lambda: any(topics == ALL_TOPICS for topics in server.subscriptions().values()), 60.0)

    def join_later() -> None:
        if _wait(lambda: first.counts()[t.IMAGE] >= JOIN_AFTER_FRAMES, 600.0):
            second.start()

    joiner = threading.Thread(target=join_later, daemon=True)
    joiner.start()
    try:
        result, _ = run_field_session(small_config(), out, seed=5, dem=dem, db=window_db, publisher=server)
    finally:
        server.close()  # lingers until both clients have received everything
    for client in (first, second):
        assert client.closed.wait(30.0)  # the server closed the connection
        client.finish()
        assert client.error is None, client.error
    joiner.join(1.0)
    logged = _by_topic((channel.topic, message.data) for _s, channel, message in _log_messages(result.log_path))
    return LiveRun(result, window_db, first, second, logged)


@pytest.fixture(scope="module")
def live_session(live_run):
    return live_run.result, live_run.first, live_run.db


def test_a_client_connected_from_the_start_receives_every_message_once(live_run):
    first, logged = live_run.first, live_run.logged
    received = _by_topic((topic, data) for topic, _, data in first.messages)
    assert first.refused() == [] and first.statuses == []
    assert {k: len(v) for k, v in received.items()} == {k: len(v) for k, v in logged.items()}
    assert received == logged  # the same bytes, in the order written, none twice
    # the topics written last (the estimate, its region and posterior, the rendered skyline, the
    # procedures' ends, the log's last lines) are among them: nothing was cut off at the close
    for topic in (t.ESTIMATE_FIX, t.ESTIMATE_RECORD, t.POSTERIOR, t.REGION, t.SKYLINE_DETECTED,
                  t.SKYLINE_RENDERED, t.SESSION, t.PROCEDURE, t.LOG):
        assert logged.get(topic), topic
    assert b'"procedure":"estimate"' in logged[t.PROCEDURE][-1]
    assert f"session {live_run.result.session_id} finished".encode() in logged[t.LOG][-1]


def test_every_channel_is_advertised_once_with_the_schema_of_the_log(live_run):
    advertised = Counter(ch["topic"] for ch in live_run.first.channels.values())
    assert advertised == Counter(ALL_TOPICS)
    specs = {spec.topic: spec for spec in session_channels()}
    with open(live_run.result.log_path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.channels) == len(live_run.logged)
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        spec = specs[channel.topic]
        assert (schema.name, schema.encoding, bytes(schema.data), channel.message_encoding) == (
            spec.schema_name, spec.schema_encoding, spec.schema_data, spec.message_encoding), channel.topic


def test_a_client_joining_mid_session_gets_the_latest_once_then_everything(live_run):
    second, logged = live_run.second, live_run.logged
    received = _by_topic((topic, data) for topic, _, data in second.messages)
    assert second.refused() == [] and second.statuses == []
    # it joined after the third frame: the latest frame then and every later one, no earlier one
    assert 0 < len(received[t.IMAGE]) <= len(logged[t.IMAGE]) - JOIN_AFTER_FRAMES + 1
    for topic, payloads in received.items():
        if topic != t.TF:  # /tf is latched per child frame: the latest of each, then every later one
            assert payloads == logged[topic][-len(payloads):], topic
    assert received[t.CALIBRATION] == logged[t.CALIBRATION]  # written once, before it joined: latched
    assert set(received) == set(logged) and set(received[t.TF]) <= set(logged[t.TF])


def test_live_client_receives_the_panorama_the_estimate_and_the_status(live_session):
    result, client, _ = live_session
    assert result.estimate is not None
    assert client.server_info["name"] == "viper"
    advertised = {ch["topic"]: ch["schemaName"] for ch in client.channels.values()}
    assert advertised[t.PANORAMA] == "foxglove.CompressedImage"
    assert advertised[t.ESTIMATE_FIX] == "foxglove.LocationFix"
    assert advertised[t.PROCEDURE] == "viper.Procedure"
    assert advertised[t.REGION] == "foxglove.GeoJSON"

    pano = CompressedImage.FromString(client.payloads(t.PANORAMA)[-1])
    assert pano.format == "jpeg" and pano.data[:2] == b"\xff\xd8"
    height, width = result.panorama.image.shape[:2]
    import cv2

    decoded = cv2.imdecode(np.frombuffer(pano.data, np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape[:2] == (height, width)

    fix = LocationFix.FromString(client.payloads(t.ESTIMATE_FIX)[-1])
    assert fix.latitude == pytest.approx(result.estimate.lat, abs=1e-9)
    assert fix.longitude == pytest.approx(result.estimate.lon, abs=1e-9)

    statuses = {}
    for p in client.payloads(t.PROCEDURE):
        rec = json.loads(p)
        statuses[rec["procedure"]] = rec["status"]
    assert statuses == {k: v for k, v in result.outcomes.items() if k != "true_position"}

    # the skyline overlay: the detected skyline at the panorama's pixels
    from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

    overlay = ImageAnnotations.FromString(client.payloads(t.PANORAMA_SKYLINE)[-1])
    pts = np.array([(p.x, p.y) for strip in overlay.points for p in strip.points])
    sky = result.skyline
    el = np.interp(result.panorama.column_azimuth_deg(pts[:, 0]), sky.azimuth_deg, sky.elevation_deg, period=360)
    np.testing.assert_allclose(pts[:, 1], result.panorama.elevation_to_row(el), atol=0.5)
    assert len(pts) > 0.5 * np.isfinite(sky.elevation_deg).sum()

    lines = [m.Log.FromString(p).message for p in client.payloads(t.LOG)]
    assert any(f"session {result.session_id} finished" in line for line in lines)


def _log_messages(path):
    with open(path, "rb") as f:
        yield from make_reader(f).iter_messages()


def test_every_json_message_of_the_log_matches_its_channel_schema(live_session):
    result, _, _ = live_session
    checked: dict[str, int] = {}
    for schema, channel, message in _log_messages(result.log_path):
        if channel.message_encoding != "json":
            continue
        spec = json.loads(schema.data)
        assert spec["additionalProperties"] is False
        validator = jsonschema.Draft202012Validator(spec)
        errors = [e.message for e in validator.iter_errors(json.loads(message.data))]
        assert not errors, f"{channel.topic}: {errors}"
        checked[channel.topic] = checked.get(channel.topic, 0) + 1
    for topic in (t.ESTIMATE_RECORD, t.PROCEDURE, t.HEADING_RAW, t.CAPTURE, t.SESSION, t.SKYLINE_DETECTED):
        assert checked.get(topic, 0) > 0, topic


def _check_feature(feature):
    kind = feature["properties"]["kind"]
    errors = [e.message for e in jsonschema.Draft202012Validator(t.GEOJSON_FEATURE_PROPERTIES[kind])
              .iter_errors(feature["properties"])]
    assert not errors, f"{kind}: {errors}"
    assert feature["geometry"]["type"] == t.GEOJSON_FEATURE_GEOMETRY[kind]


def test_the_region_topic_has_strict_properties_and_matches_the_report_layers(live_session, tmp_path):
    from foxglove_schemas_protobuf.GeoJSON_pb2 import GeoJSON

    from appliance.outputs.files import write_points_geojson, write_region_geojson

    result, client, db = live_session
    logged = [json.loads(GeoJSON.FromString(message.data).geojson)
              for _s, channel, message in _log_messages(result.log_path) if channel.topic == t.REGION]
    live = [json.loads(GeoJSON.FromString(p).geojson) for p in client.payloads(t.REGION)]
    assert len(logged) == 1 and live[-1] == logged[0]
    features = logged[0]["features"]
    assert [f["properties"]["kind"] for f in features] == ["region", "estimate"]
    for f in features:
        _check_feature(f)
    assert features[0]["properties"]["n_cells"] == result.estimate.result.region_nodes.size

    write_region_geojson(db, result.estimate, tmp_path / "region.geojson")
    write_points_geojson(result.estimate, tmp_path / "points.geojson", (36.6, -84.25))
    region = json.loads((tmp_path / "region.geojson").read_text())["features"]
    points = json.loads((tmp_path / "points.geojson").read_text())["features"]
    for f in region + points:
        _check_feature(f)
    assert region == features[:1] and points[:1] == features[1:]
    assert points[1]["geometry"]["coordinates"] == [-84.25, 36.6]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**features[1]["properties"], "extra": 1}, t.GEOJSON_FEATURE_PROPERTIES["estimate"])


def test_the_session_runner_hands_the_publisher_to_the_session(monkeypatch, tmp_path):
    import types

    import appliance.acquisition.onboard as onboard_mod
    import appliance.acquisition.session as session_mod
    import appliance.sim.field_session as field_mod
    from appliance.cli._platform import open_devices, session_runner
    from appliance.config import Config, PlatformConfig, PlatformKind

    publisher, seen = object(), {}
    done = types.SimpleNamespace(status="ok")

    def field_session(config, log_dir, seed=None, should_stop=None, on_status=None, publisher=None):
        seen["sim"] = (seed, publisher)
        return done, None

    def platform_session(opener, config, log_dir, db, should_stop, on_status, publisher=None):
        seen["hardware"] = (opener, publisher)
        return done

    monkeypatch.setattr(field_mod, "run_field_session", field_session)
    monkeypatch.setattr(session_mod, "run_platform_session", platform_session)
    monkeypatch.setattr(onboard_mod, "load_session_database", lambda session: None)
    assert session_runner(Config(), 7, publisher=publisher)(tmp_path, lambda: False, print) is done
    assert seen["sim"] == (7, publisher)
    hardware = Config(platform=PlatformConfig(PlatformKind.HARDWARE))
    assert session_runner(hardware, publisher=publisher)(tmp_path, lambda: False, lambda s: None) is done
    assert seen["hardware"] == (open_devices, publisher)


def test_a_strict_schema_refuses_an_undeclared_field():
    validator = jsonschema.Draft202012Validator(t.JSON_SCHEMAS["viper.HeadingRaw"])
    assert not list(validator.iter_errors({"mag_x": 1.0, "stage_deg": 3.0}))
    assert [e.validator for e in validator.iter_errors({"mag_x": 1.0, "tilt": 3.0})] == ["additionalProperties"]


def _rotate(q, v):
    x, y, z, w = q.x, q.y, q.z, q.w
    u = np.array([x, y, z])
    v = np.asarray(v, float)
    return 2 * np.dot(u, v) * u + (w * w - np.dot(u, u)) * v + 2 * w * np.cross(u, v)


def test_optical_frame_looks_along_the_cameras_forward_axis():
    tf = m.optical_transform(0)
    assert (tf.parent_frame_id, tf.child_frame_id) == ("camera", "camera_optical")
    np.testing.assert_allclose(_rotate(tf.rotation, [0, 0, 1]), [0, 1, 0], atol=1e-12)  # forward
    np.testing.assert_allclose(_rotate(tf.rotation, [1, 0, 0]), [1, 0, 0], atol=1e-12)  # right
    np.testing.assert_allclose(_rotate(tf.rotation, [0, 1, 0]), [0, 0, -1], atol=1e-12)  # down
    # with the stage at 90 deg (clockwise), the optical axis looks east in the platform frame
    stage = m.stage_transform(0, 90.0)
    np.testing.assert_allclose(_rotate(stage.rotation, _rotate(tf.rotation, [0, 0, 1])), [1, 0, 0], atol=1e-12)
    assert m.compressed_image(0, b"").frame_id == "camera_optical"


def test_log_frames_place_images_in_camera_optical_and_the_posterior_in_world(live_session):
    result, _, db = live_session
    transforms: dict[str, FrameTransform] = {}
    frame_ids: dict[str, set[str]] = {}
    grid = None
    for _schema, channel, message in _log_messages(result.log_path):
        if channel.topic == t.TF:
            tf = FrameTransform.FromString(message.data)
            transforms[tf.child_frame_id] = tf
        elif channel.topic == t.IMAGE:
            frame_ids.setdefault(channel.topic, set()).add(CompressedImage.FromString(message.data).frame_id)
        elif channel.topic == t.CALIBRATION:
            frame_ids.setdefault(channel.topic, set()).add(CameraCalibration.FromString(message.data).frame_id)
        elif channel.topic == t.POSTERIOR:
            from foxglove_schemas_protobuf.Grid_pb2 import Grid

            grid = Grid.FromString(message.data)
    assert frame_ids[t.IMAGE] == frame_ids[t.CALIBRATION] == {"camera_optical"}
    optical = transforms["camera_optical"]
    assert optical.parent_frame_id == "camera"
    np.testing.assert_allclose(_rotate(optical.rotation, [0, 0, 1]), [0, 1, 0], atol=1e-12)

    assert grid is not None and grid.frame_id == "skyline-grid"
    place = transforms["skyline-grid"]
    assert place.parent_frame_id == "world"
    # the estimate's node, in the grid's frame, lies at the world's origin (the estimate)
    g, res = db.grid, result.estimate.result
    in_grid = np.array([(res.col + 0.5) * g.dx_m, (g.n_rows - 1 - res.row + 0.5) * g.dy_m, 0.0])
    tr = place.translation
    world = _rotate(place.rotation, in_grid) + [tr.x, tr.y, tr.z]
    np.testing.assert_allclose(world[:2], [0.0, 0.0], atol=1e-6)
    # grid north points at the grid convergence (true azimuth) of the estimate's node
    north = _rotate(place.rotation, [0, 1, 0])
    gamma = float(db.convergence_deg[res.node])
    assert math.degrees(math.atan2(north[0], north[1])) == pytest.approx(gamma, abs=1e-9)


def test_skyline_overlay_breaks_at_gaps_and_at_the_seam():
    cols = np.array([10.0, 11.0, np.nan, 13.0, 14.0, 15.0, 1.0, 2.0])
    rows = np.array([5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0])
    ann = m.skyline_annotations(0, cols, rows)
    strips = [[(p.x, p.y) for p in s.points] for s in ann.points]
    assert strips == [[(10.0, 5.0), (11.0, 6.0)], [(13.0, 8.0), (14.0, 9.0), (15.0, 10.0)], [(1.0, 11.0), (2.0, 12.0)]]


def test_live_address_defaults_to_localhost():
    assert parse_address("8765") == ("127.0.0.1", 8765)
    assert parse_address("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_address("[::1]:9000") == ("::1", 9000)


def test_bad_live_address_is_one_line_and_non_zero(capsys, tmp_path):
    code = main(["capture", "--log-dir", str(tmp_path), "--live", "localhost:http"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0
    assert err[-1].startswith("viper capture: error: --live 'localhost:http'")
