"""``viper log recover``: rewrite a truncated or torn log into a valid, indexed MCAP file.

The broken file is read sequentially up to its first unreadable byte (see
:class:`appliance.logbook.reader.LogReader`); every schema, channel and message read is written
again, with the same ids, topics and times, into a new file that gets a summary and a footer.  The
output is written beside its final name and renamed into place only when complete
(:func:`appliance.atomic.atomic_output`); the reserve file a killed session left beside the
broken log is removed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from appliance.atomic import atomic_output, check_output_path
from appliance.errors import ErrorPolicy, LogError
from appliance.logbook.reader import LogReader
from appliance.logbook.sink import DurableFile
from appliance.logbook.writer import LIBRARY, PROFILE, remove_stale_reserves


@dataclass(frozen=True)
class RecoveryReport:
    messages: int
    topics: dict[str, int]
    source_complete: bool
    problem: str | None
    stopped_at: int | None
    source_bytes: int

    def describe(self) -> str:
        state = (
            "complete" if self.source_complete else f"cut at byte {self.stopped_at} of {self.source_bytes}"
        )
        return f"recovered {self.messages} messages on {len(self.topics)} topics (source {state})"


def recover_log(src: str | Path, dst: str | Path, overwrite: bool = False) -> RecoveryReport:
    src_p, dst_p = Path(src), Path(dst)
    if src_p.resolve() == dst_p.resolve():
        raise LogError(f"{dst_p}: the recovered log must not overwrite its source")
    check_output_path(dst_p, [src_p], overwrite)
    reader = LogReader(src_p, ErrorPolicy.SKIP)
    remove_stale_reserves(src_p.parent)
    with atomic_output(dst_p) as tmp:
        tmp.unlink()  # DurableFile creates its file itself and never opens an existing one
        topics, count = _copy(reader, src_p, tmp)
    return RecoveryReport(
        messages=count,
        topics=topics,
        source_complete=reader.complete,
        problem=reader.problem,
        stopped_at=reader.stopped_at,
        source_bytes=reader.size_bytes,
    )


def _copy(reader: LogReader, src_p: Path, tmp: Path) -> tuple[dict[str, int], int]:
    sink = DurableFile(tmp)
    topics: dict[str, int] = {}
    count = 0
    try:
        writer = McapWriter(sink, compression=CompressionType.ZSTD)  # type: ignore[arg-type]
        profile = PROFILE
        started = False
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for msg in reader.messages():
            if not started:
                if reader.header is not None:
                    profile = reader.header.profile
                writer.start(profile=profile, library=LIBRARY)
                started = True
            channel = reader.channels[msg.channel_id]
            if channel.id not in channel_ids:
                schema_id = 0
                if msg.schema is not None:
                    if msg.schema.id not in schema_ids:
                        schema_ids[msg.schema.id] = writer.register_schema(
                            msg.schema.name, msg.schema.encoding, msg.schema.data
                        )
                    schema_id = schema_ids[msg.schema.id]
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id, dict(channel.metadata)
                )
            writer.add_message(
                channel_ids[channel.id], msg.log_time_ns, msg.data, msg.log_time_ns, msg.sequence
            )
            topics[msg.topic] = topics.get(msg.topic, 0) + 1
            count += 1
        if reader.header is None:
            raise LogError(f"{src_p}: not an MCAP log ({reader.problem or 'no header'})")
        if not started:
            writer.start(profile=reader.header.profile, library=LIBRARY)
        writer.finish()
        sink.sync()
    finally:
        sink.close()
    return topics, count
