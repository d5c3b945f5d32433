// fog-driver's live page: a WebSocket from the daemon (snapshot, then updates), shown as numbers and plots.
// Every number arrives formatted (msg.text) so the page shows what `fog-driver watch` shows; the plots get the
// server's decimated series (one point per second of device time, one mean per minute).
"use strict";

const series = { points: [], minutes: [], restarts: null };
const layoutBase = {
  margin: { l: 56, r: 12, t: 30, b: 36 }, paper_bgcolor: "#fff", plot_bgcolor: "#fff",
  font: { size: 12 }, legend: { orientation: "h", y: -0.2 }, xaxis: { type: "date" },
};
const plotConfig = { displayModeBar: false, responsive: true, staticPlot: false };
let statusRows = null;
let bandLabel = "";  // the drift band's legend, as the server words it (plain sigma, or since the bias)
let socket = null;
let retryMs = 1000;

function setText(text) {
  document.querySelectorAll("[data-text]").forEach((el) => {
    const key = el.dataset.text;
    if (key in text && el.textContent !== text[key]) el.textContent = text[key];  // unchanged: no relayout
  });
}

// The thermometers in the server's order (msg.temperatures: top, bottom, housing, as `fog-driver watch`).
let temperatureOrder = [];

function showTemps(text) {
  const body = document.getElementById("temps");
  const names = temperatureOrder.map((n) => "temp_" + n).filter((k) => k in text);
  if (body.dataset.names !== names.join(",")) {
    body.replaceChildren(...names.map((key) => {
      const row = document.createElement("tr");
      const th = document.createElement("th");
      th.textContent = key.slice(5) + " temperature";
      const td = document.createElement("td");
      const span = document.createElement("span");
      span.dataset.text = key;
      span.id = "temp-" + key.slice(5);
      td.append(span, " degC");
      row.append(th, td);
      return row;
    }));
    body.dataset.names = names.join(",");
  }
}

function showStatus(rows, text) {
  const table = document.getElementById("status");
  if (rows && table.dataset.built !== "1") {
    table.replaceChildren(...rows.map(([key, label]) => {
      const row = document.createElement("tr");
      const th = document.createElement("th");
      th.textContent = label;
      const td = document.createElement("td");
      td.dataset.text = "status_" + key;
      td.id = "status-" + key;
      row.append(th, td);
      return row;
    }));
    table.dataset.built = "1";
  }
}

function showBanners(lines, alarm, device) {
  const box = document.getElementById("banners");
  box.replaceChildren(...lines.map((line) => {
    const div = document.createElement("div");
    div.textContent = line.text;
    div.className = line.level;
    return div;
  }));
  document.body.dataset.alarm = alarm ? "1" : "0";
  const link = document.getElementById("link");
  const up = device && device.state === "activated";
  link.className = "pill " + (up ? "ok" : "bad");
}

function merge(list, fresh) {
  const last = list.length ? list[list.length - 1].t_s : -Infinity;
  for (const p of fresh) if (p.t_s > last) list.push(p);
}

// Plots are over device time, shown as the host's UTC: the latest sample's UTC less the device seconds
// since each point (a replay faster than real time keeps its true spacing).
let anchorMs = null;

function x(list, offsetS = 0) {
  if (anchorMs === null) return list.map((p) => p.utc || null);
  return list.map((p) => new Date(anchorMs + (p.t_s + offsetS) * 1000));
}

// A plot of one point (or of points at one time or of one value) gets axes around it, a minute of time and a
// small band of values, instead of Plotly's milliseconds and a unit-wide guess.
function around(xs, ys, pad) {
  const layout = {};
  const times = xs.filter((t) => t !== null).map((t) => +new Date(t)).filter(Number.isFinite);
  if (times.length && Math.max(...times) === Math.min(...times)) {
    layout.xaxis = { type: "date", range: [new Date(times[0] - 30000), new Date(times[0] + 30000)], autorange: false };
  }
  const values = ys.filter((v) => v !== null && v !== undefined && Number.isFinite(v));
  if (values.length && Math.max(...values) === Math.min(...values)) {
    const half = Math.max(Math.abs(values[0]) * 0.05, pad);
    layout.yaxis = { range: [values[0] - half, values[0] + half], autorange: false };
  }
  return layout;
}

