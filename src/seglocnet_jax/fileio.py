"""Files written so that a kill at any instant loses nothing: atomic writes, stale temporary
files, and an exclusive lock on a directory.

Every writer in the project goes through :func:`atomic_path` (or the ``write_*_atomic``
shorthands): the content is written to ``<stem>.tmp-<pid><ext>`` beside the target and renamed
over it, so a reader sees either the old file or the new one, never half of one. The extension
is kept last because some writers (``np.savez``) append one otherwise. A process killed before
the rename leaves its temporary file behind; :func:`clean_stale_tmp` removes those whose process
is gone.

:class:`DirLock` holds ``<dir>/.lock`` with ``fcntl.flock`` for the life of a run. The kernel drops
the lock when its holder dies (``kill -9`` included), so a stale lock is taken over by the next
process, which reports the previous holder's pid; a live holder makes a second process fail with
an error naming that pid.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import json
import os
import re
import socket

_TMP_RE = re.compile(r"\.tmp-(\d+)(\.[^/\\]*)?$")


def tmp_name(path: str | os.PathLike) -> str:
    """``dir/name.ext`` -> ``dir/name.tmp-<pid>.ext`` (the extension stays last)."""
    path = os.fspath(path)
    head, tail = os.path.split(path)
    stem, ext = os.path.splitext(tail)
    if not stem:  # dot-files such as ".lock"
        stem, ext = tail, ""
    return os.path.join(head, f"{stem}.tmp-{os.getpid()}{ext}")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yields a temporary path to write; on a clean exit it replaces ``path``, on an exception it
    is removed and ``path`` is left as it was. Creates the parent directory."""
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = tmp_name(path)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, obj, *, indent: int = 1, sort_keys: bool = True):
    write_text_atomic(path, json.dumps(obj, indent=indent, sort_keys=sort_keys) + "\n")


def discarded_path(path: str | os.PathLike) -> str:
    """A free name ``<path>.discarded-<UTC time>[-n]`` to move ``path`` aside to (what a restart
    or a new evaluation replaces is kept there, never deleted)."""
    path = os.path.abspath(os.fspath(path))
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%dT%H%M%SZ")
    dest = f"{path}.discarded-{stamp}"
    n = 1
    while os.path.exists(dest):
        dest = f"{path}.discarded-{stamp}-{n}"
        n += 1
    return dest


def pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def clean_stale_tmp(directory: str | os.PathLike, *, recursive: bool = True) -> list[str]:
    """Removes ``*.tmp-<pid>*`` files under ``directory`` whose process no longer runs (left by
    a kill before the rename); returns the removed paths. Files of live processes are kept."""
    directory = os.fspath(directory)
    removed: list[str] = []
    if not os.path.isdir(directory):
        return removed
    walker = os.walk(directory) if recursive else [(directory, [], os.listdir(directory))]
    for root, _, files in walker:
        for name in files:
            m = _TMP_RE.search(name)
            if m is None or pid_alive(int(m.group(1))):
                continue
            path = os.path.join(root, name)
            with contextlib.suppress(FileNotFoundError):
                os.remove(path)
                removed.append(path)
    return removed


class LockError(RuntimeError):
    """Another live process holds the directory; the message names its pid and host."""


class DirLock:
    """Exclusive lock on ``directory`` (the file ``<directory>/.lock``), for a run or a data root
    while it is written. Use as a context manager or call :meth:`acquire` / :meth:`release`.

    Attributes:
      previous: ``{"pid", "host", "what"}`` of a holder that died without releasing (a stale
        lock taken over), else None.
    """

    def __init__(self, directory: str | os.PathLike, what: str = "run"):
        self.directory = os.fspath(directory)
        self.path = os.path.join(self.directory, ".lock")
        self.what = what
        self.previous: dict | None = None
        self._fd: int | None = None

    def acquire(self) -> DirLock:
        os.makedirs(self.directory, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            holder = _read_holder(fd)
            os.close(fd)
            if err.errno in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise LockError(
                    f"{self.directory} is in use by another {holder.get('what', 'process')} "
                    f"(pid {holder.get('pid', '?')} on {holder.get('host', '?')}, lock file "
                    f"{self.path}); wait for it to finish or stop it, or choose another directory"
                ) from err
            raise
        holder = _read_holder(fd)
        if holder.get("pid") not in (None, os.getpid()):
            self.previous = holder  # its process died holding the lock: taken over
        os.ftruncate(fd, 0)
        os.pwrite(
            fd,
            json.dumps(
                {"pid": os.getpid(), "host": socket.gethostname(), "what": self.what}
            ).encode(),
            0,
        )
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> DirLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _read_holder(fd: int) -> dict:
    try:
        raw = os.pread(fd, 4096, 0)
        return json.loads(raw.decode()) if raw.strip() else {}
    except (OSError, ValueError):
        return {}
