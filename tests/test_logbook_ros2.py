"""Logs as a Foxglove or ROS 2 user expects them: a two-stop traverse written by ``viper capture
--log-encoding ros2`` on the simulated platform, read back by independent readers (rosbags' pure-Python
rosbag2 reader, mcap's own reader, a CRC computed here); the metadata records, the data CRC and the
sequence numbers of a protobuf log written by the logbook itself; the Foxglove layout shipped."""

from __future__ import annotations

import hashlib
import json
import math
import struct
import zlib
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

import appliance
from appliance.acquisition.log_metadata import write_log_metadata
from appliance.acquisition.replay import read_session
from appliance.bodies import geodesic_distance_m
from appliance.cli.main import main
from appliance.config import Config, LogEncoding, load_config
from appliance.errors import ConfigError
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.writer import Logbook
from tests.conftest import rover_config_text

rosbags_highlevel = pytest.importorskip("rosbags.highlevel")

REPO = Path(__file__).resolve().parents[1]
T0 = 1_780_000_000_000_000_000
DATA_END_OPCODE = 0x0F
DATA_END_BYTES = 1 + 8 + 4  # opcode, record length, data section CRC


@pytest.fixture(scope="module")
def ros2_log(tmp_path_factory, window_db):
    """A two-stop traverse on the simulated platform, logged with ROS 2 messages."""
    folder = tmp_path_factory.mktemp("ros2")
    cfg = folder / "rover.toml"
    cfg.write_text(rover_config_text(window_db.path))
    logs = folder / "logs"
    code = main(["capture", "--config", str(cfg), "--log-dir", str(logs), "--seed", "3", "--log-encoding", "ros2"])
    assert code == 0
    (log,) = logs.glob("*.mcap")
    return log


def _rosbags_messages(log: Path):
    """(topic, ROS 2 type, log time, decoded message) of every message, as rosbags reads them."""
    with rosbags_highlevel.AnyReader([log]) as reader:
        for conn, time_ns, raw in reader.messages():
            yield conn.topic, conn.msgtype, time_ns, reader.deserialize(raw, conn.msgtype)


def _log_info_json(log: Path, capsys) -> dict:
    capsys.readouterr()
    assert main(["log", "info", "--json", str(log)]) == 0
    return json.loads(capsys.readouterr().out)


def _stamp_ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def test_rosbags_decodes_every_message_and_counts_as_log_info(ros2_log, capsys):
    counts: Counter[str] = Counter()
    types: dict[str, str] = {}
    records = {}
    fixes = {}
    for topic, msgtype, _, msg in _rosbags_messages(ros2_log):
        counts[topic] += 1
        types[topic] = msgtype
        if topic == t.ESTIMATE_RECORD:
            records[len(records)] = json.loads(msg.data)
        elif topic == t.ESTIMATE_FIX:
            fixes[len(fixes)] = msg
    info = _log_info_json(ros2_log, capsys)
    assert info["profile"] == "ros2" and info["complete"] is True
    assert {name: topic["count"] for name, topic in info["topics"].items()} == dict(counts)
    assert info["message_count"] == sum(counts.values())
    assert all(topic["message_encoding"] == "cdr" for topic in info["topics"].values())
    assert types[t.ESTIMATE_FIX] == types[t.GPS_FIX] == "sensor_msgs/msg/NavSatFix"
    assert types[t.PANORAMA] == types[t.IMAGE] == "sensor_msgs/msg/CompressedImage"
    assert types[t.TF] == "tf2_msgs/msg/TFMessage"
    assert types[t.ESTIMATE_POSE] == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert types[t.ESTIMATE_RECORD] == types[t.PROCEDURE] == "std_msgs/msg/String"
    assert info["topics"][t.ESTIMATE_RECORD]["json_schema"] == "viper.Estimate"
    assert info["topics"][t.TRAVERSE_STOP]["json_schema"] == "viper.TraverseStop"
    assert info["topics"][t.ESTIMATE_FIX]["json_schema"] is None
    # each stop's fix carries its estimate's covariance (east, north) as a known covariance
    assert len(fixes) == len(records) == 2
    for i, fix in fixes.items():
        cov = np.asarray(records[i]["covariance_m2"], float)
        assert fix.position_covariance_type == 3  # COVARIANCE_TYPE_KNOWN
        # the record keeps the covariance to 4 decimals (m^2)
        np.testing.assert_allclose(np.asarray(fix.position_covariance).reshape(3, 3)[:2, :2], cov, atol=5e-5)
        assert math.isclose(fix.latitude, records[i]["lat"], abs_tol=1e-12)


def test_log_info_text_and_json_say_the_same(ros2_log, capsys):
    info = _log_info_json(ros2_log, capsys)
    assert main(["log", "info", str(ros2_log)]) == 0
    text = capsys.readouterr().out
    assert f"{info['size_bytes']} bytes, {info['message_count']} messages, complete" in text
    assert f"lat {info['estimate']['lat']:.6f} lon {info['estimate']['lon']:.6f}" in text
    assert f"sha256 {info['metadata']['viper.map']['sha256']}" in text
    for name, topic in info["topics"].items():
        assert any(line.split()[:2] == [name, str(topic["count"])] for line in text.splitlines()), name


