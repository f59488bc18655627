r"""The Channel Access client side of :class:`~pigp_torch.machine.epics.EpicsMachine`: the calls it
needs over caproto's threading client (:class:`CaprotoAdapter`), and the check of the knob
bounds against the IOC's control limits.

**Client library.** The CA calls go through caproto's threading client
(``caproto.threading.client.Context``): pure Python, installable with pip on any platform, and
the same package as the simulated IOC (:mod:`pigp_torch.simulated_epics.ioc`), so the whole EPICS
path is tested end to end over real Channel Access on the loopback interface. pyepics is the
operators' usual client but needs the ``libca`` shared library and its environment; the CA calls
are kept in the small adapter :class:`CaprotoAdapter` (connect, read many, read with timestamp,
control limits, write many, close, a disconnection counter), named by the class attribute
``EpicsMachine._adapter_class``, so that another client (pyepics; pvAccess:
:class:`pigp_torch.machine.pva.PvaMachine`) plugs in without touching :class:`EpicsMachine`.
A put the IOC refuses (``ECA_PUTFAIL``: a value outside its control limits DRVL/DRVH, a record
that rejects it) comes back as an ``ErrorResponse``, which caproto's threading client drops (the
put would look like one never answered); :func:`watch_refusals` hands it to the put's callback,
so the refusal is reported as such (:class:`~pigp_torch.machine.errors.PutRefused`, naming the
PVs and the IOC's reason) at once, while the other puts of that set complete.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time

import torch

from pigp_torch.machine.errors import MachineError, PutRefused

#: Marks the put callbacks of this module: :func:`watch_refusals` answers only those.
_REFUSAL_AWARE = "_pigp_refusal_aware"


def watch_refusals(circuit_manager) -> None:
    """Let the puts of :meth:`CaprotoAdapter.write_many` on ``circuit_manager`` (a caproto
    ``VirtualCircuitManager``) hear the IOC's refusal (idempotent per circuit).

    caproto's threading client processes an ``ErrorResponse`` to a ``WriteNotifyRequest`` (the
    server's ``ECA_PUTFAIL``) without telling the request's owner. This wraps the command
    processing of the manager's ``circuit`` (caproto's protocol state machine): such a response
    whose ``ioid`` belongs to a put of ours (its callback marked :data:`_REFUSAL_AWARE`, its
    deadline not passed) is handed to that callback, as a completion would be; every command
    still goes through caproto's own processing.
    """
    circuit = circuit_manager.circuit
    if getattr(circuit, "_pigp_watching", False):
        return
    from caproto import ErrorResponse, WriteNotifyRequest

    process = circuit.process_command

    def process_command(command):
        if isinstance(command, ErrorResponse):
            request = command.original_request
            info = None
            if request.command == WriteNotifyRequest.ID:
                info = circuit_manager.ioids.get(request.parameter2)  # a put's ioid
            callback = None if info is None else info.get("callback")
            if getattr(callback, _REFUSAL_AWARE, False):
                circuit_manager.ioids.pop(request.parameter2, None)
                deadline = info.get("deadline")
                if deadline is None or time.monotonic() <= deadline:
                    callback(command)
        return process(command)

    circuit.process_command = process_command
    circuit._pigp_watching = True


class CaprotoAdapter:
    """The Channel Access calls :class:`EpicsMachine` needs, over caproto's threading client.

    Every method raises :class:`MachineError` (with the PV names concerned) on a timeout, a
    disconnection or an error response; none blocks longer than the timeout it is given.

    Args:
        context: a ``caproto.threading.client.Context`` to share (left open by :meth:`close`);
            ``None`` creates one owned by the adapter.
        timeout: default CA timeout of the created context (s).
    """

    def __init__(self, context=None, timeout: float = 2.0) -> None:
        from caproto import CaprotoError
        from caproto.threading.client import Context

        self._errors = (CaprotoError, OSError, TimeoutError, ValueError, KeyError)
        self._owns_context = context is None
        self.context = Context(timeout=timeout) if context is None else context
        self._pvs: dict = {}
        #: Channel disconnections seen (connection-state callbacks), all PVs together.
        self.disconnections = 0
        self._lock = threading.Lock()

    def _on_state(self, pv, state) -> None:
        if state == "disconnected":
            with self._lock:
                self.disconnections += 1

    def connect(self, names: list[str], timeout: float) -> list[str]:
        """Connect to ``names``; return those not connected within ``timeout`` (s)."""
        new = [n for n in dict.fromkeys(names) if n not in self._pvs]
        if new:
            for name, pv in zip(new, self.context.get_pvs(*new, timeout=timeout), strict=True):
                self._pvs[name] = pv
                pv.connection_state_callback.add_callback(self._on_state, run=False)
        deadline = time.monotonic() + timeout
        missing = []
        for name in names:
            try:
                self._pvs[name].wait_for_connection(timeout=max(0.0, deadline - time.monotonic()))
            except self._errors:
                missing.append(name)
        return missing

    def _wait_all(self, names: list[str], start, what: str, timeout: float) -> list:
        """Call ``start(i, pv, callback, t)`` for every name, then wait for all the callbacks.

        All requests are sent before waiting, so the group shares one deadline ``timeout`` s
        away and slow operations (a put completion that waits for a power supply) overlap.
        """
        results: list = [None] * len(names)
        pending = set(range(len(names)))
        lock = threading.Lock()
        done = threading.Event()

        def callback(i, response):
            with lock:
                results[i] = response
                pending.discard(i)
                if not pending:
                    done.set()

        deadline = time.monotonic() + timeout
        for i, name in enumerate(names):
            remaining = max(1e-3, deadline - time.monotonic())
            try:
                start(i, self._pvs[name], lambda r, i=i: callback(i, r), remaining)
            except self._errors as err:
                raise MachineError(f"could not {what} {name}: {err}") from err
        if not done.wait(max(0.0, deadline - time.monotonic())):
            with lock:
                late = [names[i] for i in sorted(pending)]
            raise MachineError(
                f"no answer to {what} {late} within {timeout:.3g} s "
                "(IOC down or channel disconnected; a refusal is reported as such)"
            )
        return results

    def read_many(self, names: list[str], timeout: float) -> list[float]:
        """Read the scalar value of each PV as a float (NaN passes through); one deadline.

        The reads are sequential blocking reads: a read costs one round trip, less than
        dispatching parallel replies through caproto's callback thread.
        """
        return [value for value, _ in self._read_each(names, timeout, None)]

    def read_alarmed(self, names: list[str], timeout: float) -> list[tuple[float, int]]:
        """``(value, alarm severity)`` of each scalar PV (DBR_TIME reads; severity 0
        ``NO_ALARM`` .. 3 ``INVALID``); one deadline, as :meth:`read_many`."""
        return self._read_each(names, timeout, "TIME_DOUBLE")

    def _read_each(self, names: list[str], timeout: float, data_type) -> list[tuple[float, int]]:
        from caproto import ChannelType

        kind = {} if data_type is None else {"data_type": getattr(ChannelType, data_type)}
        deadline = time.monotonic() + timeout
        out = []
        for k, name in enumerate(names):
            remaining = deadline - time.monotonic()
            try:
                if remaining <= 0:
                    raise TimeoutError(f"{timeout:.3g} s used up")
                response = self._pvs[name].read(timeout=remaining, **kind)
                severity = int(response.metadata.severity) if kind else 0
                out.append((float(response.data[0]), severity))
            except self._errors as err:
                raise MachineError(
                    f"could not read {names[k:]} within {timeout:.3g} s "
                    f"(IOC down or channel disconnected): {type(err).__name__}: {err}"
                ) from err
            except (TypeError, IndexError, AttributeError) as err:
                raise MachineError(f"non-numeric value read from {name}: {err}") from err
        return out

    def read_timed(self, name: str, timeout: float) -> tuple[float, float, int]:
        """``(value, CA timestamp in UNIX seconds, alarm severity)`` of one scalar PV (a
        DBR_TIME read; severity 0 ``NO_ALARM`` .. 3 ``INVALID``)."""
        from caproto import ChannelType

        try:
            response = self._pvs[name].read(timeout=timeout, data_type=ChannelType.TIME_DOUBLE)
            md = response.metadata
            return float(response.data[0]), float(md.timestamp), int(md.severity)
        except self._errors as err:
            raise MachineError(
                f"could not read {name} within {timeout:.3g} s "
                f"(IOC down or channel disconnected): {type(err).__name__}: {err}"
            ) from err
        except (TypeError, IndexError, AttributeError) as err:
            raise MachineError(f"non-numeric value read from {name}: {err}") from err

    def control_limits(self, names: list[str], timeout: float) -> list[tuple[float, float, str]]:
        """``(lower, upper, source)`` per PV: the control limits (``"DRVL/DRVH"``), else the
        display limits (``"LOPR/HOPR"``) where the control limits are unset (both 0), else
        ``(nan, nan, "none")``."""
        from caproto import ChannelType

        out = []
        for name in names:
            try:
                md = self._pvs[name].read(timeout=timeout, data_type=ChannelType.CTRL_DOUBLE)
                md = md.metadata
                lo, hi = float(md.lower_ctrl_limit), float(md.upper_ctrl_limit)
                src = "DRVL/DRVH"
                if lo == 0.0 and hi == 0.0:
                    lo, hi = float(md.lower_disp_limit), float(md.upper_disp_limit)
                    src = "LOPR/HOPR"
                if (lo == 0.0 and hi == 0.0) or not lo < hi:
                    lo, hi, src = math.nan, math.nan, "none"
            except self._errors as err:
                raise MachineError(f"could not read the limits of {name}: {err}") from err
            except (TypeError, AttributeError):  # a record type without limits
                lo, hi, src = math.nan, math.nan, "none"
            out.append((lo, hi, src))
        return out

    def write_many(
        self, names: list[str], values: list[float], timeout: float, on_ack=None
    ) -> None:
        """Write ``values`` to ``names`` in parallel and wait for every put completion;
        ``on_ack(i)`` (if given) is called for each put completed with success, as it arrives
        (also when others never complete)."""
        values = [float(v) for v in values]

        from caproto import ErrorResponse

        def start(i, pv, cb, t):
            def done(response, cb=cb, i=i):
                if on_ack is not None and response.status.success:
                    on_ack(i)
                cb(response)

            setattr(done, _REFUSAL_AWARE, True)
            pv.wait_for_connection(timeout=t)
            watch_refusals(pv.circuit_manager)
            pv.write([values[i]], wait=False, callback=done, timeout=t, notify=True)

        responses = self._wait_all(names, start, "put", timeout)
        failed = {n: r for n, r in zip(names, responses, strict=True) if not r.status.success}
        if failed:
            detail = "; ".join(
                f"{n}: {r.status.name}"
                + (f" ({_reason(r)})" if isinstance(r, ErrorResponse) and _reason(r) else "")
                for n, r in failed.items()
            )
            raise PutRefused(f"the IOC refused the put(s) to {detail}", list(failed))

    def close(self) -> None:
        """Disconnect the context if this adapter created it (idempotent), and release its
        selectors' descriptors.

        caproto's ``Context.disconnect`` stops the selector threads of the context and of its
        (own, unshared) broadcaster and joins them, but never closes their ``epoll`` objects:
        two file descriptors per context would leak in a long-lived process (a Badger
        session opening a machine per run). They are closed here once their threads ended.
        """
        if self._owns_context and self.context is not None:
            context = self.context
            broadcaster = getattr(context, "broadcaster", None)
            context.disconnect()  # waits for its threads; the broadcaster's too (last listener)
            for owner in (context, broadcaster):
                thread_owner = getattr(owner, "selector", None)
                if thread_owner is None:
                    continue
                thread = getattr(thread_owner, "thread", None)
                if thread is None or not thread.is_alive():
                    with contextlib.suppress(Exception):
                        thread_owner.selector.close()
        self.context = None
        self._pvs = {}


def _reason(response) -> str:
    """The IOC's one-line reason in an ``ErrorResponse`` (its error message, NULs removed)."""
    text = bytes(response.error_message).split(b"\0", 1)[0].decode("latin-1").strip()
    return " ".join(text.split())


def refuse_outside_control_limits(names, bounds: torch.Tensor, limits) -> None:
    """``ValueError`` listing every knob whose bounds leave its PV's control limits."""
    bad = []
    for i, (lo, hi, src) in enumerate(limits):
        if src == "none":
            continue
        b_lo, b_hi = float(bounds[0, i]), float(bounds[1, i])
        if b_lo < lo or b_hi > hi:
            bad.append(f"{names[i]}: bounds [{b_lo:g}, {b_hi:g}] outside {src} [{lo:g}, {hi:g}]")
    if bad:
        raise ValueError(
            "knob bounds outside the IOC's control limits (the IOC would refuse such puts): "
            + "; ".join(bad)
        )
