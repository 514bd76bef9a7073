"""Results files of the benchmarks, written like every other file (appliance.atomic).

A benchmark that adds rows to its table in bench/results/ calls :func:`append_result`: the file is
read, the rows are added and the whole is written back atomically (temporary file, fsync, rename),
so an interrupted run leaves the previous table intact.  A benchmark that writes its whole file
calls :func:`appliance.atomic.write_text_atomic` directly.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

from appliance.atomic import output_error, write_bytes_atomic


def append_result(path: str | Path, header: str, text: str) -> None:
    """Add ``text`` at the end of ``path``; a file that does not exist yet starts with ``header``."""
    p = Path(path)
    try:
        existing = p.read_bytes()  # as stored: no newline translation, no decoding
    except FileNotFoundError:
        existing = header.encode("utf-8")
    except OSError as exc:
        raise output_error(p, exc, "cannot read") from None
    write_bytes_atomic(p, existing + text.encode("utf-8"))


def checkout_commit(path: str | Path) -> str:
    """The short commit of the git checkout holding ``path`` (a folder or a file in it), with
    ``+dirty`` when tracked files differ from it; ``unknown`` outside a checkout."""
    p = Path(path)
    where = str(p if p.is_dir() else p.parent)
    try:
        head = subprocess.run(["git", "-C", where, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              timeout=30)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "-C", where, "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
