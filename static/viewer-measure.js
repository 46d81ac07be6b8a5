// The viewer's measurement regions and alarms (issue 35): each region of GET /api/regions
// outlined on its eye's picture with its name and corrected maximum (GET /api/measurements,
// object temperatures: emissivity, reflection and the air by each pixel's TOF distance), in
// red while one of its alarms is raised; a banner over the picture names the raised alarms
// (GET /api/alarms). "Box → region" keeps the spot meter's box (viewer-spot.js) as a region
// of the console (PUT /api/regions), named "box N"; "Clear regions" removes the regions no
// alarm watches; "Snapshot" downloads GET /api/snapshot (a ZIP); "Lock span" fixes the
// palette's span at the one shown (POST /api/thermal/span-lock; "Unlock span": automatic
// again); "Line", then a drag over one eye: the corrected temperatures along the line
// (GET /api/profile) plotted at the picture's bottom right; with two regions or more, the
// first two's difference of means (GET /api/measurements/delta) at the bottom left.
// Readings come twice a second while there are regions.
//
// window.trifuseMeasure: the state (regions, readings, active alarms, drawn) for the tests.
"use strict";
(() => {
  const frameBox = document.getElementById("frame");
  const bar = document.getElementById("bar");
  const K0 = 273.15;
  const POLL_MS = 500;

  const state = { regions: [], readings: null, active: [], events: [], drawn: 0, error: null,
    lineMode: false, line: null, profile: null, delta: null };

  const layer = document.createElement("canvas");
  layer.id = "measure-overlay";
  Object.assign(layer.style, {
    position: "absolute", left: "0", top: "0", width: "100%", height: "100%",
    pointerEvents: "none",
  });
  frameBox.appendChild(layer);
  const g = layer.getContext("2d");

  const banner = document.createElement("div");
  banner.id = "alarm-banner";
  banner.setAttribute("role", "alert");
  Object.assign(banner.style, {
    position: "absolute", left: "50%", top: "8px", transform: "translateX(-50%)",
    padding: "4px 12px", borderRadius: "4px", background: "rgba(200,0,0,.85)",
    color: "#fff", fontWeight: "600", display: "none", pointerEvents: "none",
  });
  frameBox.appendChild(banner);

  function button(id, text, title) {
    const b = document.createElement("button");
    b.id = id; b.textContent = text; b.title = title;
    bar.insertBefore(b, bar.firstChild);
    return b;
  }
  const keepButton = button("measure-keep", "Box → region",
    "keep the spot meter's box as a measurement region (read with the object parameters)");
  const clearButton = button("measure-clear", "Clear regions",
    "remove the measurement regions (those an alarm watches stay)");
  const snapButton = button("measure-snapshot", "Snapshot",
    "download the picture: the fused pair, each eye's temperatures (16-bit PNG, " +
    "centi-kelvin), the parameters and the regions' readings (ZIP)");
  const lockButton = button("measure-span-lock", "Lock span",
    "fix the palette's span at the one shown now (colours keep their temperatures); " +
    "again: automatic span");
  lockButton.onclick = async () => {
    const m = window.trifuseStats && window.trifuseStats.meta;
    try {
      if (m && m.span_auto === false) await call("PUT", "/api/thermal", { span_k: null });
      else await call("POST", "/api/thermal/span-lock");
      state.error = null;
    } catch (e) { state.error = String(e.message || e); }
  };
  setInterval(() => {  // the button says what a click does
    const m = window.trifuseStats && window.trifuseStats.meta;
    const locked = !!(m && m.span_auto === false);
    const text = locked ? "Unlock span" : "Lock span";
    if (lockButton.textContent !== text) lockButton.textContent = text;
  }, POLL_MS);
  snapButton.onclick = () => {
    const a = document.createElement("a");
    a.href = "/api/snapshot";
    a.download = "";
    document.body.appendChild(a);
    a.click();
    a.remove();
  };

  async function call(method, path, body) {
    const r = await fetch(path, {
      method, headers: body === undefined ? {} : { "content-type": "application/json" },
      body: body === undefined ? undefined : JSON.stringify(body),
    });
    const answer = await r.json().catch(() => ({}));
    if (!r.ok) {
      const d = answer.detail;
      throw new Error(typeof d === "string" ? d : (d && d[0] && d[0].msg) || `HTTP ${r.status}`);
    }
    return answer;
  }

  keepButton.onclick = async () => {
    const spot = window.trifuseSpot && window.trifuseSpot.state;
    const box = spot && spot.box;
    if (!box) { state.error = "draw a box first (drag over the picture)"; return; }
    const names = new Set(state.regions.map((r) => r.name));
    let n = 1;
    while (names.has(`box ${n}`)) n += 1;
    const region = { name: `box ${n}`, eye: box.eye, shape: "box",
      points: [[box.x0, box.y0], [box.x1, box.y1]] };
    try {
      state.regions = await call("PUT", "/api/regions", [...state.regions, region]);
      state.error = null;
      window.trifuseSpot.clear();
      poll();
    } catch (e) { state.error = String(e.message || e); }
  };
  clearButton.onclick = async () => {
    const watched = new Set(((await call("GET", "/api/alarms").catch(() => ({}))).rules || [])
      .map((a) => a.region));
    try {
      state.regions = await call("PUT", "/api/regions",
        state.regions.filter((r) => watched.has(r.name)));
      state.readings = null;
      state.error = null;
      redraw();
    } catch (e) { state.error = String(e.message || e); }
  };

  // -- a line profile: "Line", then drag over one eye; GET /api/profile, a plot under it ----

  const lineButton = button("measure-line", "Line",
    "draw a line over the picture for the temperatures along it (a profile plot)");
  const plot = document.createElement("canvas");
  plot.id = "profile-plot";
  plot.width = 420; plot.height = 150;
  Object.assign(plot.style, {
    position: "absolute", right: "8px", bottom: "8px", width: "420px", height: "150px",
    background: "rgba(0,0,0,.7)", borderRadius: "4px", display: "none", pointerEvents: "none",
  });
  frameBox.appendChild(plot);
  lineButton.onclick = () => {
    state.lineMode = !state.lineMode;
    lineButton.setAttribute("aria-pressed", String(state.lineMode));
    layer.style.pointerEvents = state.lineMode ? "auto" : "none";
    layer.style.cursor = state.lineMode ? "crosshair" : "";
    if (!state.lineMode) { state.line = null; state.profile = null; plot.style.display = "none"; }
    redraw();
  };
  const toPixel = (ev, eye) => {
    const r = layer.getBoundingClientRect();
    const u = (ev.clientX - r.left) / r.width, v = (ev.clientY - r.top) / r.height;
    const e = eye || (u < 0.5 ? "left" : "right");
    const [cw, ch] = size();
    const within = Math.min(1, Math.max(0, (e === "left" ? u : u - 0.5) * 2));
    return { eye: e, x: Math.min(cw - 1, Math.floor(within * cw)),
      y: Math.min(ch - 1, Math.max(0, Math.floor(v * ch))) };
  };
  layer.addEventListener("pointerdown", (ev) => {
    if (!state.lineMode) return;
    const p = toPixel(ev);
    state.line = { eye: p.eye, x0: p.x, y0: p.y, x1: p.x, y1: p.y, dragging: true };
    layer.setPointerCapture(ev.pointerId);
    ev.preventDefault();
  });
  layer.addEventListener("pointermove", (ev) => {
    const l = state.line;
    if (!l || !l.dragging) return;
    const p = toPixel(ev, l.eye);
    l.x1 = p.x; l.y1 = p.y;
    redraw();
  });
  layer.addEventListener("pointerup", async () => {
    const l = state.line;
    if (!l || !l.dragging) return;
    l.dragging = false;
    try {
      const q = new URLSearchParams({ eye: l.eye, x0: l.x0, y0: l.y0, x1: l.x1, y1: l.y1 });
      state.profile = await call("GET", `/api/profile?${q}`);
      state.error = null;
    } catch (e) { state.error = String(e.message || e); }
    drawPlot();
    redraw();
  });

  // The profile's object temperatures (°C) against the distance along the line (px).
  function drawPlot() {
    const p = state.profile;
    const pg = plot.getContext("2d");
    pg.clearRect(0, 0, plot.width, plot.height);
    const ys = p ? p.object_k.filter((v) => v !== null) : [];
    if (!ys.length) { plot.style.display = p ? "block" : "none"; return; }
    plot.style.display = "block";
    const lo = Math.min(...ys), hi = Math.max(...ys), span = Math.max(hi - lo, 0.1);
    const x0 = 44, x1 = plot.width - 8, y0 = 8, y1 = plot.height - 22;
    const n = p.object_k.length;
    pg.strokeStyle = "#ffb000"; pg.lineWidth = 2; pg.beginPath();
    let pen = false;
    p.object_k.forEach((v, i) => {
      if (v === null) { pen = false; return; }
      const x = x0 + (x1 - x0) * i / Math.max(1, n - 1), y = y1 - (y1 - y0) * (v - lo) / span;
      if (pen) pg.lineTo(x, y); else pg.moveTo(x, y);
      pen = true;
    });
    pg.stroke();
    pg.fillStyle = "#fff"; pg.font = "12px system-ui, sans-serif";
    pg.fillText(`${(hi - K0).toFixed(1)} °C`, 2, y0 + 10);
    pg.fillText(`${(lo - K0).toFixed(1)} °C`, 2, y1);
    pg.fillText(`0 px`, x0, plot.height - 6);
    pg.fillText(`${p.distance_px[n - 1].toFixed(0)} px along the line`, x1 - 130, plot.height - 6);
  }

  let inFlight = false;
  async function poll() {
    if (inFlight) return;
    inFlight = true;
    try {
      state.regions = await call("GET", "/api/regions");
      const alarms = await call("GET", "/api/alarms");
      state.active = alarms.active;
      state.events = alarms.events.slice(-5);
      state.readings = state.regions.length ? await call("GET", "/api/measurements") : null;
      state.delta = state.regions.length > 1
        ? await call("GET", "/api/measurements/delta").catch(() => null) : null;
    } catch (e) {
      state.error = String(e.message || e);
    } finally {
      inFlight = false;
    }
    redraw();
  }
  setInterval(poll, POLL_MS);
  poll();

  const size = () => {
    const s = window.trifuseSpot && window.trifuseSpot.state;
    return s ? [s.colorW, s.colorH] : [1280, 960];
  };

  function redraw() {
    const rect = layer.getBoundingClientRect();
    const w = Math.round(rect.width * devicePixelRatio), h = Math.round(rect.height * devicePixelRatio);
    if (layer.width !== w || layer.height !== h) { layer.width = w; layer.height = h; }
    g.clearRect(0, 0, layer.width, layer.height);
    const [cw, ch] = size();
    const half = layer.width / 2;
    const toCanvas = (eye, x, y) => [(eye === "right" ? half : 0) + (x + 0.5) * half / cw,
      (y + 0.5) * layer.height / ch];
    const font = Math.max(11, Math.round(layer.height / 55));
    const readings = (state.readings && state.readings.regions) || {};
    const raised = new Set(state.active.map((k) => k.split(" ").slice(0, -2).join(" ")));
    for (const r of state.regions) {
      const alarm = raised.has(r.name);
      g.strokeStyle = alarm ? "#ff2020" : "#40e0ff";
      g.lineWidth = Math.max(2, font / 6);
      g.beginPath();
      const pts = r.shape === "box"
        ? [[r.points[0][0], r.points[0][1]], [r.points[1][0], r.points[0][1]],
          [r.points[1][0], r.points[1][1]], [r.points[0][0], r.points[1][1]]]
        : r.points;
      const cpts = pts.map(([x, y]) => toCanvas(r.eye, x, y));
      if (r.shape === "spot") {
        const [x, y] = cpts[0];
        g.arc(x, y, font * 0.6, 0, 2 * Math.PI);
      } else {
        cpts.forEach(([x, y], i) => (i ? g.lineTo(x, y) : g.moveTo(x, y)));
        g.closePath();
      }
      g.stroke();
      const m = readings[r.name];
      const o = m && m.object;
      const text = `${r.name}: ` + (o && o.max_k !== null
        ? `max ${(o.max_k - K0).toFixed(1)} °C, mean ${(o.mean_k - K0).toFixed(1)} °C`
        : (state.readings && state.readings.errors[r.name]) || "no temperature");
      const x0 = Math.min(...cpts.map((p) => p[0])), y0 = Math.min(...cpts.map((p) => p[1]));
      g.font = `600 ${font}px system-ui, sans-serif`;
      const tw = g.measureText(text).width + 0.6 * font;
      const ty = Math.max(0, y0 - 1.5 * font);
      g.fillStyle = "rgba(0,0,0,.6)";
      g.fillRect(x0, ty, tw, 1.4 * font);
      g.fillStyle = alarm ? "#ff6060" : "#ffffff";
      g.fillText(text, x0 + 0.3 * font, ty + 1.05 * font);
    }
    const l = state.line;
    if (l) {
      const [ax, ay] = toCanvas(l.eye, l.x0, l.y0), [bx, by] = toCanvas(l.eye, l.x1, l.y1);
      g.strokeStyle = "#ffb000";
      g.lineWidth = Math.max(2, font / 6);
      g.beginPath(); g.moveTo(ax, ay); g.lineTo(bx, by); g.stroke();
    }
    const d = state.delta;
    if (d) {  // the first two regions' means, at the left eye's bottom left
      const sign = d.delta_k >= 0 ? "+" : "−";
      const dt = `Δ ${d.a} − ${d.b}: ${sign}${Math.abs(d.delta_k).toFixed(1)} K (mean)`;
      g.font = `600 ${font}px system-ui, sans-serif`;
      const tw = g.measureText(dt).width + 0.6 * font;
      g.fillStyle = "rgba(0,0,0,.6)";
      g.fillRect(0.5 * font, layer.height - 2.2 * font, tw, 1.4 * font);
      g.fillStyle = "#ffffff";
      g.fillText(dt, 0.8 * font, layer.height - 1.15 * font);
    }
    const text = state.active.length ? `⚠ ALARM: ${state.active.join(", ")}` : "";
    banner.textContent = text;
    banner.style.display = text ? "block" : "none";
    state.drawn += 1;
  }

  window.trifuseMeasure = { state, poll, redraw };
})();
