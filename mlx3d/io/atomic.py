"""Atomic file replacement.

``atomic_write`` writes to a temporary file in the destination's directory and
renames it over the destination only once everything was written (and, by
default, flushed to disk).  Readers therefore see either the old file or the
complete new one, never a partial write; on any error the temporary file is
removed and an existing destination is left untouched.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import stat
from typing import IO, Iterator

__all__ = ["atomic_write"]

_MAX_TEMP_BASENAME = 180  # keep temporary names below common 255-byte limits


def _fsync_directory(directory: str) -> None:
    """Make a rename in ``directory`` durable (POSIX only; best effort)."""
    if os.name == "nt":
        return
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_write(
    path: str | os.PathLike,
    mode: str = "wb",
    *,
    fsync: bool = True,
    encoding: str | None = None,
    newline: str | None = None,
) -> Iterator[IO]:
    """Open a temporary file that replaces ``path`` when the block succeeds.

    Usage::

        with atomic_write("out.ply") as f:
            f.write(header)
            array.tofile(f)

    ``mode`` is ``"wb"`` (binary) or ``"w"`` (text; ``encoding`` and
    ``newline`` are passed to :func:`open`).  The temporary file lives in the
    same directory as ``path`` (so the final :func:`os.replace` is atomic) and
    is named ``.<name>.<random>.tmp``; its ``name`` attribute is its path,
    which lets callers open further handles on it.  On success it is flushed,
    ``fsync``-ed (unless ``fsync=False``), closed and renamed over ``path``;
    the permission bits of an existing ``path`` are kept.  If the block
    raises, the temporary file is removed and the exception propagates.  A
    symbolic link at ``path`` is followed: the file it points to is replaced.
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_write: mode must be 'wb' or 'w', got {mode!r}")
    binary = mode == "wb"
    if binary and (encoding is not None or newline is not None):
        raise ValueError("atomic_write: encoding/newline are only valid in text mode")

    target = os.fspath(path)
    if isinstance(target, bytes):
        target = os.fsdecode(target)
    if os.path.islink(target):
        target = os.path.realpath(target)
    directory, base = os.path.split(os.path.abspath(target))
    if not base:
        raise ValueError(f"atomic_write: {target!r} names a directory, not a file")
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"atomic_write: directory {directory!r} does not exist")
    if os.path.isdir(target):
        raise IsADirectoryError(f"atomic_write: {target!r} is a directory")

    stem = base[:_MAX_TEMP_BASENAME]
    handle = None
    tmp = ""
    for _ in range(100):
        tmp = os.path.join(directory, f".{stem}.{secrets.token_hex(4)}.tmp")
        try:
            if binary:
                handle = open(tmp, "xb")
            else:
                handle = open(tmp, "x", encoding=encoding, newline=newline)
            break
        except FileExistsError:
            continue
    if handle is None:
        raise FileExistsError(f"atomic_write: could not create a temporary file in {directory!r}")

    try:
        try:
            mode_bits = stat.S_IMODE(os.stat(target).st_mode)
        except FileNotFoundError:
            mode_bits = None
        if mode_bits is not None:
            os.chmod(tmp, mode_bits)
        yield handle
        handle.flush()
        if fsync:
            os.fsync(handle.fileno())
        handle.close()
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(Exception):
            handle.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    if fsync:
        _fsync_directory(directory)
