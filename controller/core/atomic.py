"""Crash-safe file writes: a reader (or a resumed session) sees the old file or the new one, never half.

Recipe (POSIX): write a temporary file in the *same* directory (so the rename stays on
one file system), flush and ``fsync`` it, ``os.replace`` it over the target (atomic on
POSIX), then ``fsync`` the directory so the rename itself survives a power cut.
A kill -9 at any moment leaves the target untouched or fully replaced, plus at most
one stray ``.<name>.*.tmp`` file, which :func:`remove_stale_temps` clears.

Used for models, report files, exported data and generated docs. This module is the one
place where the product writes files: an OS error (read-only or full disk, a file where
a directory should be) leaves it as :class:`~.errors.DiskError` naming the path.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import errno
import dataclasses
import json
import os
import shutil
import stat
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DiskError

_TMP_SUFFIX = ".tmp"


def ensure_dir(path: str | os.PathLike[str]) -> Path:
    """Create ``path`` (and its parents) if needed; DiskError naming it when it cannot be a
    writable directory (a file there, a read-only or full disk, no permission)."""
    d = Path(path)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise DiskError("is a file, not a directory", path=str(d)) from None
    except NotADirectoryError:
        raise DiskError("a part of this path is a file, not a directory", path=str(d)) from None
    except OSError as exc:
        raise DiskError.from_os_error(exc, str(d), "cannot create this directory") from None
    if not os.access(d, os.W_OK | os.X_OK) or _read_only(d):
        raise DiskError.from_os_error(OSError(30 if _read_only(d) else 13,
                                              "Read-only file system" if _read_only(d) else "Permission denied"),
                                      str(d), "cannot write here")
    return d


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except OSError:
        return False


def _tmp_prefix(target: Path) -> str:
    return f".{target.name}."


def fsync_dir(directory: str | os.PathLike[str]) -> None:
    """Flush a directory entry table to disk (makes a rename or create durable)."""
    fd = os.open(os.fspath(directory), os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, mode: int = 0o644) -> Path:
    """Write ``data`` to ``path`` atomically and durably; returns the resolved target path.

    The parent directory must exist. ``mode`` is applied to the new file (umask ignored,
    so a model written by the controller is readable by the report server).
    """
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    try:
        existing = os.stat(target)
    except FileNotFoundError:
        existing = None
    except OSError as exc:
        raise DiskError.from_os_error(exc, str(target)) from None
    if existing is not None and not stat.S_ISREG(existing.st_mode):
        # A rename over a device or a folder entry would replace it (as root, /dev/null itself).
        raise DiskError.from_os_error(OSError(errno.EINVAL, "the target exists and is not a regular file"),
                                      str(target))
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=_tmp_prefix(target), suffix=_TMP_SUFFIX, dir=directory)
    except OSError as exc:
        raise DiskError.from_os_error(exc, str(target)) from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fchmod(f.fileno(), mode)
            os.fsync(f.fileno())
        os.replace(tmp_name, target)
    except BaseException as exc:
        # Never leave the temporary behind on an ordinary error (a kill -9 can, by design).
        try:
            os.unlink(tmp_name)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):
            raise DiskError.from_os_error(exc, str(target)) from None
        raise
    fsync_dir(directory)
    return target


def readable_text(text: str) -> str:
    """``text`` with the bytes of a file name that is not UTF-8 (which Python holds as lone
    surrogates) shown as U+FFFD: what a report or an export may store as UTF-8."""
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8",
                      mode: int = 0o644) -> Path:
    """Atomic :func:`atomic_write_bytes` of ``text`` encoded with ``encoding`` (no newline translation)."""
    return atomic_write_bytes(path, text.encode(encoding), mode=mode)


def json_default(obj: Any) -> Any:
    """``json.dumps(default=...)`` for the project's values: numpy scalars and arrays,
    paths, dataclasses. NaN/inf inside them still fail where ``allow_nan=False``: the
    contract is null, never NaN/Infinity."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def atomic_write_json(path: str | os.PathLike[str], obj: Any, indent: int | None = 2,
                      sort_keys: bool = False) -> Path:
    """Atomic JSON file (UTF-8, trailing newline). NaN/Infinity are refused (ValueError):
    write ``None`` for "not reached"."""
    text = json.dumps(obj, indent=indent, sort_keys=sort_keys, allow_nan=False,
                      default=json_default, ensure_ascii=False)
    return atomic_write_text(path, text + "\n")


# --------------------------------------------------------------------- directories
_RENAME_EXCHANGE = 2   # linux/fs.h
_AT_FDCWD = -100


def _rename_exchange(a: Path, b: Path) -> bool:
    """Swap two paths atomically with renameat2(RENAME_EXCHANGE); False if unsupported."""
    libc_name = ctypes.util.find_library("c")
    if libc_name is None:
        return False
    libc = ctypes.CDLL(libc_name, use_errno=True)
    renameat2 = getattr(libc, "renameat2", None)
    if renameat2 is None:
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    rc = renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def atomic_dir_replace(new_dir: str | os.PathLike[str], target_dir: str | os.PathLike[str]) -> Path:
    """Put the fully written directory ``new_dir`` in place of ``target_dir``.

    Both must be on the same file system (make ``new_dir`` a sibling, e.g. with
    :func:`make_staging_dir`). When ``target_dir`` exists the two are swapped with
    ``renameat2(RENAME_EXCHANGE)`` — readers see the old tree or the new one — and the
    old tree is then deleted. Where that call is unavailable, the fallback is two
    renames: a kill between them leaves ``target_dir`` missing and the old tree at
    ``<target>.old-<pid>`` (never a mixed tree).
    """
    new = Path(new_dir)
    target = Path(target_dir)
    for root, _dirs, files in os.walk(new):
        for name in files:
            fd = os.open(os.path.join(root, name), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        fsync_dir(root)
    if not target.exists():
        os.rename(new, target)
    elif _rename_exchange(new, target):
        # ``new`` now holds the old tree.
        shutil.rmtree(new, ignore_errors=True)
    else:
        old = target.with_name(f"{target.name}.old-{os.getpid()}")
        os.rename(target, old)
        os.rename(new, target)
        shutil.rmtree(old, ignore_errors=True)
    fsync_dir(target.parent)
    return target


def make_staging_dir(target_dir: str | os.PathLike[str]) -> Path:
    """A fresh empty sibling directory of ``target_dir`` to fill, then :func:`atomic_dir_replace`."""
    target = Path(target_dir)
    target.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=_tmp_prefix(target), suffix=_TMP_SUFFIX, dir=target.parent))


def remove_stale_temps(directory: str | os.PathLike[str]) -> list[Path]:
    """Delete temporaries left by a killed writer (``.<name>.*.tmp`` files and dirs); returns them.

    Call it only while holding the session lock (another writer's temporary would look stale).
    """
    removed: list[Path] = []
    for p in Path(directory).glob(".*" + _TMP_SUFFIX):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    return removed
