"""What compiled libraries say: their stderr lines and the errors their callbacks cannot raise.

GDAL, libtiff, libpng, libjpeg and OpenCV print on the process's stderr (file descriptor 2) when a
file is damaged, and rasterio's GDAL message callback cannot raise, so Python prints its failures
through ``sys.stderr`` (whatever it is at the time) and then as "Exception ignored".  A command that
reads such a file should say what is wrong in one line; :func:`native_messages` gathers those
messages for the reader to put in its own.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
import threading
from collections.abc import Iterator

#: At most this much of what the libraries print is kept.
KEEP_BYTES = 65536


@contextlib.contextmanager
def native_messages() -> Iterator[list[str]]:
    """Inside the block, what compiled code prints on stderr and the exceptions its callbacks raise
    are kept out of the terminal and listed, one entry per line, in the list it yields (filled when
    the block ends).  Only where the calling thread is the process's only one: file descriptor 2 is
    the whole process's, and another thread's log lines must not vanish into the list."""
    lines: list[str] = []
    if threading.active_count() > 1:
        yield lines
        return
    sys.stderr.flush()
    saved_fd = os.dup(2)
    saved_hook = sys.unraisablehook

    def unraisable(info: sys.UnraisableHookArgs) -> None:
        lines.append(f"{type(info.exc_value).__name__}: {info.exc_value}")

    printed = io.StringIO()  # what a callback's error prints through Python's own sys.stderr
    try:
        with tempfile.TemporaryFile() as capture, contextlib.redirect_stderr(printed):
            os.dup2(capture.fileno(), 2)
            sys.unraisablehook = unraisable
            try:
                yield lines
            finally:
                sys.unraisablehook = saved_hook
                os.dup2(saved_fd, 2)
                capture.seek(0)
                text = capture.read(KEEP_BYTES).decode("utf-8", "replace") + printed.getvalue()[:KEEP_BYTES]
                lines[:0] = [line.strip() for line in text.splitlines() if line.strip()]
    finally:
        os.close(saved_fd)