def test_metadata_records_read_by_mcaps_reader(ros2_log, window_db):
    with open(ros2_log, "rb") as f:
        records = {r.name: r.metadata for r in make_reader(f).iter_metadata()}
    assert set(records) == {"viper.software", "viper.config", "viper.calibration", "viper.map"}
    assert records["viper.software"]["version"] == appliance.__version__
    assert records["viper.map"]["sha256"] == hashlib.sha256(Path(window_db.path).read_bytes()).hexdigest()
    assert records["viper.map"]["dem_sha256"] == window_db.header["dem_sha256"]
    config = json.loads(records["viper.config"]["text"])
    assert config["logbook"]["encoding"] == "ros2" and config["traverse"]["stops"] == 2
    assert config["session"]["database"] == str(window_db.path)
    intrinsics = json.loads(records["viper.calibration"]["camera_intrinsics"])
    assert (intrinsics["width"], intrinsics["height"]) == (320, 240)


def _data_section(log: Path) -> tuple[bytes, int]:
    """The log's data section (from its magic to the DataEnd record) and the CRC its DataEnd declares,
    found from the footer's summary offset."""
    raw = log.read_bytes()
    summary_start = struct.unpack_from("<Q", raw, len(raw) - 8 - 20)[0]
    data_end = summary_start - DATA_END_BYTES
    assert raw[data_end] == DATA_END_OPCODE
    (crc,) = struct.unpack_from("<I", raw, data_end + 9)
    return raw[:data_end], crc


def test_the_data_section_crc_is_set_and_holds(ros2_log):
    data, crc = _data_section(ros2_log)
    assert crc != 0 and crc == zlib.crc32(data)
    with open(ros2_log, "rb") as f:
        assert sum(1 for _ in make_reader(f, validate_crcs=True).iter_messages()) > 100


