"""File checks shared by the readers: a FIFO, a device or a socket given as a recording (or found where
a side file is expected) is refused with one OSError at open, before anything reads from it (opening a
FIFO blocks until a writer appears; a device such as /dev/zero never ends)."""

from __future__ import annotations

import os
import stat
import zipfile
import zlib
from pathlib import Path

#: what reading a damaged .npz raises (a truncated archive, a bad CRC, a broken compressed stream, a
#: header that promises more than the file holds): each reader turns it into a ValueError naming the file
NPZ_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError)

_KINDS = (
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def special_kind(mode: int) -> str | None:
    """What a file of ``st_mode`` ``mode`` is when it is neither regular nor a folder ("a FIFO (named
    pipe)", ...); None otherwise."""
    for test, name in _KINDS:
        if test(mode):
            return name
    return None


def _refuse(path: Path, kind: str) -> OSError:
    return OSError(f"{path}: is {kind}, not a regular file: refused (reading it could block for ever)")


def check_regular(path: str | os.PathLike) -> Path:
    """``path`` when it is a regular file (links followed); FileNotFoundError when it does not exist,
    IsADirectoryError for a folder, OSError naming the kind for a FIFO, a device or a socket."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    except OSError as exc:
        raise OSError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if stat.S_ISDIR(mode):
        raise IsADirectoryError(f"{path}: is a folder, not a file")
    kind = special_kind(mode)
    if kind is not None:
        raise _refuse(path, kind)
    return path


def check_not_special(path: str | os.PathLike) -> Path:
    """``path`` when it is a regular file, a folder or absent; OSError naming the kind otherwise."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return path  # absent or unreadable: the caller's own check reports it
    kind = special_kind(mode)
    if kind is not None:
        raise _refuse(path, kind)
    return path


def is_present(path: str | os.PathLike) -> bool:
    """Whether the optional file ``path`` is there to read: True for a regular file, False when it is
    absent (or a folder); OSError naming the kind for a FIFO, a device or a socket (where ``Path.is_file``
    would answer False and hide it)."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return False
    if stat.S_ISREG(mode):
        return True
    kind = special_kind(mode)
    if kind is not None:
        raise _refuse(path, kind)
    return False
