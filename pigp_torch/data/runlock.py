r"""Exclusive locks of an online run: one run per run log and one per machine.

A :class:`RunLock` is a lock file holding a JSON description of its holder (PID, host, user,
time, what is locked), locked with ``fcntl.flock(LOCK_EX | LOCK_NB)`` for as long as the run
holds it. The kernel releases the lock when the holder exits, however it exits (SIGKILL
included), so a lock file left behind by a dead run is *stale*: the next run takes the lock
and reports the stale holder (:attr:`RunLock.stale`). A lock held by a live run is refused at
once with :class:`LockHeld`, naming the holder.

Two kinds of keys (:func:`log_lock`, :func:`machine_locks`):

* the run log: ``<log>.lock`` next to the log, so two processes never write one log;
* the machine: one lock file per PV prefix (the part of a PV name before its first ``:``) in
  the lock folder, so two runs whose PVs share any prefix (a knob, or the objective's
  ``SPEAR:``) cannot run at once, whatever their run logs. The lock folder is ``lock_dir``,
  else ``$PIGP_LOCK_DIR``, else ``<tmp>/pigp-locks`` (created world-writable with the sticky
  bit, so several operators on one host share it). Runs on *different* hosts see each other only
  when the folder is on a shared file system that supports ``flock`` (NFSv4, or a local
  folder of the control-room host).

POSIX only (``fcntl``).
"""

from __future__ import annotations

import contextlib
import getpass
import hashlib
import json
import os
import socket
import tempfile
from collections.abc import Iterable
from pathlib import Path

#: Environment variable naming the folder of the machine locks.
LOCK_DIR_ENV = "PIGP_LOCK_DIR"


class LockHeld(RuntimeError):
    """Another live process holds the lock (the message names it and the lock file).

    Attributes:
        holder: the holder's description (``pid``, ``host``, ``user``, ``time``, ``what``), or
            an empty dict when it could not be read.
        path: the lock file.
    """

    def __init__(self, message: str, holder: dict, path: Path) -> None:
        super().__init__(message)
        self.holder = holder
        self.path = path


def _read_holder(fd: int) -> dict:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = os.read(fd, 65536)
        holder = json.loads(data.decode("utf-8")) if data.strip() else {}
        return holder if isinstance(holder, dict) else {}
    except (OSError, ValueError):
        return {}


def _pid_alive(pid) -> bool:
    try:
        os.kill(int(pid), 0)
    except (ProcessLookupError, ValueError, TypeError):
        return False
    except PermissionError:  # exists, another user's
        return True
    return True


def describe(holder: dict) -> str:
    """``"PID 123 (user) on host since TIME"`` for a holder description."""
    if not holder:
        return "an unknown process"
    user = f" ({holder['user']})" if holder.get("user") else ""
    return f"PID {holder.get('pid')}{user} on {holder.get('host')} since {holder.get('time')}"


class RunLock:
    r"""An exclusive, non-blocking lock file (see the module docstring).

    Args:
        path: the lock file (created if missing; its folder too).
        what: what it protects, for messages (e.g. ``"run log runs/a.jsonl"``).

    Attributes:
        path: the lock file.
        what: as given.
        stale: after :meth:`acquire`, the description of a dead previous holder whose lock file
            was left behind (``None`` if there was none).
    """

    def __init__(self, path: str | Path, what: str) -> None:
        self.path = Path(path)
        self.what = str(what)
        self.stale: dict | None = None
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self, attempts: int = 5) -> RunLock:
        r"""Take the lock now or raise; returns ``self``.

        A holder that unlinks the file while this process opens it is handled by re-opening
        (``attempts`` times at most).

        Raises:
            LockHeld: a live process holds it.
            OSError: the lock file cannot be created or opened.
        """
        import fcntl

        if self._fd is not None:
            return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(int(attempts)):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except PermissionError:  # another user's lock file: locking needs read access only
                fd = os.open(self.path, os.O_RDONLY)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_holder(fd)
                os.close(fd)
                raise LockHeld(
                    f"{self.what} is in use by {describe(holder)} (lock file {self.path}); "
                    "stop that run first, or wait until it ends",
                    holder,
                    self.path,
                ) from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:  # the previous holder removed the file meanwhile: lock the new one
                os.close(fd)
                continue
            previous = _read_holder(fd)
            self.stale = previous or None
            if previous and previous.get("host") == socket.gethostname():
                self.stale = {**previous, "alive": _pid_alive(previous.get("pid"))}
            me = {
                "pid": os.getpid(),
                "host": socket.gethostname(),
                "user": _user(),
                "time": _now(),
                "what": self.what,
            }
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.lseek(fd, 0, os.SEEK_SET)
                os.write(fd, (json.dumps(me) + "\n").encode("utf-8"))
                os.fsync(fd)
            self._fd = fd
            return self
        raise OSError(f"could not lock {self.path}: it kept being replaced")

    def release(self) -> None:
        """Remove the lock file and release the lock (idempotent)."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            with contextlib.suppress(OSError):
                if os.fstat(fd).st_ino == os.stat(self.path).st_ino:
                    os.unlink(self.path)
        finally:
            os.close(fd)  # releases the flock

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"RunLock({str(self.path)!r}, {'held' if self.held else 'free'})"


def _user() -> str:
    try:
        return getpass.getuser()
    except Exception:  # no user name (containers)
        return ""


def _now() -> str:
    from pigp_torch._utils import utc_now  # lazily: _utils imports torch

    return utc_now()


def log_lock(log_path: str | Path) -> RunLock:
    """The lock of a run log: ``<log>.lock`` next to it (not yet acquired)."""
    path = Path(log_path)
    return RunLock(path.with_name(path.name + ".lock"), f"run log {path}")


def lock_dir(folder: str | Path | None = None) -> Path:
    """The folder of the machine locks: ``folder``, else ``$PIGP_LOCK_DIR``, else
    ``<tmp>/pigp-locks`` (created with mode 1777 if missing)."""
    if folder is not None:
        return Path(folder)
    env = os.environ.get(LOCK_DIR_ENV)
    if env:
        return Path(env)
    path = Path(tempfile.gettempdir()) / "pigp-locks"
    if not path.exists():
        path.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(OSError):
            os.chmod(path, 0o1777)
    return path


def pv_prefixes(pv_names: Iterable[str]) -> list[str]:
    """Sorted distinct prefixes (text before the first ``:``; the whole name without one)."""
    return sorted({str(n).split(":", 1)[0] for n in pv_names if str(n)})


def machine_locks(pv_names: Iterable[str], folder: str | Path | None = None) -> list[RunLock]:
    """One lock per PV prefix of ``pv_names`` in the lock folder (not yet acquired), in a fixed
    order. The file name is the prefix made safe plus a short hash of it."""
    out = []
    for prefix in pv_prefixes(pv_names):
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in prefix)[:60]
        digest = hashlib.sha256(prefix.encode("utf-8")).hexdigest()[:12]
        path = lock_dir(folder) / f"pv-{safe}-{digest}.lock"
        out.append(RunLock(path, f"machine PVs {prefix}:*"))
    return out


@contextlib.contextmanager
def holding(locks: Iterable[RunLock]):
    """Acquire every lock in order (all or none: on a refusal those taken are released), hold
    them for the block, release them after it."""
    taken: list[RunLock] = []
    try:
        for lock in locks:
            lock.acquire()
            taken.append(lock)
        yield taken
    finally:
        for lock in reversed(taken):
            lock.release()
