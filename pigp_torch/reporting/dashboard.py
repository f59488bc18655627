r"""A live page of an online run: ``pigp optimize --dashboard``.

:class:`Dashboard` serves two URLs on 127.0.0.1 from a background thread:

* ``/`` — a static, self-contained HTML page (no external scripts) that fetches ``/state.json``
  every ``poll_ms`` milliseconds and shows the current step (``step N of M``), the last reading
  and the best so far with the objective's unit, the largest knob move with the knobs' unit, the
  run's status, two plots with numbered axes and units (the readings and the best so far against
  the evaluation; every knob's setting against the evaluation, each in its own colour, with the
  bounds), the readings against wall-clock time and the optimizer's tracked unknowns against
  time (one plot per unit), a table of the knobs' last settings and the run's notices;
* ``/state.json`` — :func:`run_state` of the run log, read afresh at every request (the log is
  the only channel between the run and the page: the optimizer is never touched).

After the run. :meth:`Dashboard.finish` writes the final state as a self-contained page next to
the run log (``<log stem>_dashboard.html``: the same page with the state embedded, no polling, no
server needed) and keeps answering for at most ``linger_s`` seconds, until an open page has
fetched the final state (then the page stops polling and names that file); then the server
stops. ``pigp optimize --dashboard`` prints the file's path. Chosen over serving on after the run:
the command returns when the run is over, and the final page outlives any server.

The server only listens on the loopback interface, answers one request at a time per thread, and
stops when :meth:`Dashboard.close` is called or, at the latest, after ``lifetime_s`` seconds.
"""

from __future__ import annotations

import json
import math
import threading
import warnings
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from pigp_torch._utils.units import display_unit
from pigp_torch.data.runlog import read_log
from pigp_torch.loop.config.schema import logged_units
from pigp_torch.reporting.dashboard_page import PAGE, page_html  # noqa: F401  (re-exported)
from pigp_torch.reporting.timeline import timeline

#: Hosts the dashboard may listen on.
LOOPBACK = ("127.0.0.1", "localhost", "::1")


def _notices(records) -> list[str]:
    """The run's events as short lines (evaluations counted from 1)."""
    out = [f"resumed at evaluation {int(s.get('first_step', 0)) + 1}" for s in records.starts[1:]]
    for r in records.discarded:
        out.append(f"reading discarded at evaluation {int(r['step']) + 1}: {r.get('reason', '')}")
    for r in records.notices:
        out.append(f"evaluation {int(r['step']) + 1}: {r.get('message', '')}")
    end = records.last_end
    if end is not None:
        reason = f": {end['reason']}" if end.get("reason") else ""
        restored = end.get("restored_to")
        if end.get("restored") is False:
            restored = f"{restored}: NOT DONE, see the run log"
        out.append(f"ended {end['status']}{reason}; knobs restored to {restored}")
    return out


def run_state(path: str | Path) -> dict:
    r"""What the page shows, from the run log at ``path``.

    Returns:
        ``{"method", "budget", "n", "status", "ended", "steps", "y", "best", "last_y", "best_y",
        "move", "move_knob", "knob_names", "x", "bounds", "objective_unit", "knob_unit",
        "knob_units", "notices"}``: readings in the unit a person reads (a beam logged in m shown in
        µm, ``objective_unit`` the unit shown), ``knob_units`` one unit per knob where the log's
        header has them, ``steps`` counted from 1, ``best`` the best reading so far at each step (by
        the header's ``maximize``, default true), ``move`` the largest knob change of the last
        evaluation (``None`` before the second), ``x`` the knob settings of every evaluation (``n x
        d``, knob units), ``bounds`` ``[lower, upper]`` lists or ``None``, ``status`` the last end
        record's status or ``"running"`` (``"waiting"`` before the log exists), ``ended`` whether
        the log has an end record, ``notices`` the run's events; ``t``, ``time_unit`` and
        ``tracked``: the readings' times and the tracked unknowns
        (:func:`~pigp_torch.reporting.timeline.timeline`).
    """
    path = Path(path)
    if not path.exists():
        return {"status": "waiting", "n": 0, "steps": [], "y": [], "best": [], "budget": None,
                "ended": False, "x": [], "notices": []}  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a line being written is skipped, read next time
        records = read_log(path)
    h = records.header
    maximize = bool(h.get("maximize", True))
    objective_unit, knob_unit = logged_units(h)
    scale, objective_unit = display_unit(objective_unit)  # a beam logged in m is shown in µm
    ys = [scale * float(r["y"]) for r in records.evaluations]
    best, b = [], None
    for y in ys:
        b = y if b is None or (y > b if maximize else y < b) else b
        best.append(b)
    move = knob = None
    if len(records.evaluations) >= 2:
        a, c = records.evaluations[-2]["x"], records.evaluations[-1]["x"]
        deltas = [abs(u - v) for u, v in zip(a, c, strict=True)]
        i = max(range(len(deltas)), key=deltas.__getitem__)
        move, knob = deltas[i], (records.knob_names[i] if records.knob_names else f"x{i}")
    budget = records.starts[-1].get("budget") if records.starts else h.get("budget")
    end = records.last_end
    return {
        "method": h.get("method"),
        "budget": budget,
        "n": len(ys),
        "status": "running" if end is None else end["status"],
        "ended": end is not None,
        "steps": list(range(1, len(ys) + 1)),
        "y": ys,
        "best": best,
        "last_y": ys[-1] if ys else None,
        "best_y": best[-1] if best else None,
        "move": move,
        "move_knob": knob,
        "knob_names": records.knob_names,
        "x": [[float(v) for v in r["x"]] for r in records.evaluations],
        "bounds": h.get("bounds"),
        "maximize": maximize,
        "objective_unit": objective_unit,
        "knob_unit": knob_unit,
        "knob_units": h.get("knob_units"),
        "notices": _notices(records),
        **timeline(records.evaluations),  # t, time_unit, tracked: the run against time
    }


