"""``viper log recover``: rewrite a truncated or torn log into a valid, indexed MCAP file.

The broken file is read sequentially up to its first unreadable byte (see
:class:`appliance.logbook.reader.LogReader`); every schema, channel and message read is written
again, with the same ids, topics and times, into a new file that gets a summary and a footer.  The
output is written beside its final name and renamed into place only when complete.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from appliance.errors import LogError
from appliance.logbook.reader import ErrorPolicy, LogReader
from appliance.logbook.sink import DurableFile
from appliance.logbook.writer import LIBRARY, PROFILE


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
    if dst_p.exists() and not overwrite:
        raise LogError(f"{dst_p}: already exists (pass --force to replace it)")
    reader = LogReader(src_p, ErrorPolicy.STOP)
    tmp = dst_p.with_name(f".{dst_p.name}.partial")
    tmp.unlink(missing_ok=True)
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
        sink.close()
        os.replace(tmp, dst_p)
    except LogError:
        sink.close()
        tmp.unlink(missing_ok=True)
        raise
    except OSError as exc:
        sink.close()
        tmp.unlink(missing_ok=True)
        raise LogError(f"{dst_p}: cannot write the recovered log: {exc.strerror or exc}") from None
    except BaseException:
        sink.close()
        tmp.unlink(missing_ok=True)
        raise
    return RecoveryReport(
        messages=count,
        topics=topics,
        source_complete=reader.complete,
        problem=reader.problem,
        stopped_at=reader.stopped_at,
        source_bytes=reader.size_bytes,
    )
