"""Writing a job's output files safely: atomically (:func:`atomic_write`), never through a
symbolic link (:func:`refuse_link`, :func:`drop_links`), one job per folder at a time
(:class:`JobLock`); a failure is one line (:class:`OutputError`). Moved out of
:mod:`nirspi_pipe.records` (issue 42 item 5).
"""

from __future__ import annotations

import contextlib
import errno
import os
import socket
import tempfile
import time
from pathlib import Path

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.safeio import sanitize_text

__all__ = ["JobLock", "OutputError", "atomic_write", "drop_links", "refuse_link"]


class OutputError(NirspiError):
    """An output file could not be written (unwritable folder, disk full): one line naming it."""


def _write_failure(path: Path, exc: OSError) -> OutputError:
    reason = exc.strerror or str(exc)
    if exc.errno == errno.ENOSPC:
        reason = "no space left on device"
    return OutputError(f"cannot write {path}: {reason}")


def refuse_link(folder: Path, what: str = "output folder") -> None:
    """Raise :class:`OutputError` (one line naming it and its target) when ``folder`` is a
    symbolic link: nothing is ever written through a link (docs/hostile.md). Only ``folder``
    itself is checked, not the folders above it."""
    folder = Path(folder)
    if folder.is_symlink():
        try:
            target = os.readlink(folder)
        except OSError:
            target = "?"

        raise OutputError(
            f"{what} {sanitize_text(folder, 300)} is a symbolic link (to {sanitize_text(target, 300)}); refused: "
            "nothing is written through links (remove the link, or choose another folder)"
        )


def drop_links(folder: Path, names: tuple[str, ...]) -> None:
    """Remove each file ``folder/name`` that is a symbolic link (the link, never its target), so
    that writers that open the path itself (matplotlib's ``savefig``, pyvista) write a new file
    there, as :func:`atomic_write`'s rename does."""
    for name in names:
        path = Path(folder) / name
        if path.is_symlink():
            try:
                path.unlink()
            except OSError as exc:
                raise _write_failure(path, exc) from None


def atomic_write(path: Path, data: bytes | str, durable: bool = True) -> Path:
    """Write ``data`` to ``path`` atomically: into a uniquely named temporary file in the same
    folder (``tempfile.mkstemp``), flushed to disk, then renamed over ``path``. Concurrent writers
    never share a temporary file, and readers see the old or the new file, never a torn one.

    ``durable`` (default): the temporary file is ``fsync``-ed before the rename, so that even a
    power cut or a kernel crash leaves the old or the whole new file. ``durable=False`` leaves
    that flush to the kernel: a crash of the writing process (a kill, a segfault) still leaves
    the old or the whole new file, since the rename is atomic whether or not the data reached the
    disk, but after a power cut the file may be empty or hold zeros, which every reader here
    takes as unreadable. For bookkeeping whose loss costs nothing but a recount (``attempts.json``
    read as 0 attempts): its ``fsync`` took 12 ms of wall time a job in the sweeping process,
    which claims the jobs one after another (``paper_ci`` under ``cProfile``, issue 42 item 6).

    Raises :class:`OutputError` (one line naming ``path``) when the folder is unwritable or the
    disk is full; the temporary file is removed, and ``path`` keeps its previous content. A folder
    that is a symbolic link is refused (:func:`refuse_link`); a ``path`` that is one is replaced
    by the rename (the link, never its target).
    """
    path = Path(path)
    refuse_link(path.parent, "folder")
    payload = data.encode() if isinstance(data, str) else bytes(data)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise _write_failure(path, exc) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.chmod(tmp_name, 0o644)  # mkstemp makes 0600; records are shared (cluster file systems)
        os.replace(tmp_name, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp_name)
        if isinstance(exc, OSError):
            raise _write_failure(path, exc) from None
        raise
    return path


class JobLock:
    """An exclusive lock on a job folder (``.lock``, POSIX ``fcntl.lockf``), so that two sweeps
    writing into one folder never run the same job at once.

    The kernel releases the lock when its holder exits, however it dies (even ``SIGKILL``), so a
    lock is never stale. ``acquire(wait=False)`` returns False when another process holds it;
    ``acquire()`` waits for it. Where ``fcntl`` does not exist (Windows) the lock is a no-op.
    """

    def __init__(self, folder: Path) -> None:
        self.path = Path(folder) / ".lock"
        self._fd: int | None = None

    def acquire(self, wait: bool = True, poll_s: float = 0.2) -> bool:
        try:
            # platform: fcntl is POSIX only
            import fcntl  # POSIX only: this branch does not run on Windows
        except ImportError:  # pragma: no cover - Windows
            return True
        refuse_link(self.path.parent, "job folder")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = self._open()
        except OSError as exc:  # disk full, unwritable folder: one line naming the lock file
            raise _write_failure(self.path, exc) from None
        while True:
            try:
                fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno not in (errno.EACCES, errno.EAGAIN):
                    os.close(fd)
                    raise
                if not wait:
                    os.close(fd)
                    return False
                time.sleep(poll_s)
                continue
            self._fd = fd
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.write(fd, f"{socket.gethostname()} {os.getpid()}\n".encode())
            return True

    def _open(self) -> int:
        """The lock file's descriptor, never through a link: a ``.lock`` that is a symbolic link
        is removed (the link, not its target) and created anew."""
        flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
        try:
            return os.open(self.path, flags, 0o644)
        except OSError as exc:
            if exc.errno != errno.ELOOP:
                raise
        self.path.unlink()
        return os.open(self.path, flags, 0o644)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the lock
            self._fd = None