def final_page_path(log: str | Path) -> Path:
    """Where the final page of the run log ``log`` goes: ``<log stem>_dashboard.html`` beside it."""
    log = Path(log)
    return log.with_name(log.stem + "_dashboard.html")


def write_final_page(log: str | Path, path: str | Path | None = None) -> Path:
    """Write the run's final state as a self-contained page (default :func:`final_page_path`)."""
    path = Path(path) if path is not None else final_page_path(log)
    state = run_state(log)
    state["final_page"] = str(path)
    path.write_text(page_html(state=state), encoding="utf-8")
    return path


class Dashboard:
    r"""The live page of one run log, served from a daemon thread (see the module docstring).

    Args:
        log: the run log (it may not exist yet: the page waits for it).
        host: a loopback address (default ``"127.0.0.1"``).
        port: TCP port (default 0: any free one; see :attr:`url`).
        poll_ms: how often the page asks for the state (default 1000 ms).
        lifetime_s: the server stops after this many seconds at the latest (default 12 h).
        on_state: called with the state before each ``/state.json`` answer (monitoring, tests).

    After the run, :meth:`finish` writes the final page and stops the server once an open page
    has the final state (bounded wait).

    Raises:
        ValueError: a host other than the loopback, a non-positive poll interval or lifetime.
        OSError: the port is taken.
    """

    def __init__(
        self,
        log: str | Path,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        poll_ms: int = 1000,
        lifetime_s: float = 12 * 3600.0,
        on_state=None,
    ) -> None:
        if host not in LOOPBACK:
            raise ValueError(f"the dashboard listens on the loopback only (127.0.0.1), not {host}")
        if int(poll_ms) < 50:
            raise ValueError(f"poll_ms must be >= 50, got {poll_ms}")
        if not (0 < float(lifetime_s) < math.inf):
            raise ValueError(f"lifetime_s must be positive and finite, got {lifetime_s}")
        self.log = Path(log)
        self.requests = 0
        #: the final page written by :meth:`finish` (``None`` before)
        self.final_page: Path | None = None
        self._final_served = threading.Event()
        page = page_html(poll_ms).encode()
        dashboard = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:  # quiet: the run prints its own lines
                pass

            def do_GET(self) -> None:
                route = self.path.split("?")[0]
                if route in ("/", "/index.html"):
                    body, kind = page, "text/html; charset=utf-8"
                elif route == "/state.json":
                    try:
                        state = run_state(dashboard.log)
                    except (OSError, ValueError) as err:
                        state = {"status": f"unreadable log: {err}", "n": 0, "y": [],
                                 "best": [], "steps": [], "budget": None}  # fmt: skip
                    dashboard.requests += 1
                    if dashboard.final_page is not None:
                        state["final_page"] = str(dashboard.final_page)
                    if on_state is not None:
                        on_state(state)
                    body, kind = json.dumps(state).encode(), "application/json"
                else:
                    self.send_error(404)
                    return
                self.send_response(200)
                self.send_header("Content-Type", kind)
                self.send_header("Cache-Control", "no-store")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)
                if route == "/state.json" and state.get("ended"):
                    dashboard._final_served.set()  # an open page has the final state

        self._server = ThreadingHTTPServer((host, int(port)), Handler)
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)
        self._thread.start()
        self._timer = threading.Timer(float(lifetime_s), self.close)
        self._timer.daemon = True
        self._timer.start()
        self._closed = False

    @property
    def url(self) -> str:
        """``http://127.0.0.1:PORT/``."""
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}/"

    def finish(self, linger_s: float = 5.0) -> Path:
        """The run has ended: write the final page (:func:`write_final_page`), then, if a page
        has been polling, keep answering until it has fetched the final state (at most
        ``linger_s`` seconds), and stop (also when the page cannot be written: the error is
        raised). Returns the final page's path."""
        try:
            self.final_page = write_final_page(self.log)
            if self.requests and not self._closed and not self._final_served.is_set():
                self._final_served.wait(timeout=max(0.0, float(linger_s)))
        finally:
            self.close()
        return self.final_page

    def close(self) -> None:
        """Stop serving (idempotent; also called by the lifetime timer)."""
        if self._closed:
            return
        self._closed = True
        self._timer.cancel()
        self._server.shutdown()
        self._server.server_close()

    def __enter__(self) -> Dashboard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
