// The viewer's measurement tools (issue 35). "Measure" in the bar opens the measurement panel:
// its tools draw regions on either eye's picture and keep them as the console's regions
// (PUT /api/regions): "Spot" (a click), "Polygon" (clicks at the corners; a double click, a
// click on the first corner or Enter closes it, Escape drops it), "Box → region" (the spot
// meter's box, viewer-spot.js), "Line" (a drag: the corrected temperatures along it,
// GET /api/profile, plotted at the picture's bottom right); "Lock span" fixes the palette's
// span at the one shown (POST /api/thermal/span-lock; "Unlock span": automatic again);
// "Snapshot" downloads GET /api/snapshot (a ZIP); "Clear regions" removes the regions no
// alarm watches. The panel's forms (object parameters, each region's name and surface, the
// difference, alarms) are viewer-measure-panel.js's.
//
// Each region is outlined on its eye with its name and corrected maximum and mean, and its
// hottest and coldest pixels marked (red +, blue −) (GET
// /api/measurements: object temperatures, emissivity, reflection and the air by each
// pixel's TOF distance), red while one of its alarms is raised; a banner over the picture
// names the raised alarms (GET /api/alarms); the difference of two regions (the first two,
// or the panel's choice: GET /api/measurements/delta) sits at the bottom left. Readings come
// twice a second.
//
// window.trifuseMeasure: the state (regions, readings, alarms, the tool, the draft polygon,
// drawn), call (a REST call: the answer, or an Error saying the server's one line),
// addRegion, poll, redraw, onPoll (functions called after each poll) and the wording of
// temperatures and alarm rules, for the panel and the tests.
"use strict";
(() => {
  const frameBox = document.getElementById("frame");
  const bar = document.getElementById("bar");
  const K0 = 273.15;
  const POLL_MS = 500;
  const CLOSE_PX = 12;  // a click this near (CSS px) a polygon's first corner closes it

  const state = { regions: [], readings: null, rules: [], active: [], events: [], drawn: 0,
    error: null, tool: null, draft: null, line: null, profile: null, delta: null,
    deltaPair: null, open: false };
  const onPoll = [];

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

  // -- the panel and its tools ----------------------------------------------------------

  const panel = document.createElement("section");
  panel.id = "measure-panel";
  panel.setAttribute("aria-label", "Measurements");
  panel.hidden = true;
  document.body.appendChild(panel);
  const toggle = document.createElement("button");
  toggle.id = "measure-toggle";
  toggle.textContent = "Measure";
  toggle.title = "measurement regions, object parameters, alarms, span lock and snapshots";
  toggle.setAttribute("aria-expanded", "false");
  bar.insertBefore(toggle, bar.firstChild);
  toggle.onclick = () => {
    state.open = panel.hidden;
    panel.style.top = `${Math.round(bar.getBoundingClientRect().bottom) + 6}px`;  // under the bar
    panel.hidden = !state.open;
    toggle.setAttribute("aria-expanded", String(state.open));
    if (!state.open) setTool(null);
  };

  const tools = document.createElement("div");
  tools.className = "tools";
  panel.appendChild(tools);
  const hint = document.createElement("p");
  hint.id = "measure-hint";
  hint.setAttribute("aria-live", "polite");
  panel.appendChild(hint);
  function button(id, text, title) {
    const b = document.createElement("button");
    b.id = id; b.textContent = text; b.title = title;
    tools.appendChild(b);
    return b;
  }
  const toolButtons = {
    spot: button("measure-spot", "Spot", "click a point of either eye: a spot region"),
    polygon: button("measure-polygon", "Polygon",
      "click the corners on one eye; double-click, click the first corner or press Enter " +
      "to close it; Escape drops it"),
    line: button("measure-line", "Line",
      "drag over one eye: the temperatures along the line (a profile plot)"),
  };
  const keepButton = button("measure-keep", "Box → region",
    "keep the spot meter's box (drag over the picture) as a measurement region");
  const lockButton = button("measure-span-lock", "Lock span",
    "fix the palette's span at the one shown now (colours keep their temperatures); " +
    "again: automatic span");
  const snapButton = button("measure-snapshot", "Snapshot",
    "download the picture: the fused pair, each eye's temperatures (16-bit PNG, " +
    "centi-kelvin), the parameters and the regions' readings (ZIP)");
  const clearButton = button("measure-clear", "Clear regions",
    "remove the measurement regions (those an alarm watches stay)");
  const HINTS = {
    spot: "Click a point: a spot region.",
    polygon: "Click the corners; double-click, click the first corner or press Enter to " +
      "close; Escape drops it.",
    line: "Drag over one eye: the temperatures along the line.",
  };

  function setTool(tool) {
    state.tool = tool;
    state.draft = null;
    for (const [name, b] of Object.entries(toolButtons)) {
      b.setAttribute("aria-pressed", String(name === tool));
    }
    layer.style.pointerEvents = tool ? "auto" : "none";
    layer.style.cursor = tool ? "crosshair" : "";
    if (tool !== "line") { state.line = null; state.profile = null; plot.style.display = "none"; }
    say(null);
    redraw();
  }
  for (const [name, b] of Object.entries(toolButtons)) {
    b.onclick = () => setTool(state.tool === name ? null : name);
  }

  // What the tool expects, or what went wrong (one line, in red).
  function say(error) {
    state.error = error;
    hint.textContent = error || (state.tool ? HINTS[state.tool] : "");
    hint.classList.toggle("error", !!error);
  }

  // An alarm rule as the operator reads it (°C; a rise in K/s), and its key in the
  // console's list of active alarms ("<region> <kind> <threshold, 6 digits>").
  const celsius = (k) => (k === null || k === undefined ? "—" : (k - K0).toFixed(1));
  const ruleText = (r) => `${r.region} ${r.kind === "above" ? "max above"
    : r.kind === "below" ? "min below" : "rising faster than"} ` +
    (r.kind === "rise" ? `${r.threshold} K/s` : `${celsius(r.threshold)} °C`);
  const ruleKey = (r) => `${r.region} ${r.kind} ${+r.threshold.toPrecision(6)}`;

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

  // Keep a region drawn here as the console's, named "<shape> N" (the first N free).
  async function addRegion(shape, eye, points) {
    const names = new Set(state.regions.map((r) => r.name));
    let n = 1;
    while (names.has(`${shape} ${n}`)) n += 1;
    const region = { name: `${shape} ${n}`, eye, shape, points };
    try {
      state.regions = await call("PUT", "/api/regions", [...state.regions, region]);
      say(null);
      poll();
      return region.name;
    } catch (e) { say(String(e.message || e)); return null; }
  }

  keepButton.onclick = async () => {
    const spot = window.trifuseSpot && window.trifuseSpot.state;
    const box = spot && spot.box;
    if (!box) { say("draw a box first (drag over the picture)"); return; }
    if (await addRegion("box", box.eye, [[box.x0, box.y0], [box.x1, box.y1]])) {
      window.trifuseSpot.clear();
    }
  };
  clearButton.onclick = async () => {
    try {
      const watched = new Set((await call("GET", "/api/alarms")).rules.map((a) => a.region));
      state.regions = await call("PUT", "/api/regions",
        state.regions.filter((r) => watched.has(r.name)));
      state.readings = null;
      say(null);
      poll();
    } catch (e) { say(String(e.message || e)); }
  };
  lockButton.onclick = async () => {
    const m = window.trifuseStats && window.trifuseStats.meta;
    try {
      if (m && m.span_auto === false) await call("PUT", "/api/thermal", { span_k: null });
      else await call("POST", "/api/thermal/span-lock");
      say(null);
    } catch (e) { say(String(e.message || e)); }
  };
  setInterval(() => {  // the button says what a click does
    const m = window.trifuseStats && window.trifuseStats.meta;
    const text = m && m.span_auto === false ? "Unlock span" : "Lock span";
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

  // -- drawing on the picture: spots, polygons, a line ----------------------------------

  const plot = document.createElement("canvas");
  plot.id = "profile-plot";
  plot.width = 420; plot.height = 150;
  Object.assign(plot.style, {
    position: "absolute", right: "8px", bottom: "8px", width: "420px", height: "150px",
    background: "rgba(0,0,0,.7)", borderRadius: "4px", display: "none", pointerEvents: "none",
  });
  frameBox.appendChild(plot);

  const size = () => {
    const s = window.trifuseSpot && window.trifuseSpot.state;
    return s ? [s.colorW, s.colorH] : [1280, 960];
  };
  // The colour pixel of an eye (that of the pointer's half, or ``eye``: clamped to it).
  const toPixel = (ev, eye) => {
    const r = layer.getBoundingClientRect();
    const u = (ev.clientX - r.left) / r.width, v = (ev.clientY - r.top) / r.height;
    const e = eye || (u < 0.5 ? "left" : "right");
    const [cw, ch] = size();
    const within = Math.min(1, Math.max(0, (e === "left" ? u : u - 0.5) * 2));
    return { eye: e, x: Math.min(cw - 1, Math.floor(within * cw)),
      y: Math.min(ch - 1, Math.max(0, Math.floor(v * ch))) };
  };
  // CSS pixels between two colour pixels of one eye.
  const cssApart = (a, b) => {
    const r = layer.getBoundingClientRect(), [cw, ch] = size();
    return Math.hypot((a[0] - b[0]) * r.width / 2 / cw, (a[1] - b[1]) * r.height / ch);
  };

  async function closePolygon() {
    const d = state.draft;
    if (!d) return;
    const pts = d.points.filter((p, i) => i === 0 || p[0] !== d.points[i - 1][0]
      || p[1] !== d.points[i - 1][1]);  // a double click's second corner is the first's twin
    if (pts.length < 3) { say("a polygon takes 3 corners or more"); return; }
    state.draft = null;
    redraw();
    await addRegion("polygon", d.eye, pts);
  }

  layer.addEventListener("pointerdown", (ev) => {
    if (!state.tool) return;
    ev.preventDefault();
    if (state.tool === "spot") {
      const p = toPixel(ev);
      addRegion("spot", p.eye, [[p.x, p.y]]);
    } else if (state.tool === "polygon") {
      const d = state.draft;
      const p = toPixel(ev, d && d.eye);
      if (!d) state.draft = { eye: p.eye, points: [[p.x, p.y]], hover: null };
      else if (d.points.length >= 3 && cssApart(d.points[0], [p.x, p.y]) <= CLOSE_PX) {
        closePolygon();
      } else d.points.push([p.x, p.y]);
    } else {
      const p = toPixel(ev);
      state.line = { eye: p.eye, x0: p.x, y0: p.y, x1: p.x, y1: p.y, dragging: true };
      layer.setPointerCapture(ev.pointerId);
    }
    redraw();
  });
  layer.addEventListener("dblclick", (ev) => {
    if (state.tool === "polygon") { ev.preventDefault(); closePolygon(); }
  });
  layer.addEventListener("pointermove", (ev) => {
    const d = state.draft, l = state.line;
    if (state.tool === "polygon" && d) {
      const p = toPixel(ev, d.eye);
      d.hover = [p.x, p.y];
      redraw();
    } else if (l && l.dragging) {
      const p = toPixel(ev, l.eye);
      l.x1 = p.x; l.y1 = p.y;
      redraw();
    }
  });
  layer.addEventListener("pointerup", async () => {
    const l = state.line;
    if (state.tool !== "line" || !l || !l.dragging) return;
    l.dragging = false;
    try {
      const q = new URLSearchParams({ eye: l.eye, x0: l.x0, y0: l.y0, x1: l.x1, y1: l.y1 });
      state.profile = await call("GET", `/api/profile?${q}`);
      say(null);
    } catch (e) { say(String(e.message || e)); }
    drawPlot();
    redraw();
  });
  document.addEventListener("keydown", (ev) => {
    if (state.tool !== "polygon" || !state.draft) return;
    if (ev.key === "Enter") { ev.preventDefault(); closePolygon(); }
    if (ev.key === "Escape") { state.draft = null; say(null); redraw(); }
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

  // -- readings -------------------------------------------------------------------------

  let inFlight = false;
  async function poll() {
    if (inFlight) return;
    inFlight = true;
    try {
      state.regions = await call("GET", "/api/regions");
      const alarms = await call("GET", "/api/alarms");
      state.rules = alarms.rules;
      state.active = alarms.active;
      state.events = alarms.events.slice(-5);
      state.readings = state.regions.length ? await call("GET", "/api/measurements") : null;
      const names = state.regions.map((r) => r.name), pair = state.deltaPair;
      const chosen = pair && names.includes(pair.a) && names.includes(pair.b);
      const q = chosen ? `?${new URLSearchParams(pair)}` : "";
      state.delta = chosen || names.length > 1
        ? await call("GET", `/api/measurements/delta${q}`).catch(() => null) : null;
    } catch (e) {
      say(String(e.message || e));
    } finally {
      inFlight = false;
    }
    redraw();
    for (const f of onPoll) f(state);
  }
  setInterval(poll, POLL_MS);

  // -- the overlay ----------------------------------------------------------------------

  function label(text, x, y, font, colour) {
    g.font = `600 ${font}px system-ui, sans-serif`;
    const tw = g.measureText(text).width + 0.6 * font;
    g.fillStyle = "rgba(0,0,0,.6)";
    g.fillRect(x, y, tw, 1.4 * font);
    g.fillStyle = colour;
    g.fillText(text, x + 0.3 * font, y + 1.05 * font);
  }

  // A region's hottest (a plus) or coldest (a minus) pixel: a small ring with the sign.
  function marker([x, y], font, colour, hot) {
    const r = font * 0.45;
    g.save();
    g.lineWidth = Math.max(1.5, font / 8);
    g.strokeStyle = "#000";
    g.fillStyle = colour;
    g.beginPath(); g.arc(x, y, r, 0, 2 * Math.PI); g.fill(); g.stroke();
    g.strokeStyle = "#fff";
    g.beginPath(); g.moveTo(x - r * 0.6, y); g.lineTo(x + r * 0.6, y);
    if (hot) { g.moveTo(x, y - r * 0.6); g.lineTo(x, y + r * 0.6); }
    g.stroke();
    g.restore();
  }

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
    g.lineWidth = Math.max(2, font / 6);
    for (const r of state.regions) {
      const alarm = raised.has(r.name);
      g.strokeStyle = alarm ? "#ff2020" : "#40e0ff";
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
      if (o && o.max_at && r.shape !== "spot") {  // where the maximum (+) and minimum (−) are
        marker(toCanvas(r.eye, ...o.max_at), font, "#ff4040", true);
        marker(toCanvas(r.eye, ...o.min_at), font, "#40a0ff", false);
      }
      const text = `${r.name}: ` + (o && o.max_k !== null
        ? (r.shape === "spot" ? `${(o.mean_k - K0).toFixed(1)} °C`
          : `max ${(o.max_k - K0).toFixed(1)} °C, mean ${(o.mean_k - K0).toFixed(1)} °C`)
        : (state.readings && state.readings.errors[r.name]) || "no temperature");
      const x0 = Math.min(...cpts.map((p) => p[0])), y0 = Math.min(...cpts.map((p) => p[1]));
      label(text, x0, Math.max(0, y0 - 1.5 * font), font, alarm ? "#ff6060" : "#ffffff");
    }
    const d = state.draft;
    if (d) {  // the polygon being drawn, its next side to the pointer
      g.strokeStyle = "#ffe040";
      g.beginPath();
      const pts = d.hover ? [...d.points, d.hover] : d.points;
      pts.map(([x, y]) => toCanvas(d.eye, x, y))
        .forEach(([x, y], i) => (i ? g.lineTo(x, y) : g.moveTo(x, y)));
      g.stroke();
      const [fx, fy] = toCanvas(d.eye, ...d.points[0]);
      g.strokeRect(fx - font / 2, fy - font / 2, font, font);  // click here to close it
    }
    const l = state.line;
    if (l) {
      const [ax, ay] = toCanvas(l.eye, l.x0, l.y0), [bx, by] = toCanvas(l.eye, l.x1, l.y1);
      g.strokeStyle = "#ffb000";
      g.beginPath(); g.moveTo(ax, ay); g.lineTo(bx, by); g.stroke();
    }
    const dl = state.delta;
    if (dl) {  // two regions' difference, at the left eye's bottom left
      const sign = dl.delta_k >= 0 ? "+" : "−";
      label(`Δ ${dl.a} − ${dl.b}: ${sign}${Math.abs(dl.delta_k).toFixed(1)} K (${dl.stat})`,
        0.5 * font, layer.height - 2.2 * font, font, "#ffffff");
    }
    const named = new Map(state.rules.map((r) => [ruleKey(r), ruleText(r)]));
    const text = state.active.length
      ? `⚠ ALARM: ${state.active.map((k) => named.get(k) || k).join(", ")}` : "";
    banner.textContent = text;
    banner.style.display = text ? "block" : "none";
    state.drawn += 1;
  }

  window.trifuseMeasure = { state, call, addRegion, poll, redraw, say, onPoll, K0, celsius,
    ruleText, ruleKey };
  poll();
})();
