"""Output folders that cannot be damaged: created with one-line errors, locked, and kept inside themselves.

* :func:`make_out_dir` creates ``--out`` and turns "under a file", "read-only" and "permission denied"
  into one line each.
* :class:`OutLock` is an exclusive ``flock`` on ``OUT/.capture.lock``: a second run on the same folder
  fails at once with one line naming the first one's process. The kernel drops the lock when its
  process ends, however it ends (``kill -9`` included), so a stale lock file never blocks a later run;
  forked children (the fit and figure processes) do not keep it, even while they wind down after a kill.
* :func:`check_no_links` refuses a run folder whose entries are symbolic links: nothing is written
  through a link to outside ``--out``.
* :func:`clean_temp_files` removes the temporary siblings of atomic writes that a killed run left
  (only ever called while holding the lock, so no writer is using them).
"""

from __future__ import annotations

import errno
import fcntl
import os
from pathlib import Path
from typing import Iterable

from capture.io.atomic import is_temp_name
from capture.io.errors import CaptureError

LOCK_NAME = ".capture.lock"

#: Lock files this process holds. A forked child (the fit or figure process) shares the parent's open file
#: description of each; ``flock`` is released only when every descriptor of it is closed, so a child that
#: outlives a killed run would keep the folder locked. Children close their copies at once (closing, not
#: unlocking: unlocking would release the parent's lock too).
_HELD_FDS: set[int] = set()


def _close_held_in_child() -> None:
    for fd in list(_HELD_FDS):
        try:
            os.close(fd)
        except OSError:
            pass
    _HELD_FDS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_close_held_in_child)


def make_out_dir(out: Path, flag: str = "--out") -> Path:
    """Create ``out`` (and its parents); one line when it cannot be a writable folder."""
    out = Path(out)
    for p in (out, *out.absolute().parents):
        if p.is_symlink() and not p.exists():
            raise CaptureError(f"{flag} {out}: {p} is a broken symbolic link; remove it or choose another folder")
        if p.exists():
            if not p.is_dir():
                where = "is a file" if p == out else f"is under {p}, which is a file"
                raise CaptureError(f"{flag} {out} {where}; give a folder")
            break
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CaptureError(f"cannot create {flag} folder {out}: {os_reason(exc)}; choose a folder you can "
                           f"write to") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise CaptureError(f"{flag} {out} is not writable (read-only or not yours); choose a folder you can write to")
    return out


def os_reason(exc: OSError) -> str:
    """A few words for an OS error (``no space left on device``, ``read-only file system``, ...)."""
    if exc.errno is not None:
        return os.strerror(exc.errno).lower()
    return exc.__class__.__name__


class OutLock:
    """Exclusive lock of a folder for one run (``with OutLock(out, "run"):``)."""

    def __init__(self, out: Path, what: str = "run", flag: str = "--out"):
        self.path = Path(out) / LOCK_NAME
        self.out, self.what, self.flag = Path(out), what, flag
        self._fd: int | None = None

    def acquire(self) -> "OutLock":
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise CaptureError(f"cannot write in {self.flag} {self.out}: {os_reason(exc)}; choose a folder you can "
                               f"write to") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            try:
                holder = os.read(fd, 64).decode("ascii", "replace").strip() or "?"
            finally:
                os.close(fd)
            if exc.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise CaptureError(f"another capture {self.what} (process {holder}) is writing to {self.out}; wait "
                                   f"for it to finish or choose another {self.flag}") from None
            raise CaptureError(f"cannot lock {self.flag} {self.out}: {os_reason(exc)}") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        _HELD_FDS.add(fd)
        return self

    def release(self) -> None:
        if self._fd is not None:
            _HELD_FDS.discard(self._fd)
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "OutLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _walk(root: Path, names: Iterable[str]):
    """``(path, is_dir)`` of every entry named in ``names`` under ``root`` and all below it (links not followed)."""
    for name in names:
        p = root / name
        if not (p.exists() or p.is_symlink()):
            continue
        yield p, p.is_dir() and not p.is_symlink()
        if p.is_dir() and not p.is_symlink():
            for d, dirs, files in os.walk(p, followlinks=False):
                for n in dirs:
                    yield Path(d) / n, True
                for n in files:
                    yield Path(d) / n, False


def check_no_links(out: Path, names: Iterable[str], flag: str = "--out") -> None:
    """One line when an entry the run writes (``names`` under ``out``, or anything below them) is a symbolic link."""
    for p, _is_dir in _walk(Path(out), names):
        if p.is_symlink():
            target = os.readlink(p)
            raise CaptureError(f"{p} is a symbolic link (to {target}); a run writes only inside {flag}: replace "
                               f"the link with a folder or file of its own, or choose another {flag}")


def clean_temp_files(out: Path, names: Iterable[str]) -> int:
    """Remove the temporary files of interrupted atomic writes in ``out`` and under ``names``; their count."""
    out = Path(out)
    n = 0
    candidates = [out / e.name for e in os.scandir(out) if e.is_file(follow_symlinks=False)]
    candidates += [p for p, is_dir in _walk(out, names) if not is_dir]
    for p in candidates:
        if is_temp_name(p.name) and not p.is_symlink():
            try:
                p.unlink()
                n += 1
            except FileNotFoundError:
                pass
    return n
