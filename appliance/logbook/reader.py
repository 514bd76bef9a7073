"""Reading a log, complete or cut short by a power cut, a kill or a full disk.

:class:`LogReader` reads the file sequentially, record by record from the file (it never needs the
summary, and never holds more than a chunk in memory), so a log that was truncated anywhere yields
every message of every complete chunk before the cut.  Zeros where a record should start (the room a
flush holds past the log's end, a sparse file) end the log there.  What happens at
the first unreadable byte depends on the :class:`~appliance.errors.ErrorPolicy`: ``RAISE`` raises
:class:`LogError` naming the offset; ``SKIP`` ends the iteration there and records the problem in
``reader.problem`` (``reader.complete`` is False); ``LOG`` does the same and logs a warning.

A damaged or hostile file cannot make the reader allocate more than it holds: a record is at most
:data:`MAX_RECORD_BYTES` long and never longer than the file (mcap's own ``record_size_limit``), a
length inside a record longer than the whole file is refused before anything is read for it, one that
runs past the file's end ends the log there, and a chunk is decompressed
(:func:`chunk_records`) into at most the size it declares, itself at most :data:`MAX_CHUNK_BYTES`.
"""

from __future__ import annotations

import dataclasses
import io
import json
import logging
import os
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, cast

import lz4.frame
import zstandard
from google.protobuf.message import DecodeError
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.well_known import MessageEncoding
from mcap_protobuf.decoder import DecoderFactory

from appliance.errors import ErrorPolicy, LogError
from appliance.extras import require
from appliance.inputs import check_nesting, open_regular
from appliance.logbook.topics import JSON_SCHEMA_KEY

log = logging.getLogger(__name__)

# What a corrupt or truncated byte stream raises inside mcap's reader (CRC errors are ValueErrors).
_CORRUPTION = (McapError, struct.error, ValueError, zstandard.ZstdError, RuntimeError, MemoryError, LogError,
               OverflowError)
#: The longest record a log may hold (a chunk, an attachment): a session's chunks are 256 KiB, a
#: camera frame a few MiB.
MAX_RECORD_BYTES = 256 << 20
#: The largest size a chunk may declare for its records, uncompressed.
MAX_CHUNK_BYTES = 256 << 20


def chunk_records(chunk: Chunk) -> list[Any]:
    """The records a chunk holds, its CRC checked; :class:`LogError` where it declares more than
    :data:`MAX_CHUNK_BYTES` uncompressed, decompresses to another size (never past the declared one),
    or holds a record that runs past its end."""
    size = chunk.uncompressed_size
    if size > MAX_CHUNK_BYTES:
        raise LogError(f"a chunk declaring {size} bytes uncompressed, more than the {MAX_CHUNK_BYTES >> 20} MiB "
                       "a chunk may hold")
    if chunk.compression == "zstd":
        with zstandard.ZstdDecompressor().stream_reader(chunk.data) as stream:
            data = _read_up_to(stream.read, size + 1)
    elif chunk.compression == "lz4":
        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise LogError(f"a chunk compressed with unknown {chunk.compression[:40]!r}")
    if len(data) != size:
        got = f"more than {size}" if len(data) > size else str(len(data))
        raise LogError(f"a chunk declaring {size} bytes uncompressed holds {got}")
    try:
        return breakup_chunk(dataclasses.replace(chunk, compression="", data=data), validate_crc=True)
    except EndOfFile:
        raise LogError("a record runs past the end of its chunk") from None


def _read_up_to(read: Callable[[int], bytes], limit: int) -> bytes:
    parts: list[bytes] = []
    total = 0
    while total < limit:
        part = read(limit - total)
        if not part:
            break
        parts.append(part)
        total += len(part)
    return b"".join(parts)