function drawPlots() {
  if (typeof Plotly === "undefined") return;
  const pts = series.points, mins = series.minutes;
  // The band: drift +- drift_band_dph (BAND_SIGMAS sigma, as the server computed it for each point), drawn
  // only once a point has one; a point without a sigma leaves a gap.
  const band = (sign) => pts.map((p) => (p.drift_band_dph == null || p.drift_dph == null ? null : p.drift_dph + sign * p.drift_band_dph));
  const drift = [{ x: x(pts), y: pts.map((p) => p.drift_dph), name: "drift estimate", line: { color: "#3b5ba5" } }];
  if (pts.some((p) => p.drift_band_dph != null)) {
    drift.unshift(
      { x: x(pts), y: band(-1), name: bandLabel, mode: "lines", showlegend: false, hoverinfo: "skip", line: { width: 0 } },
      { x: x(pts), y: band(1), name: bandLabel, mode: "lines", fill: "tonexty", fillcolor: "rgba(59, 91, 165, 0.18)", line: { width: 0 } },
    );
  }
  const driftBand = drift.flatMap((trace) => trace.y);
  Plotly.react("plot-drift", drift, { ...layoutBase, title: { text: "drift estimate (deg/h)" },
    ...around(x(pts), driftBand, 0.01) }, plotConfig);
  const rateAround = around(x(mins, 30), mins.flatMap((m) => [m.rate_dph, m.rate_raw_dph]), 0.1);
  Plotly.react("plot-rate", [
    { x: x(mins, 30), y: mins.map((m) => m.rate_dph), name: "compensated", mode: "lines+markers", line: { color: "#1f7a3a" } },
    { x: x(mins, 30), y: mins.map((m) => m.rate_raw_dph), name: "raw", mode: "lines+markers", line: { color: "#aaa" } },
  ], { ...layoutBase, title: { text: "rate, 1-minute means (deg/h)" },
    annotations: mins.length ? [] : [{ text: "the first mean comes after a full minute of data", showarrow: false,
      xref: "paper", yref: "paper", x: 0.5, y: 0.5 }],
    xaxis: { ...layoutBase.xaxis, ...rateAround.xaxis, visible: mins.length > 0 },
    yaxis: { ...rateAround.yaxis, visible: mins.length > 0 } }, plotConfig);
  const seen = new Set();
  pts.forEach((p) => Object.keys(p.temps_c || {}).forEach((n) => seen.add(n)));
  const names = [...temperatureOrder.filter((n) => seen.has(n)), ...[...seen].filter((n) => !temperatureOrder.includes(n)).sort()];
  const temps = names.map((n) => ({ x: x(pts), y: pts.map((p) => (p.temps_c || {})[n] ?? null), name: n }));
  Plotly.react("plot-temps", temps, { ...layoutBase, title: { text: "temperatures (degC)" },
    ...around(x(pts), temps.flatMap((trace) => trace.y), 0.05) }, plotConfig);
  document.getElementById("plot-drift").dataset.points = String(pts.length);
  document.getElementById("plot-temps").dataset.points = String(pts.length);
  document.getElementById("plot-rate").dataset.points = String(mins.length);
}

function handle(msg) {
  document.body.dataset.updates = String((Number(document.body.dataset.updates) || 0) + 1);
  if (msg.type === "snapshot" || msg.restarts !== series.restarts) {
    series.points = [];
    series.minutes = [];
    series.restarted = msg.type !== "snapshot";
    series.restarts = msg.restarts;
  }
  const before = series.points.length + series.minutes.length;
  merge(series.points, msg.points || []);
  merge(series.minutes, msg.minutes || []);
  if (msg.rows) statusRows = msg.rows;
  if (msg.temperatures && msg.temperatures.length) temperatureOrder = msg.temperatures;
  if (msg.type === "snapshot") document.getElementById("logout").hidden = !msg.login;
  const sampled = Boolean(msg.angle && msg.angle.seq !== undefined);
  // What the figures are, as the server judged them (view.page_state): live, stale (link down, no data: greyed
  // by the stylesheet) or waiting; a reader of the angles only gets no judgement.
  const state = msg.page_state || { text: sampled ? "live" : "waiting for data", level: sampled ? "ok" : "waiting" };
  pageState(state.text, state.level === "ok" ? true : state.level === "bad" ? false : null);
  document.body.dataset.stale = state.stale ? "1" : "0";
  document.getElementById("when").hidden = !sampled;
  document.getElementById("waiting").hidden = sampled;
  if (msg.text && msg.text.drift_band_label) bandLabel = "band: " + msg.text.drift_band_label;
  const utcMs = msg.angle && msg.angle.utc ? Date.parse(msg.angle.utc) : NaN;
  if (Number.isFinite(utcMs) && typeof msg.angle.t_s === "number") anchorMs = utcMs - msg.angle.t_s * 1000;
  showStatus(statusRows, msg.text);
  showTemps(msg.text);
  setText(msg.text);
  showBanners(msg.banners || [], msg.alarm, msg.device);
  document.body.dataset.seq = msg.angle && msg.angle.seq !== undefined ? String(msg.angle.seq) : "";
  if (msg.type === "snapshot" || series.restarted) {
    series.restarted = false;
    drawPlots();
  } else if (series.points.length + series.minutes.length !== before) {
    schedulePlots();
  }
}

// New points are drawn at most every PLOT_EVERY_MS: a plot of an hour gains nothing from faster redraws, and
// a redraw is the page's dearest work (an operator's laptop, or the instrument PC itself, pays for it).
const PLOT_EVERY_MS = 5000;
let plotTimer = null;
let plottedAt = 0;

function schedulePlots() {
  if (plotTimer !== null) return;
  const wait = Math.max(0, plottedAt + PLOT_EVERY_MS - Date.now());
  plotTimer = setTimeout(() => { plotTimer = null; plottedAt = Date.now(); drawPlots(); }, wait);
}

// ok: true (green), false (red), null (neither: waiting).
function pageState(text, ok) {
  const el = document.getElementById("page-state");
  if (el.textContent !== text) el.textContent = text;
  el.className = "pill" + (ok === null ? "" : ok ? " ok" : " bad");
}

function connect() {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  socket = new WebSocket(scheme + "//" + location.host + "/ws");
  socket.onopen = () => { retryMs = 1000; pageState("waiting for data", null); };
  socket.onmessage = (event) => handle(JSON.parse(event.data));
  socket.onclose = () => {
    // A session that ended (its 12 h, a new token, a log-out elsewhere) closes the socket too: log in again.
    fetch("/api/view", { method: "HEAD", cache: "no-store" })
      .then((answer) => { if (answer.status === 401) location.assign("/login"); })
      .catch(() => {});
    pageState("no connection to the daemon: retrying", false);
    document.body.dataset.stale = "1";
    const box = document.getElementById("banners");
    const div = document.createElement("div");
    div.textContent = "NO CONNECTION to the daemon's web listener: the numbers below are stale";
    div.className = "alarm";
    box.replaceChildren(div);
    document.body.dataset.alarm = "1";
    setTimeout(connect, retryMs);
    retryMs = Math.min(retryMs * 2, 10000);
  };
}

connect();
