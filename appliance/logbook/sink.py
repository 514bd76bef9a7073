"""The file under the MCAP writer: unbuffered, write-through, fsync-able, truncatable.

Every ``write`` hands the whole buffer to the kernel (looping over short writes) before it
returns, so the MCAP writer's record batches land whole or raise; ``committed`` is the offset
after the last ``write`` that completed, always a record boundary.  ``sync`` makes everything
written durable (fsync).  After a failed write (a full disk) ``truncate(committed)`` removes the
torn tail.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Protocol

from appliance.atomic import fsync_folder
from appliance.errors import LogError


class Sink(Protocol):
    """What :class:`appliance.logbook.writer.Logbook` needs from its file."""

    committed: int

    def write(self, data: bytes | bytearray | memoryview) -> int: ...

    def tell(self) -> int: ...

    def flush(self) -> None: ...

    def sync(self) -> None: ...

    def truncate(self, offset: int) -> None: ...

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
        return total

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        """Nothing is buffered here; :meth:`sync` is what makes data durable."""

    def sync(self) -> None:
        os.fsync(self.fd)

    def truncate(self, offset: int) -> None:
        os.ftruncate(self.fd, offset)
        os.lseek(self.fd, offset, os.SEEK_SET)
        self._pos = self.committed = offset

    def close(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)