@dataclass(frozen=True)
class LogMessage:
    """One message as stored: topic, schema, encoding, acquisition time (ns) and raw bytes."""

    topic: str
    schema_name: str
    message_encoding: str
    log_time_ns: int
    data: bytes
    schema: Schema | None
    sequence: int = 0
    channel_id: int = 0
    #: the JSON schema a ROS 2 log's ``std_msgs/msg/String`` channel carries (its channel metadata)
    json_schema: str = ""

    def decode(self) -> Any:
        """The protobuf object (``foxglove.*``), the ROS 2 message (attributes named as its fields) or
        the parsed JSON value (of a JSON channel, or of a ROS 2 String channel holding JSON)."""
        if self.message_encoding == MessageEncoding.JSON:
            return self._json(self.data)
        if self.message_encoding == MessageEncoding.CDR and self.schema is not None:
            decoded = _ros2_decoder(self.schema)(self.data)
            return self._json(decoded.data.encode()) if self.json_schema else decoded
        if self.message_encoding == MessageEncoding.Protobuf and self.schema is not None:
            decoder = _proto_decoder(self.schema)
            try:
                return decoder(self.data)
            except DecodeError as exc:
                raise LogError(f"{self.topic} at {self.log_time_ns} ns: invalid {self.schema.name} message: "
                               f"{exc}") from None
        raise LogError(f"{self.topic}: cannot decode messages of encoding {self.message_encoding!r}")

    def _json(self, data: bytes) -> Any:
        try:
            check_nesting(data)
            return json.loads(data)
        except (ValueError, UnicodeDecodeError) as exc:
            raise LogError(f"{self.topic} at {self.log_time_ns} ns: invalid JSON message: {exc}") from None


_DECODERS: dict[tuple[str, bytes], Callable[[bytes], Any]] = {}


def _proto_decoder(schema: Schema) -> Callable[[bytes], Any]:
    key = (schema.name, schema.data)
    dec = _DECODERS.get(key)
    if dec is None:
        try:
            made = DecoderFactory().decoder_for(MessageEncoding.Protobuf, schema)
        except McapError as exc:
            raise LogError(f"schema {schema.name}: cannot build a protobuf decoder: {exc}") from None
        if made is None:
            raise LogError(f"schema {schema.name}: not a protobuf schema")
        dec = _DECODERS[key] = made
    return dec


def _ros2_decoder(schema: Schema) -> Callable[[bytes], Any]:
    key = (schema.name, schema.data)
    dec = _DECODERS.get(key)
    if dec is None:
        # mcap-ros2-support is optional (the rover extra): loaded only for a ROS 2 log
        factory = require("mcap_ros2.decoder", "reading a ROS 2-encoded log").DecoderFactory()
        try:
            made = factory.decoder_for(MessageEncoding.CDR, schema)
        except (McapError, ValueError) as exc:
            raise LogError(f"schema {schema.name}: cannot build a ROS 2 decoder: {exc}") from None
        if made is None:
            raise LogError(f"schema {schema.name}: not a ROS 2 schema")
        wrapped = _decode_errors(schema.name, made)
        dec = _DECODERS[key] = wrapped
    return dec


def _decode_errors(name: str, decoder: Callable[[bytes], Any]) -> Callable[[bytes], Any]:
    """``decoder`` raising :class:`LogError` for a message that does not decode."""

    def decode(data: bytes) -> Any:
        try:
            return decoder(data)
        except (ValueError, IndexError, struct.error, UnicodeDecodeError, EOFError) as exc:
            raise LogError(f"invalid {name} message: {exc}") from None

    return decode


class _FileStream:
    """The log file as the MCAP reader reads it: no read asks for more than is left of the file's
    ``size`` bytes (a file cut short then ends as such), and a length longer than the whole file, forged
    inside a record (an attachment's data, a string, a chunk's records), is a :class:`LogError`: nothing
    is allocated for it."""

    def __init__(self, fh: io.BufferedReader, size: int) -> None:
        self._fh, self._size = fh, size

    def read(self, n: int = -1) -> bytes:
        if n is not None and n > self._size:
            raise LogError(f"a length of {n} bytes, more than the file's {self._size}")
        left = max(self._size - self._fh.tell(), 0)
        return self._fh.read(left if n is None or n < 0 else min(n, left))

    def tell(self) -> int:
        return self._fh.tell()

    def peek(self, n: int) -> bytes:
        return self._fh.peek(n)[:n]


