"""Files the registry writes for itself (its home's state, the pending-requests journal and its
lock): written whole or not at all, and never through a link someone else planted.

:func:`write_atomic` writes a fresh temporary file beside the target (``O_EXCL``: a name that
exists, a symlink included, is never opened), fsyncs it and renames it over the target, which
replaces a link instead of writing where it points. :func:`open_lock` opens a lock file without
following a symlink.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


class UnsafeFileError(OSError):
    """A file the registry writes is a symlink or not a regular file; the message says which."""


def write_atomic(path: str | os.PathLike[str], data: bytes, mode: int = 0o600) -> None:
    """Replace ``path`` with ``data`` atomically (a reader sees the old file or the new one, whole),
    durably (fsynced), and without following a link at ``path`` or at any temporary name.

    Raises:
        UnsafeFileError: ``path`` is a folder or another non-regular file (a link is replaced).
        OSError: the folder cannot be written.
    """
    target = Path(path)
    if target.is_dir() and not target.is_symlink():
        raise UnsafeFileError(f"{target} is a folder, not a file the registry can write")
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def open_lock(path: str | os.PathLike[str]) -> int:
    """A descriptor of the lock file ``path`` (created if missing), opened without following a
    symlink; UnsafeFileError for a link or anything but a regular file."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0), 0o600)
    except OSError as exc:
        if Path(path).is_symlink():
            raise UnsafeFileError(f"{path} is a symlink: the registry's lock file must be a plain file; "
                                  "remove the link") from None
        raise exc
    if not os.path.samestat(os.fstat(fd), os.lstat(path)) or not _regular(fd):
        os.close(fd)
        raise UnsafeFileError(f"{path} is not a regular file: the registry's lock file must be one")
    return fd


def _regular(fd: int) -> bool:
    import stat

    return stat.S_ISREG(os.fstat(fd).st_mode)
