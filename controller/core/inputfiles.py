"""Files a user names (plans, cells, objects, meshes, calibration files): refused before they
are read when they are not regular files of a believable size.

Why: ``/dev/zero`` named as a cell file was read until the machine ran out of memory, and a
named pipe blocks the reader until someone writes to it. ``os.stat`` answers without
opening, so nothing here blocks; the errors are ``OSError`` with a ``strerror`` a person can
read, which every reader already reports with the file's name.
"""
from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

MAX_TEXT_BYTES = 16 * 1024 * 1024          # a plan, cell, object or calibration file
MAX_MESH_BYTES = 2 * 1024 * 1024 * 1024    # a mesh: a few million triangles in binary PLY/STL


def check_input_file(path: str | os.PathLike[str], max_bytes: int = MAX_TEXT_BYTES) -> int:
    """The size (bytes) of ``path``, a regular file of at most ``max_bytes``; ``OSError``
    (FileNotFoundError, IsADirectoryError, or EINVAL / EFBIG with a message) otherwise."""
    st = os.stat(path)
    if stat.S_ISDIR(st.st_mode):
        raise IsADirectoryError(errno.EISDIR, "is a directory", str(path))
    if not stat.S_ISREG(st.st_mode):
        raise OSError(errno.EINVAL, "not a regular file (a device, pipe or socket)", str(path))
    if st.st_size > max_bytes:
        raise OSError(errno.EFBIG, f"{st.st_size} bytes, more than the {max_bytes} such a file can be", str(path))
    return int(st.st_size)


def read_input_bytes(path: str | os.PathLike[str], max_bytes: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of ``path`` after :func:`check_input_file` (and never more than ``max_bytes``:
    a file that grows while being read is cut there and refused)."""
    check_input_file(path, max_bytes)
    with open(path, "rb") as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise OSError(errno.EFBIG, f"more than the {max_bytes} bytes such a file can be", str(path))
    return data


def read_input_text(path: str | os.PathLike[str], max_bytes: int = MAX_TEXT_BYTES) -> str:
    """:func:`read_input_bytes` decoded as UTF-8 (``UnicodeDecodeError`` otherwise)."""
    return read_input_bytes(Path(path), max_bytes).decode("utf-8")