class LogReader:
    """Sequential reader of one MCAP log.  Iterate :meth:`messages` once; then read the outcome.

    After iteration: ``complete`` (the footer was reached), ``problem`` (why reading stopped early,
    or None), ``stopped_at`` (byte offset of the first unreadable record), ``header``,
    ``size_bytes``, ``metadata`` (the MCAP metadata records read: name -> key/value pairs; a name
    written twice keeps its last record).
    """

    def __init__(self, path: str | Path, policy: ErrorPolicy = ErrorPolicy.SKIP) -> None:
        self.path = Path(path)
        self.policy = policy
        self.complete = False
        self.problem: str | None = None
        self.stopped_at: int | None = None
        self.header: Header | None = None
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        with self._open() as fh:
            self.size_bytes = os.fstat(fh.fileno()).st_size

    def _open(self) -> io.BufferedReader:
        """The log opened for reading (a regular file), or :class:`LogError` in one line."""
        try:
            return open_regular(self.path, "log", LogError)
        except FileNotFoundError:
            raise LogError(f"{self.path}: log file not found") from None
        except LogError:
            raise
        except OSError as exc:
            raise LogError(f"{self.path}: cannot read log: {exc.strerror}") from None

    def messages(self) -> Iterator[LogMessage]:
        """The log's messages in file order, read record by record from the file (a chunk at a time
        in memory, never the whole log)."""
        with self._open() as fh:
            yield from self._messages(_FileStream(fh, self.size_bytes))

    def _messages(self, stream: _FileStream) -> Iterator[LogMessage]:
        reader = StreamReader(cast(IO[bytes], stream), emit_chunks=True, validate_crcs=True,
                              record_size_limit=min(self.size_bytes, MAX_RECORD_BYTES))
        records = reader.records
        offset = 0
        while True:
            try:
                offset = stream.tell()
                if stream.peek(1)[:1] == b"\x00":
                    # no record starts with opcode 0: zeros past the last write (a flush's held room, a
                    # sparse file), read as the log's end rather than walked nine bytes at a time
                    self._stop(offset, f"zeros where a record should start at byte {offset} (truncated)")
                    return
                record = next(records)
                inner = chunk_records(record) if isinstance(record, Chunk) else [record]
            except StopIteration:
                break
            except EndOfFile:
                self._stop(offset, "file ends before its footer (truncated)")
                return
            except _CORRUPTION as exc:
                why = "a length no file can hold" if isinstance(exc, OverflowError) else str(exc) or type(exc).__name__
                self._stop(offset, f"unreadable record at byte {offset}: {why}")
                return
            for rec in inner:
                msg = self._take(rec)
                if msg is not None:
                    yield msg
            if isinstance(record, Footer):
                self.complete = True
        if not self.complete:
            self._stop(offset, "file ends before its footer (truncated)")

    def _take(self, rec: Any) -> LogMessage | None:
        if isinstance(rec, Header):
            self.header = rec
        elif isinstance(rec, Schema):
            self.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            self.channels[rec.id] = rec
        elif isinstance(rec, Metadata):
            self.metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Message):
            channel = self.channels.get(rec.channel_id)
            if channel is None:
                problem = f"message on unknown channel {rec.channel_id} at {rec.log_time} ns"
                if self.policy is ErrorPolicy.RAISE:
                    raise LogError(f"{self.path}: {problem}")
                if self.policy is ErrorPolicy.LOG:
                    log.warning("%s: %s", self.path, problem)
                return None
            schema = self.schemas.get(channel.schema_id)
            return LogMessage(
                topic=channel.topic,
                schema_name=schema.name if schema is not None else "",
                message_encoding=channel.message_encoding,
                log_time_ns=rec.log_time,
                data=bytes(rec.data),
                schema=schema,
                sequence=rec.sequence,
                channel_id=rec.channel_id,
                json_schema=channel.metadata.get(JSON_SCHEMA_KEY, ""),
            )
        elif isinstance(rec, DataEnd):
            pass
        return None

    def _stop(self, offset: int, problem: str) -> None:
        self.complete = False
        self.stopped_at = offset
        self.problem = problem
        if self.policy is ErrorPolicy.RAISE:
            raise LogError(f"{self.path}: {problem}")
        if self.policy is ErrorPolicy.LOG:
            log.warning("%s: %s", self.path, problem)


def read_messages(
    path: str | Path, policy: ErrorPolicy = ErrorPolicy.SKIP
) -> tuple[list[LogMessage], LogReader]:
    """All messages of a log in file order, and the reader (for ``complete``/``problem``)."""
    reader = LogReader(path, policy)
    return list(reader.messages()), reader
