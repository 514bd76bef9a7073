"""The session writer: one MCAP file, flushed and fsynced often, sealed cleanly on a full disk.

Durability.  The MCAP writer collects messages into a compressed chunk in memory; :meth:`Logbook.flush`
closes that chunk, hands it to the file and fsyncs.  The session calls it after every capture and
the logbook calls it itself when ``fsync_interval_s`` has passed since the last one, so a power
cut loses at most that much: the file then reads (with :class:`appliance.logbook.reader.LogReader`
or ``viper log recover``) up to its last flush.

Full disk.  A write that fails with ENOSPC (or EDQUOT, or EFBIG under a file size limit) cuts the
torn tail off at the last complete record, frees a small reserve file kept beside the log, and closes
the data section with an empty summary (DataEnd with the data section's CRC, Footer, magic): a valid
MCAP file holding everything written before the failure.  Every flush also holds the room for those
closing records (50 bytes, zeros) past the end of the log, so that where the freed reserve gives the
log no room (a per-file limit, a disk filled again by another writer) the log is still closed after
its last flush, overwriting bytes it already has.  The logbook then refuses further writes and raises
:class:`LogbookFullError` (a full disk) or :class:`LogError`.

Encoding.  ``encoding`` chooses the messages: Foxglove's protobuf schemas (the default), or standard
ROS 2 messages in CDR (:mod:`appliance.logbook.ros2`), the JSON records then as ``std_msgs/msg/String``
whose channel metadata ``json_schema`` names their JSON schema.  Either way every message carries its
channel's sequence number (1, 2, ...), the data section its CRC, and :meth:`Logbook.write_metadata`
adds MCAP metadata records (the configuration, calibrations, software version, map).

The reserve file (``.NAME.mcap.reserve``) stays locked (``flock``) while its log is open; a killed
session leaves it unlocked, and :func:`remove_stale_reserves` (called at session start and by
``viper log recover``) removes it.
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import MCAP0_MAGIC, CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set

from appliance.atomic import remove_if_unheld
from appliance.config import Compression, LogEncoding
from appliance.errors import LogError
from appliance.logbook import ros2
from appliance.logbook.live import Publisher
from appliance.logbook.messages import SESSION_FRAMES, pose_in_frame, to_jsonable, with_frame_prefix
from appliance.logbook.sink import DurableFile, Sink
from appliance.logbook.topics import JSON_SCHEMA_KEY, JSON_SCHEMAS

LOG = logging.getLogger(__name__)
PROFILE = "viper"
PROFILES = {LogEncoding.PROTOBUF: PROFILE, LogEncoding.ROS2: "ros2"}
LIBRARY = "viper-appliance logbook"
_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)

def _closing_records(data_section_crc: int) -> bytes:
    """What closes a log's data section with an empty summary: DataEnd, Footer and the magic."""
    builder = RecordBuilder()
    DataEnd(data_section_crc=data_section_crc).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    return bytes(builder.end()) + MCAP0_MAGIC


CLOSING_BYTES = len(_closing_records(0))
COMPRESSIONS = {Compression.ZSTD: CompressionType.ZSTD, Compression.LZ4: CompressionType.LZ4,
                Compression.NONE: CompressionType.NONE}


class LogbookFullError(LogError):
    """The disk filled up; the log was sealed with everything written before."""


