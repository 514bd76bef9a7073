"""The file under the MCAP writer: unbuffered, write-through, fsync-able, truncatable.

Every ``write`` hands the whole buffer to the kernel (looping over short writes) before it
returns, so the MCAP writer's record batches land whole or raise; ``committed`` is the offset
after the last ``write`` that completed, always a record boundary, and ``crc`` the CRC-32 of the
bytes before it (the data section's CRC, were the data section to end there).  ``sync`` makes
everything written durable (fsync).

A full disk.  ``hold(n)`` writes ``n`` zero bytes past the end without moving it: the next writes
overwrite them, and until then they hold the room the log's closing records need, on a full disk
and under a per-file size limit alike.  ``end_at(offset, data)`` overwrites the file from ``offset``
with ``data`` and cuts it there (the torn tail of a failed write removed): within bytes already
held, it needs no new room.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path
from typing import Protocol

from appliance.atomic import fsync_folder
from appliance.errors import LogError


class Sink(Protocol):
    """What :class:`appliance.logbook.writer.Logbook` needs from its file."""

    committed: int
    crc: int

    def write(self, data: bytes | bytearray | memoryview) -> int: ...

    def tell(self) -> int: ...

    def flush(self) -> None: ...

    def sync(self) -> None: ...

    def hold(self, size: int) -> None: ...

    def end_at(self, offset: int, data: bytes) -> None: ...

    def close(self) -> None: ...


class DurableFile:
    """A new file (never overwrites one) written through ``os.write`` and made durable with fsync."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._fd: int | None = os.open(
                self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o644
            )
        except FileExistsError:
            raise LogError(
                f"{self.path}: log file already exists; a session never overwrites a log"
            ) from None
        except OSError as exc:
            raise LogError(f"{self.path}: cannot create log file: {exc.strerror}") from None
        self._pos = 0
        self.committed = 0
        self.crc = 0
        fsync_folder(self.path.parent)

    @property
    def fd(self) -> int:
        if self._fd is None:
            raise LogError(f"{self.path}: log file is closed")
        return self._fd

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        total = len(view)
        while view:
            n = os.write(self.fd, view)
            self._pos += n
            view = view[n:]
        self.committed = self._pos
        self.crc = zlib.crc32(data, self.crc)
        return total

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        """Nothing is buffered here; :meth:`sync` is what makes data durable."""

    def sync(self) -> None:
        os.fsync(self.fd)

    def hold(self, size: int) -> None:
        self._write_at(self._pos, bytes(size))

    def end_at(self, offset: int, data: bytes) -> None:
        self._write_at(offset, data)
        end = offset + len(data)
        os.ftruncate(self.fd, end)
        os.lseek(self.fd, end, os.SEEK_SET)
        self._pos = self.committed = end

    def _write_at(self, offset: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = os.pwrite(self.fd, view, offset)
            offset += n
            view = view[n:]

    def close(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)


