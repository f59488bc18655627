r"""How a run ends: the loop's exceptions, signals turned into them, and the end record's status."""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager

from pigp_torch.machine.errors import MachineError


class RunAborted(RuntimeError):
    """The loop stopped a run on one of its safety rules (the objective fell below its floor)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived during a run; handled like Ctrl-C (knobs restored, then
    re-raised).

    Attributes:
        signum: the signal number (``signal.SIGTERM`` or ``signal.SIGHUP``).
    """

    def __init__(self, message: str = "", signum: int = signal.SIGTERM) -> None:
        super().__init__(message)
        self.signum = int(signum)


#: Signals that end a run like SIGTERM (where the platform has them).
_TERMINATING = tuple(s for s in (signal.SIGTERM, getattr(signal, "SIGHUP", None)) if s is not None)


class SignalGuard:
    r"""SIGTERM/SIGHUP -> :class:`Terminated` during a run; all three deferred while restoring.

    Installed for the whole of :func:`~pigp_torch.loop.optimize` (main thread only; otherwise a
    no-op), the previous handlers are put back on exit. While ``deferring`` is false, SIGTERM or
    SIGHUP raise :class:`Terminated` and SIGINT goes to the previous handler (Python's default
    raises ``KeyboardInterrupt``; an ignored SIGINT stays ignored). While ``deferring`` is true
    (the restore and the end record), signals are only recorded in ``deferred``; a second one
    raises ``KeyboardInterrupt`` — the way out of a restore that hangs. Inside :meth:`held` a
    signal
    acts only when the block ends.
    """

    SIGNALS = (signal.SIGINT, *_TERMINATING)

    def __init__(self, enabled: bool) -> None:
        self.enabled = bool(enabled) and threading.current_thread() is threading.main_thread()
        self.deferring = False
        self.deferred: list[str] = []
        self._previous: dict = {}
        self._holding = False
        self._held: list = []

    def _handler(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        if self._holding:
            self._held.append((signum, frame))
            return
        if self.deferring:
            self.deferred.append(name)
            if len(self.deferred) >= 2:
                raise KeyboardInterrupt(f"second signal ({name}) during the restore: abandoned")
            return
        self._act(signum, frame)

    def _act(self, signum, frame) -> None:
        if signum in _TERMINATING:
            raise Terminated(f"received {signal.Signals(signum).name}", signum)
        previous = self._previous.get(signum)
        if callable(previous):
            previous(signum, frame)
        elif previous != signal.SIG_IGN:
            raise KeyboardInterrupt

    @contextmanager
    def held(self):
        """Signals arriving inside the block act when it ends, so the block is never cut in two
        (used to write an evaluation to the log and to the table together)."""
        self._holding = True
        try:
            yield
        finally:
            self._holding = False
            held, self._held = self._held, []
            if held:
                self._act(*held[0])

    def __enter__(self) -> SignalGuard:
        if self.enabled:
            for s in self.SIGNALS:
                if (
                    s != signal.SIGINT
                    and s != signal.SIGTERM
                    and signal.getsignal(s) == signal.SIG_IGN
                ):
                    continue  # SIGHUP ignored on purpose (nohup): the run goes on
                self._previous[s] = signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc) -> None:
        for s, h in self._previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
        self._previous.clear()


def classify(err: BaseException) -> tuple[str, str]:
    """``(status, reason)`` of the end record for an exception that ended a run."""
    if isinstance(err, Terminated):
        return "interrupted", f"Terminated ({err})"
    if isinstance(err, KeyboardInterrupt):
        return "interrupted", f"KeyboardInterrupt (Ctrl-C / SIGINT){f': {err}' if str(err) else ''}"
    if isinstance(err, (MachineError, RunAborted)):
        return "aborted", f"{type(err).__name__}: {err}"
    return "failed", f"{type(err).__name__}: {err}"
