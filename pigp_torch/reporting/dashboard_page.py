"""The dashboard's page: one self-contained HTML document with its script (no external files).

:func:`page_html` fills in the polling period (milliseconds) and, for the final page, the
embedded run state (the JSON of :func:`pigp_torch.reporting.dashboard.run_state`).
"""

from __future__ import annotations

import json

PAGE = """<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>pigp run</title>
<style>body{font-family:sans-serif;margin:1.5em} #step{font-size:1.6em;font-weight:bold}
td{padding:0 1em 0 0} svg{border:1px solid #ccc;background:#fff;margin:0.3em 0}
#final{background:#eef6ee;padding:0.4em;display:none} .num{text-align:right}
#notices{font-family:monospace;font-size:0.9em}</style></head>
<body><h2 id="title">pigp run</h2><div id="step">waiting for the run log ...</div>
<p id="final"></p>
<table><tr><td>last reading</td><td id="last">-</td></tr>
<tr><td>best so far</td><td id="best">-</td></tr>
<tr><td>largest knob move</td><td id="move">-</td></tr>
<tr><td>status</td><td id="status">-</td></tr></table>
<svg id="plot" width="760" height="300"></svg>
<div style="display:flex;gap:1em;align-items:flex-start">
<svg id="knobs" width="760" height="260"></svg>
<table id="knobtable" style="font-size:0.85em"></table></div>
<svg id="timeplot" width="760" height="260"></svg>
<div id="tracked"></div>
<h3>notices</h3><ul id="notices"><li>none</li></ul>
<p style="color:#888">updated <span id="updates">0</span> times; steps seen:
<span id="seen"></span></p>
<script>
const POLL_MS = __POLL_MS__;
const INITIAL = __STATE__;
const COLORS = ["#1f77b4", "#aec7e8", "#ff7f0e", "#ffbb78", "#2ca02c", "#98df8a", "#d62728",
  "#ff9896", "#9467bd", "#c5b0d5", "#8c564b", "#c49c94", "#e377c2", "#f7b6d2", "#7f7f7f",
  "#c7c7c7", "#bcbd22", "#dbdb8d", "#17becf", "#9edae5"];
const DASHES = ["", "6,3", "2,2", "6,2,2,2"];
let lastN = -1, updates = 0, seen = [];
function fmt(v) { return v === null || v === undefined ? "-" : Number(v).toPrecision(6); }
function esc(t) { return String(t).replace(/[&<>"]/g, c => "&#" + c.charCodeAt(0) + ";"); }
function ticks(lo, hi, n) {
  const span = Math.max(hi - lo, 1e-12), raw = span / n;
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map(f => f * mag).find(v => v >= raw);
  const out = [];
  for (let t = Math.ceil(lo / step) * step; t <= hi + 1e-9 * span; t += step) out.push(t);
  return out;
}
function tickText(t) { return Math.abs(t) < 1e-12 ? "0" : Number(t.toPrecision(6)).toString(); }
// series: [{xs, ys, color, dash, dots}], hlines: [{y, color}]
function chart(id, series, x0, x1, y0, y1, xlabel, ylabel, hlines, legend) {
  const svg = document.getElementById(id);
  const W = +svg.getAttribute("width"), H = +svg.getAttribute("height");
  const L = 70, R = 15, T = 12, B = 42;
  if (y1 - y0 < 1e-12) { y0 -= 0.5; y1 += 0.5; }
  const pad = 0.05 * (y1 - y0); y0 -= pad; y1 += pad;
  const px = x => L + (x - x0) / Math.max(1e-12, x1 - x0) * (W - L - R);
  const py = y => H - B - (y - y0) / (y1 - y0) * (H - T - B);
  let g = '<rect x="' + L + '" y="' + T + '" width="' + (W - L - R) + '" height="' +
    (H - T - B) + '" fill="none" stroke="#444"/>';
  for (const t of ticks(x0, x1, 8)) {
    g += '<line x1="' + px(t) + '" x2="' + px(t) + '" y1="' + T + '" y2="' + (H - B) +
      '" stroke="#eee"/><text class="xtick" x="' + px(t) + '" y="' + (H - B + 14) +
      '" font-size="11" text-anchor="middle">' + tickText(t) + '</text>';
  }
  for (const t of ticks(y0, y1, 6)) {
    g += '<line x1="' + L + '" x2="' + (W - R) + '" y1="' + py(t) + '" y2="' + py(t) +
      '" stroke="#eee"/><text class="ytick" x="' + (L - 5) + '" y="' + (py(t) + 4) +
      '" font-size="11" text-anchor="end">' + tickText(t) + '</text>';
  }
  for (const h of hlines) {
    g += '<line x1="' + L + '" x2="' + (W - R) + '" y1="' + py(h.y) + '" y2="' + py(h.y) +
      '" stroke="' + h.color + '" stroke-dasharray="5,3"/>';
  }
  for (const s of series) {
    const pts = s.xs.map((x, i) => px(x).toFixed(1) + "," + py(s.ys[i]).toFixed(1));
    if (s.dots) {
      g += pts.map(p => '<circle r="2.5" fill="' + s.color + '" cx="' + p.split(",")[0] +
        '" cy="' + p.split(",")[1] + '"/>').join("");
    } else {
      g += '<polyline fill="none" stroke="' + s.color + '" stroke-width="1.5" ' +
        'stroke-dasharray="' + (s.dash || "") + '" points="' + pts.join(" ") + '"/>';
    }
  }
  if (legend) {
    g += '<text x="' + (L + 8) + '" y="' + (T + 16) + '" font-size="12">' + legend + '</text>';
  }
  g += '<text class="xlabel" x="' + (L + (W - L - R) / 2) + '" y="' + (H - 6) +
    '" font-size="12" text-anchor="middle">' + esc(xlabel) + '</text>';
  g += '<text class="ylabel" transform="translate(14,' + (T + (H - T - B) / 2) +
    ') rotate(-90)" font-size="12" text-anchor="middle">' + esc(ylabel) + '</text>';
  svg.innerHTML = g;
}
function draw(s) {
  if (!s.y.length) { return; }
  const yu = s.objective_unit || "", ku = s.knob_unit || "";
  const all = s.y.concat(s.best), x1 = Math.max(s.budget || s.n, 2);
  chart("plot", [{xs: s.steps, ys: s.y, color: "#1f77b4", dots: true},
                 {xs: s.steps, ys: s.best, color: "#d62728"}],
        1, x1, Math.min(...all), Math.max(...all), "evaluation", "objective (" + yu + ")", [],
        '<tspan fill="#1f77b4">&#9679; readings</tspan>   ' +
        '<tspan fill="#d62728">&#8212; best so far</tspan>');
  const names = s.knob_names || [], d = names.length;
  const xs = s.x || [], flat = [].concat(...xs);
  const lo = s.bounds ? Math.min(...s.bounds[0]) : Math.min(...flat);
  const hi = s.bounds ? Math.max(...s.bounds[1]) : Math.max(...flat);
  const series = names.map((n, i) => ({xs: s.steps, ys: xs.map(r => r[i]),
    color: COLORS[i % 20], dash: DASHES[Math.floor(i / 20) % 4]}));
  const hl = s.bounds ? [...new Set(s.bounds[0].concat(s.bounds[1]))].map(
    y => ({y: y, color: "#444"})) : [];
  chart("knobs", series, 1, x1, lo, hi, "evaluation", "knob setting (" + ku + ")", hl,
        s.bounds ? "- - - bounds" : "");
  const last = xs.length ? xs[xs.length - 1] : [];
  const per = (s.knob_units && s.knob_units.length === d) ? s.knob_units : null;
  let rows = '<tr><th></th><th>knob</th><th>last setting' + (per ? '' : ' (' + esc(ku) + ')') +
    '</th>' + (per ? '<th>unit</th>' : '') + '</tr>';
  names.forEach((n, i) => {
    rows += '<tr><td style="color:' + COLORS[i % 20] + '">&#9632;</td><td>' + esc(n) +
      '</td><td class="num">' + fmt(last[i]) + '</td>' +
      (per ? '<td>' + esc(per[i]) + '</td>' : '') + '</tr>';
  });
  document.getElementById("knobtable").innerHTML = rows;
  drawTime(s);
}
// the readings and the tracked unknowns (one plot per unit) against wall-clock time
function drawTime(s) {
  const ok = (s.t || []).map((t, i) => t !== null ? i : -1).filter(i => i >= 0);
  if (!ok.length) { return; }
  const ts = ok.map(i => s.t[i]), tu = s.time_unit || "s";
  const t1 = Math.max(ts[ts.length - 1], ts[0] + 1e-9), ys = ok.map(i => s.y[i]);
  chart("timeplot", [{xs: ts, ys: ys, color: "#1f77b4", dots: true}], ts[0], t1,
        Math.min(...ys), Math.max(...ys), "time since the first reading (" + tu + ")",
        "objective (" + (s.objective_unit || "") + ")", [],
        '<tspan fill="#1f77b4">&#9679; readings against time</tspan>');
  const groups = {};
  for (const [name, e] of Object.entries(s.tracked || {})) {
    (groups[e.unit] = groups[e.unit] || []).push(name);
  }
  const units = Object.keys(groups), box = document.getElementById("tracked");
  box.innerHTML = units.map((u, k) =>
    '<svg id="tracked' + k + '" width="760" height="220"></svg>').join("");
  units.forEach((u, k) => {
    const series = groups[u].map((name, j) => {
      const v = s.tracked[name].values, idx = ok.filter(i => v[i] !== null);
      return {xs: idx.map(i => s.t[i]), ys: idx.map(i => v[i]), color: COLORS[(2 * j) % 20],
              name: name};
    });
    const vals = [].concat(...series.map(e => e.ys));
    if (!vals.length) { return; }
    chart("tracked" + k, series, ts[0], t1, Math.min(...vals), Math.max(...vals),
          "time since the first reading (" + tu + ")", "tracked (" + u + ")", [],
          series.map(e => '<tspan fill="' + e.color + '">&#8212; ' + esc(e.name) +
                     '</tspan>').join("   "));
  });
}
function show(s) {
  const yu = s.objective_unit ? " " + s.objective_unit : "";
  const ku = s.knob_unit ? " " + s.knob_unit : "";
  document.getElementById("title").textContent = "pigp run: " + (s.method || "");
  document.getElementById("step").textContent =
    "step " + s.n + " of " + (s.budget === null ? "?" : s.budget);
  document.getElementById("last").textContent = s.last_y === null ? "-" : fmt(s.last_y) + yu;
  document.getElementById("best").textContent = s.best_y === null ? "-" : fmt(s.best_y) + yu;
  document.getElementById("move").textContent =
    s.move === null || s.move === undefined ? "-" : fmt(s.move) + ku + " (" + s.move_knob + ")";
  const notes = s.notices || [];
  document.getElementById("notices").innerHTML =
    notes.length ? notes.map(t => "<li>" + esc(t) + "</li>").join("") : "<li>none</li>";
  draw(s);
}
function ended(s) {
  const box = document.getElementById("final");
  box.style.display = "block";
  box.textContent = "The run has ended (" + s.status + "); this is its final state." +
    (s.final_page ? " Saved as " + s.final_page + " (open it any time)." : "");
}
async function poll() {
  try {
    const s = await (await fetch("state.json", {cache: "no-store"})).json();
    if (s.n !== lastN || s.ended) {
      lastN = s.n; updates += 1; seen.push(s.n);
      document.getElementById("updates").textContent = updates;
      document.getElementById("seen").textContent = seen.join(",");
      show(s);
    }
    document.getElementById("status").textContent = s.status;
    if (s.ended) { ended(s); return; }  // the final state: no more polling
  } catch (e) {
    document.getElementById("status").textContent = "no connection to the run";
  }
  setTimeout(poll, POLL_MS);
}
if (INITIAL) {
  show(INITIAL); ended(INITIAL);
  document.getElementById("updates").parentNode.style.display = "none";
  document.getElementById("status").textContent = INITIAL.status;
} else { poll(); }
</script></body></html>
"""


def page_html(poll_ms: int = 1000, state: dict | None = None) -> str:
    """The page: live (``state`` ``None``: it polls ``state.json`` every ``poll_ms``) or final
    (``state`` embedded, no polling, no server needed)."""
    embedded = "null" if state is None else json.dumps(state).replace("</", "<\\/")
    return PAGE.replace("__POLL_MS__", str(int(poll_ms))).replace("__STATE__", embedded)
