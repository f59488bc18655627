r"""A live page of an online run: ``pigp optimize --dashboard``.

:class:`Dashboard` serves two URLs on 127.0.0.1 from a background thread:

* ``/`` — a static, self-contained HTML page (no external scripts) that fetches ``/state.json``
  every ``poll_ms`` milliseconds and shows the current step (``step N of M``), the last reading,
  the best so far, the largest knob move, the run's status and a plot of the readings and the
  best so far;
* ``/state.json`` — :func:`run_state` of the run log, read afresh at every request (the log is
  the only channel between the run and the page: the optimizer is never touched).

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

from pigp_torch.runlog import read_log

#: Hosts the dashboard may listen on.
LOOPBACK = ("127.0.0.1", "localhost", "::1")


def run_state(path: str | Path) -> dict:
    r"""What the page shows, from the run log at ``path``.

    Returns:
        ``{"method", "budget", "n", "status", "steps", "y", "best", "last_y", "best_y",
        "move", "move_knob", "knob_names"}``: ``steps`` counted from 1, ``best`` the best reading
        so far at each step (by the header's ``maximize``, default true), ``move`` the largest
        knob change of the last evaluation (``None`` before the second), ``status`` the last end
        record's status or ``"running"`` (``"waiting"`` before the log exists).
    """
    path = Path(path)
    if not path.exists():
        return {"status": "waiting", "n": 0, "steps": [], "y": [], "best": [], "budget": None}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a line being written is skipped, read next time
        records = read_log(path)
    h = records.header
    maximize = bool(h.get("maximize", True))
    ys = [float(r["y"]) for r in records.evaluations]
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
        "steps": list(range(1, len(ys) + 1)),
        "y": ys,
        "best": best,
        "last_y": ys[-1] if ys else None,
        "best_y": best[-1] if best else None,
        "move": move,
        "move_knob": knob,
        "knob_names": records.knob_names,
    }


PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>pigp run</title>
<style>body{font-family:sans-serif;margin:1.5em} #step{font-size:1.6em;font-weight:bold}
td{padding:0 1em 0 0} svg{border:1px solid #ccc;background:#fff}</style></head>
<body><h2 id="title">pigp run</h2><div id="step">waiting for the run log ...</div>
<table><tr><td>last reading</td><td id="last">-</td></tr>
<tr><td>best so far</td><td id="best">-</td></tr>
<tr><td>largest knob move</td><td id="move">-</td></tr>
<tr><td>status</td><td id="status">-</td></tr></table>
<svg id="plot" width="720" height="300"></svg>
<p style="color:#888">updated <span id="updates">0</span> times; steps seen:
<span id="seen"></span></p>
<script>
const POLL_MS = __POLL_MS__;
let lastN = -1, updates = 0, seen = [];
function fmt(v) { return v === null || v === undefined ? "-" : Number(v).toPrecision(6); }
function line(xs, ys, x0, x1, y0, y1, color) {
  const W = 720, H = 300, m = 30;
  const px = x => m + (x - x0) / Math.max(1e-12, x1 - x0) * (W - 2 * m);
  const py = y => H - m - (y - y0) / Math.max(1e-12, y1 - y0) * (H - 2 * m);
  const pts = xs.map((x, i) => px(x).toFixed(1) + "," + py(ys[i]).toFixed(1)).join(" ");
  return '<polyline fill="none" stroke="' + color + '" stroke-width="1.5" points="' + pts + '"/>';
}
function draw(s) {
  const svg = document.getElementById("plot");
  if (!s.y.length) { svg.innerHTML = ""; return; }
  const all = s.y.concat(s.best), y0 = Math.min(...all), y1 = Math.max(...all);
  const x1 = Math.max(s.budget || s.n, 2);
  svg.innerHTML = line(s.steps, s.y, 1, x1, y0, y1, "#1f77b4") +
    line(s.steps, s.best, 1, x1, y0, y1, "#d62728") +
    '<text x="35" y="20" font-size="12">readings (blue), best so far (red)</text>';
}
async function poll() {
  try {
    const s = await (await fetch("state.json", {cache: "no-store"})).json();
    if (s.n !== lastN) {
      lastN = s.n; updates += 1; seen.push(s.n);
      document.getElementById("title").textContent = "pigp run: " + (s.method || "");
      document.getElementById("step").textContent =
        "step " + s.n + " of " + (s.budget === null ? "?" : s.budget);
      document.getElementById("last").textContent = fmt(s.last_y);
      document.getElementById("best").textContent = fmt(s.best_y);
      document.getElementById("move").textContent =
        s.move === null || s.move === undefined ? "-" : fmt(s.move) + " (" + s.move_knob + ")";
      document.getElementById("updates").textContent = updates;
      document.getElementById("seen").textContent = seen.join(",");
      draw(s);
    }
    document.getElementById("status").textContent = s.status;
  } catch (e) {
    document.getElementById("status").textContent = "no connection to the run";
  }
  setTimeout(poll, POLL_MS);
}
poll();
</script></body></html>
"""


class Dashboard:
    r"""The live page of one run log, served from a daemon thread (see the module docstring).

    Args:
        log: the run log (it may not exist yet: the page waits for it).
        host: a loopback address (default ``"127.0.0.1"``).
        port: TCP port (default 0: any free one; see :attr:`url`).
        poll_ms: how often the page asks for the state (default 1000 ms).
        lifetime_s: the server stops after this many seconds at the latest (default 12 h).
        on_state: called with the state before each ``/state.json`` answer (monitoring, tests).

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
        page = PAGE.replace("__POLL_MS__", str(int(poll_ms))).encode()
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
