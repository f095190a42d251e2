"""Output files a command writes for its user (a recording, an exported model): checked before the
work starts, written whole under a fresh temporary name and moved into place, never through a link.

:func:`check_output` refuses, with one line saying what to do, a target that is a folder, a device,
FIFO or socket (``/dev/full``), whose name is too long, whose folder is missing or cannot be
written, or (unless ``overwrite``) that exists, a link included. :class:`AtomicOutput` writes a
fresh temporary file beside the target (``O_EXCL``: nothing that is there, a planted link included,
is opened) and on :meth:`AtomicOutput.commit` fsyncs it and moves it into place: linked to the
target's name, which fails if anything took that name meanwhile, or with ``overwrite`` renamed over
it (a link there is replaced, never written through). A write that fails removes its temporary file.
:func:`check_output_folder` does the same for an output folder (a run's, the demo's) before the work.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from pathlib import Path
from typing import IO

from medc_training.untrusted import printable

#: Characters of the target's name the temporary name starts with (``.<name>.<random>.tmp``).
TMP_NAME_CHARS = 40


class OutputError(ValueError):
    """An output file cannot be written where asked; the message names it and says what to do."""


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def check_output(path: str | os.PathLike[str], overwrite: bool = False, flag: str = "--overwrite") -> Path:
    """``path`` as an output file to write (made absolute, not resolved: a link at ``path`` is the
    link, not its target).

    Raises:
        OutputError: a folder, not a regular file or a link, a name longer than the file system
            takes, a missing or unwritable folder, or (unless ``overwrite``) something already there;
            ``flag`` is the option the message names to overwrite.
    """
    target = Path(os.path.abspath(os.fspath(path)))
    parent = target.parent
    if not parent.is_dir():
        raise OutputError(f"cannot write {_shown(target)}: the folder {_shown(parent)} does not exist")
    if len(os.fsencode(target.name)) > _name_max(parent):
        raise OutputError(f"cannot write {_shown(parent / target.name[:40])}...: the name is longer than the "
                          f"{_name_max(parent)} bytes the file system takes")
    if target.is_dir() and not target.is_symlink():
        raise OutputError(f"{_shown(target)} is a folder: give the file to write, e.g. "
                          f"{_shown(target / 'out')}")
    try:
        mode = target.lstat().st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise OutputError(f"cannot write {_shown(target)}: {exc.strerror}") from None
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        raise OutputError(f"{_shown(target)} is not a regular file (a device, FIFO or socket): give a file "
                          "to write")
    if mode is not None and not overwrite:
        what = "a link" if stat.S_ISLNK(mode) else "a file"
        raise OutputError(f"{_shown(target)} exists ({what}): not overwritten; give {flag} to replace it, or "
                          "another name")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {_shown(target)}: the folder {_shown(parent)} is not writable")
    return target


def check_output_folder(path: str | os.PathLike[str]) -> Path:
    """``path`` as a folder to write into, made later if missing (made absolute, not resolved).

    Raises:
        OutputError: ``path`` or a folder on the way to it is something else (a file, a device, a
            link to one), a name on the way is longer than the file system takes, or the folder to
            write into (or the nearest one that exists) cannot be written.
    """
    target = Path(os.path.abspath(os.fspath(path)))
    existing = _nearest_folder(target)
    below = target.relative_to(existing).parts
    # another process (a parallel run of the same plan) may make the folder between the walk and
    # this check: what exists and is not a folder the second time round is refused
    if below and os.path.lexists(existing / below[0]) and not os.path.isdir(existing / below[0]):
        there = existing / below[0]
        raise OutputError(f"{_shown(there)} is not a folder: give a folder to write into"
                          + ("" if there == target else f" (for {_shown(target)})"))
    for name in below:
        if len(os.fsencode(name)) > _name_max(existing):
            raise OutputError(f"cannot make the folder {_shown(target)[:120]}...: the name "
                              f"{_shown(name)[:40]}... is longer than the {_name_max(existing)} bytes "
                              "the file system takes")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write into {_shown(target)}: the folder {_shown(existing)} is not "
                          "writable")
    return target


def _nearest_folder(target: Path) -> Path:
    """``target`` or the nearest of its parents that is a folder (a missing name is not)."""
    existing = target
    while not os.path.isdir(existing):  # False for what is missing or cannot be looked at
        existing = existing.parent
    return existing


class AtomicOutput:
    """A fresh temporary file beside ``target`` (``.file``, open for binary writing) that
    :meth:`commit` moves into place (see the module docstring); :meth:`discard` removes it. As a
    context manager: committed when the block ends normally, discarded when it raises.

    Raises:
        OutputError: the temporary file cannot be created (the folder cannot be written, a name
            too long, the disk full): the work has not started.
    """

    def __init__(self, target: str | os.PathLike[str], overwrite: bool = False,
                 flag: str = "--overwrite") -> None:
        self.target = Path(os.path.abspath(os.fspath(target)))
        self.overwrite = overwrite
        self.flag = flag
        prefix = f".{self.target.name[:TMP_NAME_CHARS]}."
        try:
            fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=self.target.parent)
        except OSError as exc:
            raise OutputError(f"cannot write {_shown(self.target)}: {exc.strerror or exc}") from None
        self.tmp = Path(tmp)
        # mkstemp makes the file 0600; an output is a file to share: the mode open() would give it.
        with contextlib.suppress(OSError):
            os.fchmod(fd, 0o666 & ~_umask())
        self.file: IO[bytes] = os.fdopen(fd, "wb")
        self.done = False

    def sync(self) -> None:
        """Flush and fsync what was written so far (a full disk says so here).

        Raises:
            OutputError: the write failed.
        """
        try:
            self.file.flush()
            os.fsync(self.file.fileno())
        except OSError as exc:
            raise OutputError(f"cannot write {_shown(self.target)}: {exc.strerror or exc}") from None

    def commit(self) -> Path:
        """Fsync the file and move it to the target's name; returns the target.

        Raises:
            OutputError: the write failed (the temporary file is removed), or (without
                ``overwrite``) something took the target's name meanwhile (the temporary file is
                kept and named in the message: nothing written is lost).
        """
        try:
            self.sync()
            self.file.close()
        except BaseException:
            self.discard()
            raise
        self.done = True
        if self.overwrite:
            os.replace(self.tmp, self.target)
            return self.target
        try:
            os.link(self.tmp, self.target, follow_symlinks=False)
        except FileExistsError:
            raise OutputError(f"{_shown(self.target)} appeared while writing: not overwritten; what was "
                              f"written is in {_shown(self.tmp)}") from None
        except OSError as exc:  # a file system without hard links: the last look, then the rename
            if exc.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.EMLINK):
                raise
            if os.path.lexists(self.target):
                raise OutputError(f"{_shown(self.target)} appeared while writing: not overwritten; what was "
                                  f"written is in {_shown(self.tmp)}") from None
            os.replace(self.tmp, self.target)
            return self.target
        os.unlink(self.tmp)
        return self.target

    def discard(self) -> None:
        """Close and remove the temporary file (idempotent)."""
        self.done = True
        with contextlib.suppress(OSError):
            self.file.close()
        with contextlib.suppress(OSError):
            os.unlink(self.tmp)

    def __enter__(self) -> AtomicOutput:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.commit()
        else:
            self.discard()


def write_output(path: str | os.PathLike[str], data: bytes, overwrite: bool = False,
                 flag: str = "--overwrite") -> Path:
    """Check ``path`` (:func:`check_output`) and write ``data`` to it atomically; returns the path."""
    target = check_output(path, overwrite, flag)
    with AtomicOutput(target, overwrite, flag) as out:
        try:
            out.file.write(data)
        except OSError as exc:
            raise OutputError(f"cannot write {_shown(target)}: {exc.strerror or exc}") from None
    return target


def is_same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """Whether ``a`` and ``b`` name one file (links followed; False when either is missing)."""
    try:
        return os.path.samefile(a, b)
    except OSError as exc:
        if exc.errno in (errno.ENOENT, errno.ENOTDIR, errno.ELOOP):
            return False
        raise


def _shown(path: str | os.PathLike[str]) -> str:
    """``path`` for a message: printable ASCII only (anything else as ``?``), 300 characters at most."""
    return printable(os.fspath(path), 300)


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


__all__ = ["AtomicOutput", "OutputError", "check_output", "check_output_folder", "is_same_file",
           "write_output"]
