"""The logbook writes MCAP that mcap's own readers open, with Foxglove schemas that decode back."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from appliance.bodies import MARS, MOON, geodesic_distance_m
from appliance.errors import LogError
from appliance.logbook import Logbook, LogReader
from appliance.logbook import messages as m
from appliance.logbook import topics as t
from appliance.logbook.summary import summarize_log
from appliance.vision.intrinsics import CameraIntrinsics

T0 = 1_700_000_000_123_456_789


def write_session(path, n=5):
    intr = CameraIntrinsics.from_fov(640, 480, 60.0)
    post = np.arange(12, dtype=np.float32).reshape(3, 4) / 66.0
    with Logbook.create(path) as lb:
        lb.write_proto(t.CALIBRATION, m.camera_calibration(T0, intr), T0)
        lb.write_proto(
            t.REGION, m.geojson([m.polygon_feature([(-98, 33), (-97, 33), (-97, 34)], "region")]), T0
        )
        for i in range(n):
            ns = T0 + i * 1_000_000
            lb.write_proto(t.IMAGE, m.compressed_image(ns, bytes([i]) * 100), ns)
            lb.write_proto(t.GPS_FIX, m.location_fix(ns, 33.5 + i * 1e-6, -97.5, 250.0, 2.5), ns)
            lb.write_proto(t.TF, m.attitude_transform(ns, 90.0, 1.0, -2.0), ns)
            lb.write_proto(t.TF, m.stage_transform(ns, 30.0 * i), ns)
            lb.write_json(t.TILT_RAW, "viper.TiltRaw", {"roll_deg": 0.25 * i, "pitch_deg": math.nan}, ns)
            lb.flush()
        lb.write_proto(t.LOG, m.log_message(T0, "warning", "compass: residual high"), T0)
        lb.write_proto(t.POSTERIOR, m.grid(T0, post, (30.0, 30.0), (1000.0, 2000.0)), T0)
        lb.write_proto(t.GPS_TRUTH, m.location_fix(T0, 33.5, -97.5, sigma_m=1.0), T0)
        lb.write_proto(
            t.ESTIMATE_FIX, m.location_fix(T0, 33.501, -97.5, sigma_m=50.0, frame_id="estimate"), T0
        )
        lb.write_json(t.ESTIMATE_RECORD, "viper.Estimate", {"lat": 33.501, "lon": -97.5, "sigma_m": 50.0}, T0)
    return post


def test_mcap_reader_decodes_foxglove_messages(tmp_path):
    path = tmp_path / "s.mcap"
    post = write_session(path)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        names = {s.name for s in summary.schemas.values()}
        assert {
            "foxglove.CompressedImage",
            "foxglove.LocationFix",
            "foxglove.FrameTransform",
            "foxglove.Log",
            "foxglove.Grid",
            "foxglove.GeoJSON",
            "foxglove.CameraCalibration",
        } <= names
        decoded = {}
        for _schema, channel, message, proto in reader.iter_decoded_messages(
            topics=[t.GPS_FIX, t.POSTERIOR, t.IMAGE, t.CALIBRATION, t.TF]
        ):
            decoded.setdefault(channel.topic, []).append((message.log_time, proto))
    fixes = decoded[t.GPS_FIX]
    assert [lt for lt, _ in fixes] == [T0 + i * 1_000_000 for i in range(5)]
    assert fixes[3][1].latitude == pytest.approx(33.5 + 3e-6, abs=1e-12)
    assert fixes[3][1].position_covariance[0] == pytest.approx(6.25)
    assert fixes[0][1].timestamp.ToNanoseconds() == T0
    assert [p.data for _, p in decoded[t.IMAGE]] == [bytes([i]) * 100 for i in range(5)]
    np.testing.assert_array_equal(m.grid_values(decoded[t.POSTERIOR][0][1]), post)
    cal = decoded[t.CALIBRATION][0][1]
    assert (cal.width, cal.height, cal.K[2]) == (640, 480, pytest.approx(319.5))
    assert len(decoded[t.TF]) == 10


def test_json_messages_carry_their_schema_and_null_for_nan(tmp_path):
    path = tmp_path / "s.mcap"
    write_session(path)
    reader = LogReader(path)
    tilts = [msg for msg in reader.messages() if msg.topic == t.TILT_RAW]
    assert reader.complete and reader.problem is None
    assert [msg.decode() for msg in tilts][2] == {"roll_deg": 0.5, "pitch_deg": None}
    assert tilts[0].schema is not None and tilts[0].schema.encoding == "jsonschema"
    assert json.loads(tilts[0].schema.data)["title"].startswith("Raw inclinometer")


def test_quaternion_of_attitude_matches_rotation():
    # heading 90 deg (east) is a rotation of -90 deg about up in ENU: x=east maps to -y (south)
    x, y, z, w = m.quaternion_from_euler_deg(-90.0, 0.0, 0.0)
    assert (x, y) == (0.0, 0.0) and z == pytest.approx(-math.sqrt(0.5)) and w == pytest.approx(math.sqrt(0.5))
    # combined rotation stays a unit quaternion
    q = np.array(m.quaternion_from_euler_deg(33.0, -4.0, 7.0))
    assert np.linalg.norm(q) == pytest.approx(1.0)


def test_summary_counts_span_and_error(tmp_path):
    path = tmp_path / "s.mcap"
    write_session(path)
    s = summarize_log(path)
    assert s.complete
    assert s.topics[t.GPS_FIX].count == 5 and s.topics[t.TF].count == 10
    assert s.span_ns == (T0, T0 + 4_000_000)
    # 0.001 deg of latitude along the WGS84 meridian: M = a (1 - e^2) / (1 - e^2 sin^2 phi)^1.5 per radian
    a, f = 6_378_137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    phi = math.radians(33.5005)
    meridian_m = a * (1 - e2) / (1 - e2 * math.sin(phi) ** 2) ** 1.5
    assert s.error_m == pytest.approx(meridian_m * math.radians(0.001), abs=1e-3)


def test_geodesic_distance_against_closed_forms():
    # one degree along the equator is a * pi / 180 on the ellipsoid, R * pi / 180 on a sphere
    assert geodesic_distance_m(0, 0, 0, 1) == pytest.approx(6_378_137.0 * math.pi / 180, abs=1e-6)
    assert geodesic_distance_m(0, 0, 0, 1, MOON) == pytest.approx(MOON.radius_m * math.pi / 180, abs=1e-6)
    assert geodesic_distance_m(10, 20, 10, 20, MARS) == 0.0
    # symmetric, and a quarter meridian of the Moon's sphere is R * pi / 2
    assert geodesic_distance_m(0, 0, 90, 0, MOON) == pytest.approx(MOON.radius_m * math.pi / 2, rel=1e-12)
    assert geodesic_distance_m(1, 2, 3, 4) == pytest.approx(geodesic_distance_m(3, 4, 1, 2), rel=1e-12)


def test_topic_cannot_change_schema_and_existing_log_is_never_overwritten(tmp_path):
    path = tmp_path / "s.mcap"
    with Logbook.create(path) as lb:
        lb.write_proto(t.GPS_FIX, m.location_fix(T0, 1.0, 2.0), T0)
        with pytest.raises(LogError, match="carries foxglove.LocationFix"):
            lb.write_proto(t.GPS_FIX, m.log_message(T0, "info", "x"), T0)
    with pytest.raises(LogError, match="already exists"):
        Logbook.create(path)
    assert summarize_log(path).topics[t.GPS_FIX].count == 1


def test_periodic_flush_makes_messages_durable_without_explicit_flush(tmp_path):
    now = [0.0]
    path = tmp_path / "s.mcap"
    lb = Logbook.create(path, fsync_interval_s=2.0, clock=lambda: now[0])
    lb.write_proto(t.GPS_FIX, m.location_fix(T0, 1.0, 2.0), T0)
    assert lb.messages_durable == 0
    now[0] = 2.5
    lb.write_proto(t.GPS_FIX, m.location_fix(T0 + 1, 1.0, 2.0), T0 + 1)
    assert lb.messages_durable == 2
    # what a power cut now leaves on disk reads back both messages
    reader = LogReader(path)
    assert [msg.log_time_ns for msg in reader.messages()] == [T0, T0 + 1]
    assert not reader.complete
    lb.close()


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_every_compression_reads_back_through_the_bounded_chunk_reader(tmp_path, compression):
    from appliance.config import Compression

    path = tmp_path / f"{compression}.mcap"
    images = [bytes(range(i, i + 200)) * (i + 1) for i in range(6)]
    with Logbook.create(path, compression=Compression(compression), chunk_size_bytes=512) as lb:
        for i, data in enumerate(images):
            lb.write_proto(t.IMAGE, m.compressed_image(T0 + i, data), T0 + i)
            lb.write_json(t.TILT_RAW, "viper.TiltRaw", {"roll_deg": 0.5 * i}, T0 + i)
            if i % 2:
                lb.flush()
    reader = LogReader(path)
    got = [(msg.topic, msg.log_time_ns, msg.data) for msg in reader.messages()]
    assert reader.complete and reader.problem is None
    with open(path, "rb") as f:  # mcap's own reader, which decompresses without our bounds
        chunks = {c.compression for c in make_reader(f).get_summary().chunk_indexes}
        f.seek(0)
        theirs = [(ch.topic, msg.log_time, msg.data) for _, ch, msg in make_reader(f).iter_messages(
            log_time_order=False)]
    assert chunks == {"" if compression == "none" else compression}
    assert got == theirs and len(got) == 12
    assert [msg.decode().data for msg in LogReader(path).messages() if msg.topic == t.IMAGE] == images
