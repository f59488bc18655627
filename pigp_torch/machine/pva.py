r"""An accelerator behind EPICS 7 pvAccess: :class:`PvaMachine`, the same machine over ``p4p``.

:class:`PvaMachine` is :class:`~pigp_torch.machine.epics.EpicsMachine` with its Channel Access
client swapped for a pvAccess one (``p4p.client.thread.Context``): the same checks before a
write, the same put-and-wait and readback polling, the same timestamped, freshness-checked and
averaged readings, the same control-limit check at connection, the same disconnection counter;
see :mod:`pigp_torch.machine.epics` for the behaviour. The PVs are expected to be normative
scalars (``NTScalar``, ``value`` a double): the timestamp is ``timeStamp``, the control limits
``control.limitLow``/``limitHigh`` (else ``display.limitLow``/``limitHigh``; both 0 or missing:
none). A put that the server refuses is reported as such (a ``MachineError`` naming the PV and
the server's message), unlike caproto's CA client.

Network configuration: the ``conf`` argument (``EPICS_PVA_ADDR_LIST``, ``EPICS_PVA_AUTO_ADDR_LIST``,
...) or, without it, p4p's usual reading of the environment. Needs the optional extra
``pva`` (``pip install pigp-torch[pva]``, i.e. ``p4p``).
"""

from __future__ import annotations

import math
import threading

from pigp_torch.machine.epics import EpicsMachine
from pigp_torch.machine.errors import MachineError