def _sequences(log: Path) -> dict[str, list[int]]:
    out: dict[str, list[int]] = defaultdict(list)
    with open(log, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
            out[channel.topic].append(message.sequence)
    return out


def test_every_channel_counts_its_messages_from_one(ros2_log):
    sequences = _sequences(ros2_log)
    assert len(sequences[t.TF]) > 10
    for topic, seq in sequences.items():
        assert seq == list(range(1, len(seq) + 1)), topic


def test_the_skyline_annotations_carry_the_panoramas_time(ros2_log):
    panoramas, overlays = [], []
    for topic, _, time_ns, msg in _rosbags_messages(ros2_log):
        if topic == t.PANORAMA:
            panoramas.append((time_ns, _stamp_ns(msg.header.stamp)))
        elif topic == t.PANORAMA_SKYLINE:
            stamps = {_stamp_ns(p.timestamp) for p in msg.points}
            assert len(stamps) == 1 and len(msg.points) >= 1
            overlays.append((time_ns, stamps.pop()))
    assert len(panoramas) == len(overlays) == 2
    assert panoramas == overlays
    assert panoramas[0][0] == panoramas[0][1]


def test_the_traverse_frames_share_one_root_at_the_stops_positions(ros2_log):
    parent: dict[str, str] = {}
    offsets = {}
    image_frames = set()
    stops = []
    for topic, _, _, msg in _rosbags_messages(ros2_log):
        if topic == t.TF:
            for tf in msg.transforms:
                child, up = tf.child_frame_id, tf.header.frame_id
                assert parent.setdefault(child, up) == up, f"{child} has two parents"
                if up == m.MAP:
                    offsets[child] = (tf.transform.translation.x, tf.transform.translation.y)
        elif topic == t.IMAGE:
            image_frames.add(msg.header.frame_id)
        elif topic == t.TRAVERSE_STOP:
            stops.append(json.loads(msg.data))

    def root(frame: str) -> str:
        while frame in parent:
            frame = parent[frame]
        return frame

    assert {"stop-0/world", "stop-1/world", "stop-1/platform", "stop-1/camera_optical"} <= set(parent)
    assert {root(f) for f in parent} == {m.MAP}
    assert image_frames == {"stop-0/camera_optical", "stop-1/camera_optical"}
    assert offsets["stop-0/world"] == (0.0, 0.0)
    a, b = stops[0]["position"], stops[1]["position"]
    leg_m = geodesic_distance_m(a["lat"], a["lon"], b["lat"], b["lon"])
    assert leg_m > 100.0
    assert math.isclose(math.hypot(*offsets["stop-1/world"]), leg_m, rel_tol=1e-6)
    north_m = geodesic_distance_m(a["lat"], a["lon"], b["lat"], a["lon"])
    assert math.isclose(abs(offsets["stop-1/world"][1]), north_m, rel_tol=1e-2, abs_tol=1.0)


def test_replay_reads_the_estimate_inputs_of_a_ros2_log(ros2_log):
    data = read_session(ros2_log)
    truths = [(msg.latitude, msg.longitude) for topic, _, _, msg in _rosbags_messages(ros2_log) if topic == t.GPS_TRUTH]
    assert data.complete and data.problem is None
    assert data.intrinsics is not None and (data.intrinsics.width, data.intrinsics.height) == (320, 240)
    assert len(data.frames) == data.facts.captures >= 16
    assert data.frames[0].frame.image.shape == (240, 320, 3)
    assert data.truth == truths[-1]


def test_a_cut_ros2_log_recovers_with_its_metadata_and_decodes(ros2_log, tmp_path, capsys):
    raw = ros2_log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: len(raw) * 2 // 3])
    fixed = tmp_path / "fixed.mcap"
    assert main(["log", "recover", str(cut), "--out", str(fixed)]) == 0
    with open(fixed, "rb") as f:
        names = {r.name for r in make_reader(f).iter_metadata()}
    assert names == {"viper.software", "viper.config", "viper.calibration", "viper.map"}
    counts = Counter(topic for topic, _, _, _ in _rosbags_messages(fixed))
    info = _log_info_json(fixed, capsys)
    assert {name: topic["count"] for name, topic in info["topics"].items()} == dict(counts)
    assert 0 < info["message_count"] < _log_info_json(ros2_log, capsys)["message_count"]
    data, crc = _data_section(fixed)
    assert crc == zlib.crc32(data)


def test_a_protobuf_log_has_the_metadata_crc_and_sequences_too(tmp_path, window_db):
    log = tmp_path / "proto.mcap"
    with Logbook.create(log) as book:
        assert book.encoding is LogEncoding.PROTOBUF
        write_log_metadata(book, Config(), window_db, None)
        for i in range(3):
            book.write_proto(t.TF, m.stage_transform(T0 + i, 10.0 * i), T0 + i)
            book.write_json(t.STAGE_RAW, "viper.StageRaw", {"angle_deg": 10.0 * i}, T0 + i)
        book.write_proto(t.GPS_FIX, m.location_fix(T0, 36.6, -84.3, sigma_m=3.0), T0)
    with open(log, "rb") as f:
        records = {r.name: r.metadata for r in make_reader(f).iter_metadata()}
    assert records["viper.software"]["version"] == appliance.__version__
    assert records["viper.map"]["sha256"] == hashlib.sha256(Path(window_db.path).read_bytes()).hexdigest()
    assert json.loads(records["viper.config"]["text"])["logbook"]["encoding"] == "protobuf"
    data, crc = _data_section(log)
    assert crc != 0 and crc == zlib.crc32(data)
    assert _sequences(log) == {t.TF: [1, 2, 3], t.STAGE_RAW: [1, 2, 3], t.GPS_FIX: [1]}


@pytest.mark.parametrize("value", ['"ros3"', '"ROS2"', "2"])
def test_a_bad_log_encoding_is_one_line_at_config_load(tmp_path, value):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(f"[logbook]\nencoding = {value}\n")
    with pytest.raises(ConfigError) as err:
        load_config(cfg)
    text = str(err.value)
    assert "\n" not in text and "logbook.encoding" in text and "'protobuf' or 'ros2'" in text


def test_the_foxglove_layout_shows_the_logs_topics():
    layout = json.loads((REPO / "examples" / "foxglove-layout.json").read_text())
    panels = layout["configById"]

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)
    by_type = {pid.split("!")[0]: cfg for pid, cfg in panels.items()}
    assert set(by_type) == {"Image", "map", "3D", "Plot", "RawMessages"}
    assert by_type["Image"]["imageMode"]["imageTopic"] == t.PANORAMA
    assert t.PANORAMA_SKYLINE in by_type["Image"]["imageMode"]["annotations"]
    assert by_type["map"]["followTopic"] == t.ESTIMATE_FIX and t.GPS_FIX in by_type["map"]["topicColors"]
    assert by_type["3D"]["followTf"] == m.MAP
    assert by_type["RawMessages"]["topicPath"] == t.PROCEDURE
    plotted = {p["value"].split(".")[0] for p in by_type["Plot"]["paths"]}
    assert plotted == {t.ESTIMATE_RECORD, t.ESTIMATE_FIX}
    assert {"error_m", "radius95_m"} <= set(t.JSON_SCHEMAS["viper.Estimate"]["properties"])
    pyproject = (REPO / "pyproject.toml").read_text()
    assert '"appliance.examples" = ["*.toml", "*.conf", "*.json"]' in pyproject


def test_the_skyline_only_demo_refuses_a_log_encoding_it_would_not_use(tmp_path, capsys):
    code = main(["demo", "--skyline-only", "--log-encoding", "ros2", "--out", str(tmp_path / "demo")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and "--log-encoding ros2" in err[0] and "writes no log" in err[0]
    assert not (tmp_path / "demo").exists()
