"""Records of skyline databases whose every block passed its CRC32 check, so that loading the same,
unchanged file again does not read and hash all of it (1.3 GB for a whole SRTM tile: most of an
estimate's time).

A record is kept per file, named by its device and inode, in ``verified-databases/`` of the
appliance's cache folder (:func:`cache_root`).  It holds the file's size, modification and change
times (ns) as ``fstat`` gave them on the open file that was checked, and a SHA-256 of its header and
checksum table.  A load skips the block checks only when all of these match the file it has open.
Any write to the file through the file system moves its change time (which no user call can set
back), so a database modified, truncated, extended or copied over after its verification is
checked in full again, and a damaged block is refused as before; a database replaced by a rename
is another inode.

Two cases the file system's times cannot show, and how they are covered:

- a write in the same tick of the file system's clock as the file's last change, after it was
  opened for checking: no record is kept of a file changed less than :data:`SETTLE_NS` before its
  check began (it is checked in full again next time);
- a fault of the storage itself (a flipped bit on the card, not written through the file system):
  a record is trusted for :data:`MAX_AGE_S` at most, then the file is checked in full again.

No record can be kept (no cache folder, a read-only one): every load checks in full, as before.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from appliance.atomic import write_text_atomic
from appliance.errors import ViperError

LOG = logging.getLogger(__name__)

#: The folder of the records, inside the cache folder.
RECORD_DIR = "verified-databases"
#: A file changed less than this long (ns) before its check began gets no record.
SETTLE_NS = 2_000_000_000
#: How long (s) a record is trusted before the file is checked in full again.
MAX_AGE_S = 24 * 3600.0


def cache_root() -> Path | None:
    """The appliance's cache folder: $VIPER_CACHE_DIR; else the first folder of $CACHE_DIRECTORY (the
    units' ``CacheDirectory=viper``: /var/cache/viper); else $XDG_CACHE_HOME/viper or ~/.cache/viper.
    None when none of these can be named."""
    own = os.environ.get("VIPER_CACHE_DIR")
    if own:
        return Path(own)
    unit = os.environ.get("CACHE_DIRECTORY")
    if unit:
        return Path(unit.split(":")[0])
    xdg = os.environ.get("XDG_CACHE_HOME")
    if xdg and os.path.isabs(xdg):
        return Path(xdg) / "viper"
    try:
        return Path.home() / ".cache" / "viper"
    except (RuntimeError, KeyError):
        return None


@dataclass(frozen=True)
class FileIdentity:
    """What ``fstat`` says of an open file: which file it is and when it last changed."""

    dev: int
    ino: int
    size: int
    mtime_ns: int
    ctime_ns: int

    @classmethod
    def of_fd(cls, fd: int) -> FileIdentity:
        st = os.fstat(fd)
        return cls(st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def digest_of(head: bytes, table: bytes) -> str:
    """SHA-256 (hex) of a database's header bytes and checksum table."""
    return hashlib.sha256(head + table).hexdigest()


def _record_path(identity: FileIdentity) -> Path | None:
    root = cache_root()
    return None if root is None else root / RECORD_DIR / f"{identity.dev:x}-{identity.ino:x}.json"


def is_verified(identity: FileIdentity, digest: str, now_s: float | None = None) -> bool:
    """Whether a record says that this very file, unchanged, passed every block check less than
    :data:`MAX_AGE_S` ago."""
    path = _record_path(identity)
    if path is None:
        return False
    try:
        rec = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(rec, dict):
            return False
        same = (rec.get("identity") == asdict(identity) and rec.get("digest") == digest)
        age = (time.time() if now_s is None else now_s) - float(rec.get("verified_at", 0.0))
    except (OSError, ValueError, TypeError):
        return False
    return same and 0.0 <= age <= MAX_AGE_S


def remember_verified(identity: FileIdentity, digest: str, source: str, started_ns: int) -> bool:
    """Record that the file of ``identity`` passed every block check begun at ``started_ns``
    (time.time_ns()); returns whether a record was written.  A file changed less than
    :data:`SETTLE_NS` before that gets none; a cache folder that cannot be written is no error."""
    if started_ns - max(identity.mtime_ns, identity.ctime_ns) < SETTLE_NS:
        return False
    path = _record_path(identity)
    if path is None:
        return False
    rec = {"source": source, "identity": asdict(identity), "digest": digest, "verified_at": started_ns / 1e9}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        for old in path.parent.glob("*.json"):  # records of earlier files at the same path
            if old != path and _source_of(old) == source:
                old.unlink(missing_ok=True)
        write_text_atomic(path, json.dumps(rec) + "\n")
    except (OSError, ViperError) as exc:
        LOG.debug("no verification record for %s in %s: %s", source, path.parent, exc)
        return False
    return True


def _source_of(record: Path) -> str | None:
    try:
        rec = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return rec.get("source") if isinstance(rec, dict) else None
