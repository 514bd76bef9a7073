"""A database file's bytes: positioned reads and writes, the CRC32 of each block of its arrays, and
the check of those checksums when it is loaded (:mod:`appliance.terrain.database` gives the layout).
The blocks are checksummed on a pool of threads (:func:`run_threads`), as the build sweeps its
azimuths."""

from __future__ import annotations

import errno
import os
import time
import zlib
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from appliance.errors import DatabaseError
from appliance.terrain.verified import FileIdentity, digest_of, is_verified, remember_verified

CHECKSUM_BLOCK = 1 << 20  # bytes of the array section per CRC32


def run_threads(fn: Callable[[int], None], items: Iterable[int], workers: int | None = None) -> Iterator[int]:
    """Call ``fn`` on every item from a pool of threads (default: one per core); yields each item as
    it completes.  ``fn`` is expected to spend its time in kernels that release the GIL."""
    n = workers or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=max(int(n), 1)) as pool:
        futures = {pool.submit(fn, i): i for i in items}
        for fut in as_completed(futures):
            fut.result()
            yield futures[fut]


def pwrite_all(fd: int, arr: np.ndarray, offset: int) -> None:
    """Write the bytes of the contiguous array ``arr`` at ``offset`` of ``fd``."""
    view = np.ascontiguousarray(arr).data.cast("B")
    while view:
        k = os.pwrite(fd, view, offset)
        view = view[k:]
        offset += k


def pread_into(fd: int, arr: np.ndarray, offset: int) -> None:
    """Fill the contiguous array ``arr`` with the bytes at ``offset`` of ``fd``."""
    view = arr.data.cast("B")
    while view:
        k = os.preadv(fd, [view], offset)
        if k == 0:
            raise OSError(errno.EIO, f"the file ends {len(view)} bytes short")
        view = view[k:]
        offset += k


def file_block_checksums(fd: int, start: int, size: int, workers: int | None = None) -> list[int]:
    """CRC32 of each CHECKSUM_BLOCK bytes of the ``size`` bytes at ``start`` of ``fd`` (a database's
    array section), read back a block at a time."""
    crcs = {}

    def one(lo: int) -> None:
        buf = np.empty(min(CHECKSUM_BLOCK, size - lo), np.uint8)
        pread_into(fd, buf, start + lo)
        crcs[lo] = zlib.crc32(buf.data)

    for _ in run_threads(one, range(0, size, CHECKSUM_BLOCK), workers):
        pass
    return [crcs[lo] for lo in range(0, size, CHECKSUM_BLOCK)]


def verify_checksums(p: Path, header: dict, head: bytes, body: np.ndarray, identity: FileIdentity | None = None,
                     full_check: bool = False) -> None:
    """Compare the header and every block of ``body`` (the array section, checksum table included)
    with the table written at build; a mismatch is a DatabaseError naming the block.

    The header is always checked.  The blocks are not when a record of :mod:`appliance.terrain.verified`
    says that this file (``identity``: fstat of the open file ``body`` maps), unchanged since, with
    this header and table, passed them all (unless ``full_check``); a file that passes them all is
    recorded so."""
    spec = header.get("checksum")
    if spec is None:
        return  # a version 2 file written before the checksums
    try:
        size, offset, n_blocks = int(spec["block_bytes"]), int(spec["offset"]), int(spec["blocks"])
        if spec.get("algorithm") != "crc32" or size != CHECKSUM_BLOCK or n_blocks != -(-offset // size):
            raise ValueError(f"checksum entry {spec}")
    except (KeyError, TypeError, ValueError) as exc:
        raise DatabaseError(f"{p}: corrupt database header ({exc})") from None
    if body.size < offset + 4 * (1 + n_blocks):
        raise DatabaseError(f"{p}: truncated database: {body.size} bytes of arrays and checksums, expected "
                            f"{offset + 4 * (1 + n_blocks)}")
    table = body[offset : offset + 4 * (1 + n_blocks)].view("<u4")
    if zlib.crc32(head) != int(table[0]):
        raise DatabaseError(f"{p}: the header fails its CRC32 check: the file is damaged; rebuild it")
    digest = digest_of(head, table.tobytes())
    if identity is not None and not full_check and is_verified(identity, digest):
        return
    started_ns = time.time_ns()
    arrays = body[:offset]
    # zlib releases the GIL on large buffers: the blocks are checked on every core
    with ThreadPoolExecutor(max_workers=max(len(os.sched_getaffinity(0)), 1)) as pool:
        crcs = list(pool.map(lambda lo: zlib.crc32(arrays[lo : lo + size].data), range(0, offset, size)))
    for k in range(n_blocks):
        lo = k * size
        if crcs[k] != int(table[1 + k]):
            hi = min(lo + size, offset)
            raise DatabaseError(
                f"{p}: block {k} of {n_blocks} (array bytes {lo}-{hi - 1}) fails its CRC32 check: the file "
                "is damaged; rebuild it"
            )
    if identity is not None:
        remember_verified(identity, digest, str(p.resolve()), started_ns)