class Logbook:
    """Writes one session's MCAP file.  Not thread-safe: one writer per session.

    ``sink`` is the file (normally a :class:`DurableFile`); ``clock`` a monotonic clock in seconds,
    used only for the periodic flush; ``publisher`` (the live view) receives every message written.
    Every message's log_time (and publish_time) is its acquisition time in nanoseconds since the Unix
    epoch.
    """

    def __init__(
        self,
        sink: Sink,
        *,
        name: str = "log",
        fsync_interval_s: float = 2.0,
        chunk_size_bytes: int = 256 * 1024,
        compression: Compression = Compression.ZSTD,
        reserve_path: Path | None = None,
        reserve_bytes: int = 64 * 1024,
        clock: Callable[[], float] = time.monotonic,
        publisher: Publisher | None = None,
        encoding: LogEncoding = LogEncoding.PROTOBUF,
    ) -> None:
        if compression not in COMPRESSIONS:
            known = ", ".join(c.value for c in COMPRESSIONS)
            raise LogError(f"{name}: unknown compression {compression!r} (known: {known})")
        if not fsync_interval_s > 0:
            raise LogError(f"{name}: fsync_interval_s must be positive, got {fsync_interval_s}")
        self.name = name
        self._sink = sink
        self._clock = clock
        self._interval_s = fsync_interval_s
        self._reserve_path = reserve_path
        self._reserve_fd: int | None = None
        self._state = "open"
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._sequences: dict[int, int] = {}
        self.encoding = LogEncoding(encoding)
        self._ros2 = ros2.Ros2Encoder() if self.encoding is LogEncoding.ROS2 else None
        #: prefixed to the session frames of every message (a traverse's stop: ``stop-2/``)
        self.frame_prefix = ""
        self._publisher = publisher
        self._schema_data: dict[str, tuple[str, bytes]] = {}
        self._published: dict[str, tuple[str, str, bytes, str]] = {}
        self.messages_written = 0
        self.messages_durable = 0
        self.flushes = 0
        self.seal_problem: str | None = None
        #: where the log can be closed in place: the offset after the last flush (its closing records'
        #: room held), the data section's CRC there and the messages before it
        self._sealable: tuple[int, int, int] | None = None
        #: the offset after the last chunk written whole, and the messages before it
        self._written_through = (0, 0)
        if reserve_path is not None:
            self._make_reserve(reserve_path, reserve_bytes)
        self._writer = McapWriter(
            sink,  # type: ignore[arg-type]
            chunk_size=chunk_size_bytes,
            compression=COMPRESSIONS[compression],
            enable_data_crcs=True,
        )
        self._guarded(lambda: self._writer.start(profile=PROFILES[self.encoding], library=LIBRARY))
        self._last_flush = self._clock()

    @classmethod
    def create(
        cls,
        path: str | Path,
        *,
        fsync_interval_s: float = 2.0,
        chunk_size_bytes: int = 256 * 1024,
        compression: Compression = Compression.ZSTD,
        reserve_bytes: int = 64 * 1024,
        clock: Callable[[], float] = time.monotonic,
        publisher: Publisher | None = None,
        encoding: LogEncoding = LogEncoding.PROTOBUF,
    ) -> Logbook:
        """A new log at ``path`` (its directory is created; an existing file is never overwritten)."""
        p = Path(path)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise LogError(f"{p.parent}: cannot create log directory: {exc.strerror}") from None
        remove_stale_reserves(p.parent)
        sink = DurableFile(p)
        reserve = reserve_path_of(p) if reserve_bytes > 0 else None
        try:
            return cls(
                sink,
                name=str(p),
                fsync_interval_s=fsync_interval_s,
                chunk_size_bytes=chunk_size_bytes,
                compression=compression,
                reserve_path=reserve,
                reserve_bytes=reserve_bytes,
                clock=clock,
                publisher=publisher,
                encoding=encoding,
            )
        except LogError:
            sink.close()
            raise

    # ----------------------------------------------------------------------------------- state
    @property
    def is_open(self) -> bool:
        return self._state == "open"

    @property
    def disk_full(self) -> bool:
        return self._state == "full"

    def _require_open(self) -> None:
        if self._state == "full":
            raise LogbookFullError(f"{self.name}: disk full; the log was sealed and takes no more messages")
        if self._state != "open":
            raise LogError(f"{self.name}: log is closed")

    # ----------------------------------------------------------------------------------- writes
    def write_proto(self, topic: str, message: Any, log_time_ns: int) -> None:
        """Write a Foxglove protobuf message on ``topic`` (as its ROS 2 message in a ROS 2 log)."""
        self._require_open()
        message = with_frame_prefix(message, self.frame_prefix)
        if self._ros2 is not None:
            ros_type, fields = ros2.to_ros2(message)
            self._write_ros2(topic, ros_type, ros_type, fields, log_time_ns)
            return
        type_name = type(message).DESCRIPTOR.full_name
        channel_id = self._channel(
            topic, type_name, MessageEncoding.Protobuf, lambda: self._proto_schema(message)
        )
        data = message.SerializeToString()
        self._add(channel_id, log_time_ns, data)
        self._publish(topic, data, log_time_ns)

    def write_json(self, topic: str, schema_name: str, payload: Any, log_time_ns: int) -> None:
        """Write a JSON message; ``schema_name`` must be one of :data:`topics.JSON_SCHEMAS` (in a ROS 2 log,
        a ``std_msgs/msg/String`` holding the JSON text)."""
        self._require_open()
        if schema_name not in JSON_SCHEMAS:
            raise LogError(f"{self.name}: unknown JSON schema {schema_name!r} for topic {topic}")
        text = json.dumps(to_jsonable(payload), allow_nan=False, separators=(",", ":"))
        if self._ros2 is not None:
            self._write_ros2(topic, schema_name, ros2.STRING, {"data": text}, log_time_ns,
                             {JSON_SCHEMA_KEY: schema_name})
            return
        channel_id = self._channel(
            topic, schema_name, MessageEncoding.JSON, lambda: self._json_schema(schema_name)
        )
        data = text.encode()
        self._add(channel_id, log_time_ns, data)
        self._publish(topic, data, log_time_ns)

    def write_pose(self, topic: str, time_ns: int, frame_id: str, position_m: Any,
                   covariance_m2: Any = None) -> None:
        """A position (x, y, z in metres) in ``frame_id``: a ``geometry_msgs/msg/PoseWithCovarianceStamped``
        with ``covariance_m2`` (3 x 3) in a ROS 2 log, a foxglove.PoseInFrame (no covariance) otherwise."""
        frame = self.frame_prefix + frame_id if frame_id in SESSION_FRAMES else frame_id
        if self._ros2 is None:
            self.write_proto(topic, pose_in_frame(time_ns, frame, position_m), time_ns)
            return
        self._require_open()
        fields = ros2.pose_with_covariance(time_ns, frame, position_m, covariance_m2)
        self._write_ros2(topic, ros2.POSE, ros2.POSE, fields, time_ns)

    def write_metadata(self, name: str, data: dict[str, str]) -> None:
        """An MCAP metadata record ``name`` (string keys and values)."""
        self._require_open()
        self._guarded(lambda: self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()}))

    def _write_ros2(self, topic: str, channel_schema: str, ros_type: str, fields: dict[str, Any], log_time_ns: int,
                    metadata: dict[str, str] | None = None) -> None:
        assert self._ros2 is not None
        encoder = self._ros2
        channel_id = self._channel(topic, channel_schema, ros2.MESSAGE_ENCODING,
                                   lambda: (ros2.SCHEMA_ENCODING, encoder.schema(ros_type)), ros_type, metadata)
        data = encoder.encode(ros_type, fields)
        self._add(channel_id, log_time_ns, data)
        self._publish(topic, data, log_time_ns)

    def flush(self) -> None:
        """Close the chunk in progress, write it and fsync: everything written so far is durable."""
        self._require_open()
        self._flush()
        self.flushes += 1
        self._last_flush = self._clock()

    def _flush(self) -> None:
        self._guarded(self._writer.flush)
        self._written_through = (self._sink.committed, self.messages_written)
        self._guarded(lambda: self._sink.hold(CLOSING_BYTES))
        self._guarded(self._sink.sync)
        self.messages_durable = self.messages_written
        self._sealable = (self._sink.committed, self._sink.crc, self.messages_durable)

    def maybe_flush(self) -> None:
        """Flush if ``fsync_interval_s`` has passed since the last flush."""
        if self._state == "open" and self._clock() - self._last_flush >= self._interval_s:
            self.flush()

    def close(self) -> None:
        """Write the summary and footer, fsync and close.  A sealed (full) log just closes."""
        if self._state == "closed":
            return
        if self._state == "full":
            self._state = "closed"
            return
        self._flush()
        self._guarded(self._writer.finish, at_last_flush=True)
        # the summary may be shorter than the room held for the closing records: cut the file at its end
        self._guarded(lambda: self._sink.end_at(self._sink.committed, b""), at_last_flush=True)
        self._guarded(self._sink.sync, at_last_flush=True)
        self._sink.close()
        self._drop_reserve()
        self._state = "closed"

    def __enter__(self) -> Logbook:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------------------------- internals
    def _channel(
        self, topic: str, schema_name: str, encoding: str, schema: Callable[[], tuple[str, bytes]],
        record_name: str | None = None, metadata: dict[str, str] | None = None,
    ) -> int:
        """The channel of ``topic`` (made the first time); ``schema_name`` is what the topic carries (the
        JSON schema of a ROS 2 String channel), ``record_name`` the schema record's name if another."""
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != schema_name:
                raise LogError(f"{self.name}: topic {topic} carries {known[1]}, cannot write a {schema_name}")
            return known[0]
        stored = record_name or schema_name
        schema_id = self._schemas.get(stored)
        if schema_id is None:
            schema_encoding, data = schema()
            self._schema_data[stored] = (schema_encoding, data)
            schema_id = self._guarded(
                lambda: self._writer.register_schema(stored, schema_encoding, data)
            )
            self._schemas[stored] = schema_id
        self._published[topic] = (stored, *self._schema_data[stored], encoding)
        channel_id = self._guarded(
            lambda: self._writer.register_channel(topic, encoding, schema_id, metadata or {}))
        self._channels[topic] = (channel_id, schema_name)
        return channel_id

    def _publish(self, topic: str, data: bytes, log_time_ns: int) -> None:
        """Hand a written message to the live view; a failing live view never stops the log."""
        if self._publisher is None:
            return
        schema_name, schema_encoding, schema_data, message_encoding = self._published[topic]
        try:
            self._publisher.publish(topic, schema_name, schema_encoding, schema_data, message_encoding, data,
                                    int(log_time_ns))
        except Exception as exc:  # the live view is optional: log once and carry on without it
            LOG.warning("%s: live view dropped after an error on %s: %s", self.name, topic, exc)
            self._publisher = None

    @staticmethod
    def _proto_schema(message: Any) -> tuple[str, bytes]:
        return SchemaEncoding.Protobuf, build_file_descriptor_set(type(message)).SerializeToString()

    @staticmethod
    def _json_schema(schema_name: str) -> tuple[str, bytes]:
        return SchemaEncoding.JSONSchema, json.dumps(JSON_SCHEMAS[schema_name]).encode()

    def _add(self, channel_id: int, log_time_ns: int, data: bytes) -> None:
        t = int(log_time_ns)
        if t < 0:
            raise LogError(f"{self.name}: negative log_time {t} ns")
        sequence = self._sequences.get(channel_id, 0) + 1
        self._guarded(lambda: self._writer.add_message(channel_id, t, data, t, sequence))
        self._sequences[channel_id] = sequence
        self.messages_written += 1
        self.maybe_flush()

    def _guarded(self, action: Callable[[], Any], at_last_flush: bool = False) -> Any:
        try:
            return action()
        except OSError as exc:
            full = exc.errno in _FULL_ERRNOS
            sealed = self._seal(at_last_flush)
            self._state = "full" if full else "closed"
            what = "disk full" if full else f"write failed ({exc.strerror or exc})"
            if sealed:
                kept = f"sealed with {self.messages_durable} durable messages"
            elif self._sealable is None:
                kept = "closed before its first flush"
            else:
                kept = "left readable up to its last flush (run 'viper log recover')"
            cls = LogbookFullError if full else LogError
            raise cls(f"{self.name}: {what}; log {kept}") from None

    def _seal(self, at_last_flush: bool) -> bool:
        """Cut the torn tail and close the data section with an empty summary; True if it worked.

        First after the last complete write (unless ``at_last_flush``), which needs up to 50 bytes
        of new room (the freed reserve's, on a full disk); failing that, after the last flush, within
        the room that flush held."""
        self._drop_reserve()
        committed = self._sink.committed
        messages = self._written_through[1] if committed == self._written_through[0] else self.messages_durable
        places = [] if at_last_flush else [(committed, self._sink.crc, messages)]
        if self._sealable is not None and self._sealable not in places:
            places.append(self._sealable)
        try:
            for offset, crc, messages in places:
                if offset == 0:
                    continue
                try:
                    self._sink.end_at(offset, _closing_records(crc))
                    self._sink.sync()
                except OSError as exc:
                    self.seal_problem = str(exc)
                    continue
                self.messages_durable = messages
                self.seal_problem = None
                return True
            return False
        finally:
            try:
                self._sink.close()
            except OSError:
                pass

    def _make_reserve(self, path: Path, size: int) -> None:
        fd = None
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            view = memoryview(b"\0" * size)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
        except OSError as exc:
            if fd is not None:
                os.close(fd)
                path.unlink(missing_ok=True)
            raise LogbookFullError(
                f"{path}: cannot reserve {size} bytes beside the log: {exc.strerror}"
            ) from None
        self._reserve_fd = fd

    def _drop_reserve(self) -> None:
        if self._reserve_path is not None:
            try:
                self._reserve_path.unlink()
            except FileNotFoundError:
                pass
            self._reserve_path = None
        if self._reserve_fd is not None:
            fd, self._reserve_fd = self._reserve_fd, None
            os.close(fd)


def reserve_path_of(log_path: str | Path) -> Path:
    """The reserve file kept beside the log ``log_path`` while it is written."""
    p = Path(log_path)
    return p.with_name(f".{p.name}.reserve")


def remove_stale_reserves(folder: str | Path) -> list[Path]:
    """Remove the reserve files in ``folder`` whose log is no longer written (a killed session).

    A reserve is stale when no process holds its lock; a live session's reserve is left alone.
    """
    try:
        candidates = sorted(Path(folder).glob(".*.reserve"))
    except OSError:
        return []
    return [q for q in candidates if remove_if_unheld(q, q.unlink)]
