"""``viper log recover``: rewrite a truncated, torn or partly corrupt log into a valid, indexed MCAP file.

The broken file is walked record by record (:func:`scan_records`): each record is checked by its
opcode, its length (it must end within the file and be read whole by its own length) and, for a
chunk, its CRC.  Where a record does not check, the walk resynchronises on the next offset where a
valid record starts (followed by another, by the file's trailing magic or by its end, unless it is a
chunk whose CRC holds), so that everything after a corrupt stretch is kept; a stretch that runs to
the end of the file is where it was cut.  Every message read is written again, with its topic,
schema, times and sequence number, into a new file (with the log's metadata records and a data CRC)
that gets a summary and a footer; a message whose channel was lost in a corrupt stretch is taken
with the channel the log's summary declares, if it has one.  The
output is written beside its final name and renamed into place only when complete
(:func:`appliance.atomic.atomic_output`); the reserve file a killed session left beside the broken
log is removed.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import MCAP0_MAGIC, CompressionType
from mcap.writer import Writer as McapWriter

from appliance.atomic import atomic_output, check_output_path
from appliance.errors import LogError
from appliance.logbook.reader import chunk_records
from appliance.logbook.sink import DurableFile
from appliance.logbook.writer import LIBRARY, PROFILE, remove_stale_reserves

#: The record kinds of MCAP, by opcode.
_KINDS: dict[int, Any] = {
    Opcode.HEADER: Header, Opcode.FOOTER: Footer, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel,
    Opcode.MESSAGE: Message, Opcode.CHUNK: Chunk, Opcode.MESSAGE_INDEX: MessageIndex,
    Opcode.CHUNK_INDEX: ChunkIndex, Opcode.ATTACHMENT: Attachment, Opcode.ATTACHMENT_INDEX: AttachmentIndex,
    Opcode.STATISTICS: Statistics, Opcode.METADATA: Metadata, Opcode.METADATA_INDEX: MetadataIndex,
    Opcode.SUMMARY_OFFSET: SummaryOffset, Opcode.DATA_END: DataEnd,
}
# What a corrupt record raises inside mcap's record parsers (CRC errors are ValueErrors).
_CORRUPTION = (McapError, struct.error, ValueError, zstandard.ZstdError, RuntimeError, MemoryError,
               UnicodeDecodeError, EOFError, IndexError, OverflowError, LogError)
_HEAD = 9  # opcode (1 byte) and length (8 bytes, little-endian)


@dataclass
class Scan:
    """What :func:`scan_records` found: the header, every schema and channel, the number of messages,
    the corrupt stretches skipped in the middle (start, end) and where a torn tail starts."""

    header: Header | None = None
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: int = 0
    skipped: list[tuple[int, int]] = field(default_factory=list)
    cut_at: int | None = None
    footer: bool = False
    metadata: list[Metadata] = field(default_factory=list)


@dataclass(frozen=True)
class RecoveryReport:
    messages: int
    topics: dict[str, int]
    source_complete: bool
    problem: str | None
    stopped_at: int | None
    source_bytes: int
    skipped: tuple[tuple[int, int], ...] = ()
    lost_channel: int = 0

    def describe(self) -> str:
        state = "complete" if self.stopped_at is None else f"cut at byte {self.stopped_at} of {self.source_bytes}"
        if self.skipped:
            n = sum(b - a for a, b in self.skipped)
            state += (f"; {n} corrupt bytes skipped in {len(self.skipped)} stretch"
                      f"{'es' if len(self.skipped) != 1 else ''} from byte {self.skipped[0][0]}")
        lost = f", {self.lost_channel} dropped (their channel was lost)" if self.lost_channel else ""
        return f"recovered {self.messages} messages on {len(self.topics)} topics{lost} (source {state})"


def _record_at(data: bytes, pos: int) -> tuple[Any, list[Any], int] | None:
    """The record starting at byte ``pos`` with the records it holds (a chunk's) and where it ends, or
    None where no whole, valid record starts there."""
    if pos + _HEAD > len(data):
        return None
    kind = _KINDS.get(data[pos])
    length = int.from_bytes(data[pos + 1:pos + _HEAD], "little")
    end = pos + _HEAD + length
    if kind is None or end > len(data):
        return None
    body = io.BytesIO(data[pos + _HEAD:end])
    try:
        stream = ReadDataStream(body)
        record = kind.read(stream, length) if kind is Message else kind.read(stream)
        if body.tell() != length:
            return None
        inner = chunk_records(record) if kind is Chunk else [record]
    except _CORRUPTION:
        return None
    return record, inner, end


def _plausible_at(data: bytes, pos: int) -> bool:
    """Whether ``pos`` is the file's end, its trailing magic, or a record header whose length fits."""
    if pos == len(data) or data[pos:pos + len(MCAP0_MAGIC)] == MCAP0_MAGIC:
        return True
    if pos + _HEAD > len(data) or data[pos] not in _KINDS:
        return False
    return pos + _HEAD + int.from_bytes(data[pos + 1:pos + _HEAD], "little") <= len(data)


def _resync(data: bytes, start: int) -> tuple[int, tuple[Any, list[Any], int] | None]:
    """The next offset from ``start`` where a valid record starts (a chunk whose CRC holds, or a
    record followed by a plausible one) or the MCAP magic, with that record; the file's end if none."""
    for pos in range(start, len(data)):
        if data[pos:pos + len(MCAP0_MAGIC)] == MCAP0_MAGIC:
            return pos, None
        if data[pos] not in _KINDS:
            continue
        got = _record_at(data, pos)
        if got is None:
            continue
        record, _, end = got
        if (isinstance(record, Chunk) and record.uncompressed_crc != 0) or _plausible_at(data, end):
            return pos, got
    return len(data), None


def _walk(data: bytes, scan: Scan) -> Iterator[Any]:
    """Every record of ``data`` in file order (a chunk's inner records in its place), recording the
    corrupt stretches skipped in ``scan``."""
    pos = 0
    while pos < len(data):
        if data[pos:pos + len(MCAP0_MAGIC)] == MCAP0_MAGIC:
            pos += len(MCAP0_MAGIC)
            continue
        got = _record_at(data, pos)
        if got is None:
            nxt, got = _resync(data, pos + 1)
            if nxt == len(data):
                scan.cut_at = pos
                return
            scan.skipped.append((pos, nxt))
            pos = nxt
            if got is None:
                continue
        record, inner, pos = got
        if isinstance(record, Footer):
            scan.footer = True
        yield from inner


def scan_records(data: bytes) -> Scan:
    """The header, schemas and channels of an MCAP byte string, however damaged, and what was lost."""
    scan = Scan()
    for rec in _walk(data, scan):
        if isinstance(rec, Header) and scan.header is None:
            scan.header = rec
        elif isinstance(rec, Schema):
            scan.schemas.setdefault(rec.id, rec)
        elif isinstance(rec, Channel):
            scan.channels.setdefault(rec.id, rec)
        elif isinstance(rec, Message):
            scan.messages += 1
        elif isinstance(rec, Metadata):
            scan.metadata.append(rec)
    return scan


def messages(data: bytes) -> Iterator[Message]:
    """The messages of an MCAP byte string in file order, as :func:`scan_records` finds them."""
    return (rec for rec in _walk(data, Scan()) if isinstance(rec, Message))


def recover_log(src: str | Path, dst: str | Path, overwrite: bool = False) -> RecoveryReport:
    src_p, dst_p = Path(src), Path(dst)
    if src_p.resolve() == dst_p.resolve():
        raise LogError(f"{dst_p}: the recovered log must not overwrite its source")
    check_output_path(dst_p, [src_p], overwrite)
    try:
        data = src_p.read_bytes()
    except FileNotFoundError:
        raise LogError(f"{src_p}: log file not found") from None
    except OSError as exc:
        raise LogError(f"{src_p}: cannot read log: {exc.strerror}") from None
    scan = scan_records(data)
    if scan.header is None and not scan.messages:
        why = "no MCAP magic" if not data.startswith(MCAP0_MAGIC) else "no readable record"
        raise LogError(f"{src_p}: not an MCAP log ({why})")
    remove_stale_reserves(src_p.parent)
    with atomic_output(dst_p) as tmp:
        tmp.unlink()  # DurableFile creates its file itself and never opens an existing one
        topics, count = _copy(scan, messages(data), tmp)
    problems = []
    if scan.skipped:
        a, b = scan.skipped[0]
        problems.append(f"corrupt bytes {a} to {b} skipped" + (f" and {len(scan.skipped) - 1} more stretches"
                                                               if len(scan.skipped) > 1 else ""))
    if scan.cut_at is not None or not scan.footer:
        problems.append(f"file ends before its footer (truncated at byte {scan.cut_at or len(data)})")
    return RecoveryReport(
        messages=count,
        topics=topics,
        source_complete=not problems,
        problem="; ".join(problems) or None,
        stopped_at=scan.cut_at if scan.cut_at is not None else (None if scan.footer else len(data)),
        source_bytes=len(data),
        skipped=tuple(scan.skipped),
        lost_channel=scan.messages - count,
    )


def _copy(scan: Scan, found: Iterator[Message], tmp: Path) -> tuple[dict[str, int], int]:
    sink = DurableFile(tmp)
    topics: dict[str, int] = {}
    count = 0
    try:
        writer = McapWriter(sink, compression=CompressionType.ZSTD, enable_data_crcs=True)  # type: ignore[arg-type]
        writer.start(profile=scan.header.profile if scan.header is not None else PROFILE, library=LIBRARY)
        for record in scan.metadata:
            writer.add_metadata(record.name, dict(record.metadata))
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for msg in found:
            channel = scan.channels.get(msg.channel_id)
            if channel is None:
                continue
            if channel.id not in channel_ids:
                schema = scan.schemas.get(channel.schema_id)
                schema_id = 0
                if schema is not None:
                    if schema.id not in schema_ids:
                        schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                    schema_id = schema_ids[schema.id]
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
                )
            writer.add_message(channel_ids[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
            topics[channel.topic] = topics.get(channel.topic, 0) + 1
            count += 1
        writer.finish()
        sink.sync()
    finally:
        sink.close()
    return topics, count