class _P4pAdapter:
    """The calls :class:`EpicsMachine` needs, over pvAccess with p4p's threaded client.

    Args:
        context: a ``p4p.client.thread.Context`` to share (left open by :meth:`close`), or a
            ``dict`` of PVA configuration for a context owned by the adapter, or ``None`` (an
            owned context configured from the environment).
        timeout: default timeout (s), used by nothing but kept for the interface.
    """

    def __init__(self, context=None, timeout: float = 2.0) -> None:
        from p4p.client.thread import Context, Disconnected

        self._disconnected_type = Disconnected
        self._owns_context = context is None or isinstance(context, dict)
        if context is None:
            self.context = Context("pva")
        elif isinstance(context, dict):
            self.context = Context("pva", conf=dict(context), useenv=False)
        else:
            self.context = context
        self.disconnections = 0
        self._lock = threading.Lock()
        self._subscriptions: dict = {}
        self._connected: dict[str, bool] = {}

    def _on_update(self, name: str, value) -> None:
        """Monitor event: a value (connected) or Disconnected; a disconnection of a connected
        channel counts (p4p also reports the state before the first connection)."""
        with self._lock:
            if isinstance(value, self._disconnected_type):
                if self._connected.get(name):
                    self.disconnections += 1
                self._connected[name] = False
            elif isinstance(value, Exception):
                pass  # other monitor errors: the reads report them
            else:
                self._connected[name] = True

    def _get(self, names: list[str], timeout: float) -> list:
        """Values of ``names`` (p4p wrapped scalars) or the exceptions, one deadline."""
        return self.context.get(list(names), timeout=max(1e-3, timeout), throw=False)

    def connect(self, names: list[str], timeout: float) -> list[str]:
        """Get every PV once (that is the connection); return those not answering in time.
        Each connected PV is also monitored, to count disconnections."""
        names = list(dict.fromkeys(names))
        results = self._get(names, timeout)
        missing = [n for n, r in zip(names, results, strict=True) if isinstance(r, Exception)]
        for name in names:
            if name not in missing and name not in self._subscriptions:
                self._subscriptions[name] = self.context.monitor(
                    name, lambda v, n=name: self._on_update(n, v), notify_disconnect=True
                )
        return missing

    def read_many(self, names: list[str], timeout: float, results=None) -> list[float]:
        """Read the scalar ``value`` of each PV as a float (NaN passes through); ``results``:
        what a get of ``names`` returned already."""
        results = self._get(names, timeout) if results is None else results
        bad = [(n, r) for n, r in zip(names, results, strict=True) if isinstance(r, Exception)]
        if bad:
            detail = "; ".join(f"{n}: {type(r).__name__}: {r}" for n, r in bad)
            raise MachineError(
                f"could not read {[n for n, _ in bad]} within {timeout:.3g} s (server down or "
                f"channel disconnected): {detail}"
            )
        try:
            return [float(r) for r in results]
        except (TypeError, ValueError) as err:
            raise MachineError(f"non-numeric value read from {names}: {err}") from err

    def read_alarmed(self, names: list[str], timeout: float) -> list[tuple[float, int]]:
        """``(value, alarm.severity)`` of each scalar PV (0 ``NO_ALARM`` .. 3 ``INVALID``)."""
        results = self._get(names, timeout)
        values = self.read_many(names, timeout, results)
        return [(v, _severity(r)) for v, r in zip(values, results, strict=True)]

    def read_timed(self, name: str, timeout: float) -> tuple[float, float, int]:
        """``(value, timeStamp in UNIX seconds, alarm.severity)`` of one scalar PV."""
        (result,) = self._get([name], timeout)
        if isinstance(result, Exception):
            raise MachineError(f"could not read {name} within {timeout:.3g} s: {result}")
        try:
            return float(result), float(result.timestamp), _severity(result)
        except (TypeError, ValueError, AttributeError) as err:
            raise MachineError(f"non-numeric value read from {name}: {err}") from err

    def control_limits(self, names: list[str], timeout: float) -> list[tuple[float, float, str]]:
        """``(lower, upper, source)`` per PV: ``control`` limits, else ``display`` limits,
        else ``(nan, nan, "none")``."""
        results = self._get(names, timeout)
        out = []
        for name, r in zip(names, results, strict=True):
            if isinstance(r, Exception):
                raise MachineError(f"could not read the limits of {name}: {r}")
            limits = (math.nan, math.nan, "none")
            for field, src in (("control", "control.limitLow/High"), ("display", "display")):
                try:
                    sub = r.raw[field]
                    lo, hi = float(sub["limitLow"]), float(sub["limitHigh"])
                except (KeyError, AttributeError, TypeError, ValueError):
                    continue
                if lo < hi and not (lo == 0.0 and hi == 0.0):
                    limits = (lo, hi, src)
                    break
            out.append(limits)
        return out

    def write_many(
        self, names: list[str], values: list[float], timeout: float, on_ack=None
    ) -> None:
        """Put ``values`` to ``names`` (all sent at once) and wait for every completion;
        ``on_ack(i)`` (if given) for each put that completed."""
        results = self.context.put(
            list(names), [float(v) for v in values], timeout=max(1e-3, timeout), wait=True,
            throw=False,
        )  # fmt: skip
        if on_ack is not None:
            for i, r in enumerate(results):
                if not isinstance(r, Exception):
                    on_ack(i)
        bad = [(n, r) for n, r in zip(names, results, strict=True) if isinstance(r, Exception)]
        if bad:
            detail = "; ".join(f"{n}: {type(r).__name__}: {r}" for n, r in bad)
            raise MachineError(f"puts to {[n for n, _ in bad]} failed within {timeout:.3g} s: "
                               f"{detail}")  # fmt: skip

    def close(self) -> None:
        """Stop the monitors; close the context if this adapter created it (idempotent)."""
        for sub in self._subscriptions.values():
            sub.close()
        self._subscriptions = {}
        if self._owns_context and self.context is not None:
            self.context.close()
        self.context = None


def _severity(result) -> int:
    """The ``alarm.severity`` of a p4p scalar (0 where the PV carries no alarm)."""
    severity = getattr(result, "severity", None)
    return 0 if severity is None else int(severity)


class PvaMachine(EpicsMachine):
    r"""Knobs and objective of a machine over EPICS 7 pvAccess (see the module docstring).

    Takes the arguments of :class:`~pigp_torch.machine.epics.EpicsMachine`, except that
    ``context`` is a ``p4p.client.thread.Context`` to share, or a dict of PVA configuration
    (``{"EPICS_PVA_ADDR_LIST": "127.0.0.1:5076", "EPICS_PVA_AUTO_ADDR_LIST": "NO"}``) for a
    context of its own, or ``None`` (configured from the environment).

    Raises:
        ImportError: p4p is not installed (the ``pva`` extra).
        ValueError, MachineError: as :class:`~pigp_torch.machine.epics.EpicsMachine`.
    """

    _adapter_class = _P4pAdapter

    def __repr__(self) -> str:
        return super().__repr__().replace("EpicsMachine(", "PvaMachine(", 1)
