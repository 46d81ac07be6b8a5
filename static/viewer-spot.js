// The viewer's spot meter (issue 19): click or tap a point of either eye's picture for the
// temperature there and the distance to it; drag for a box with its hottest and coldest
// point; markers that follow the picture's hot and cold spot; in WebXR, the same reading
// under the gaze (the middle of the view) or a controller's ray.
//
// Readings come from the console: GET /api/spot and /api/area (5 times a second while a
// spot or box is set; app/server/routers/spot_api.py), the hot and cold spots with every
// frame's metadata (`spots`: {hot|cold: {left|right: {x, y, temperature_k, distance_m}}}).
// All of them are in colour-camera pixels of one eye (0..W-1, 0..H-1; W x H from
// /api/rig); the picture shows the eyes side by side, left | right, scaled to the canvas.
// Markers are drawn on a canvas of their own over the picture (the picture stays as it
// came), and into the WebXR texture by drawXr() (viewer.js calls it).
//
// window.trifuseSpot: the state, clear(), and the functions the browser tests call
// (toColorPixel, xrDirToPixel, xrFrame, drawXr).
"use strict";
(() => {
  const view = document.getElementById("view");
  const frameBox = document.getElementById("frame");
  const bar = document.getElementById("bar");
  const K0 = 273.15;
  const POLL_MS = 200;
  const DRAG_PX = 6;  // a pointer moved further than this (CSS px) draws a box

  const state = {
    colorW: 1280, colorH: 960,  // an eye's colour picture (from /api/rig)
    spot: null,        // {eye, x, y}: the operator's spot
    spotReading: null, // the last /api/spot answer for it
    box: null,         // {eye, x0, y0, x1, y1}
    boxReading: null,  // the last /api/area answer
    extremes: true,    // draw the hot and cold spot markers
    drag: null,        // {eye, x0, y0, x1, y1, startX, startY, moved} while dragging
    xr: null,          // {mode: "gaze"|"controller", px: {left, right}} in a WebXR session
    xrReading: null,   // the last /api/spot answer under the XR pointer
    errors: 0,         // failed readings (shown in the readout)
    drawn: 0,          // overlay redraws (for the tests)
    labels: [],        // the overlay's labels: {text, eye, rect: [x0, y0, x1, y1]} (canvas px)
  };

  // -- the overlay canvas, the readout and the buttons ----------------------------------------

  const overlay = document.createElement("canvas");
  overlay.id = "spot-overlay";
  overlay.setAttribute("aria-label", "spot meter: click for a spot, drag for a box");
  Object.assign(overlay.style, {
    position: "absolute", left: "0", top: "0", width: "100%", height: "100%",
    cursor: "crosshair", touchAction: "none",
  });
  frameBox.appendChild(overlay);
  const g = overlay.getContext("2d");

  const readout = document.createElement("div");
  readout.id = "spot-readout";
  readout.setAttribute("role", "status");
  Object.assign(readout.style, {
    position: "absolute", left: "8px", bottom: "8px", padding: "4px 8px", whiteSpace: "pre",
    background: "rgba(0,0,0,.55)", borderRadius: "4px", pointerEvents: "none",
  });
  readout.textContent = "spot meter: click for a spot, drag for a box";
  document.body.appendChild(readout);

  // The readout at the window's bottom left: under the colour scales' row (viewer.html) when
  // it fits there, else just above the row, over the picture's corner: never on the scales.
  const scalesRow = document.getElementById("scales");
  function placeReadout() {
    const room = innerHeight - scalesRow.getBoundingClientRect().bottom;
    const bottom = room >= readout.offsetHeight + 12 ? 8
      : Math.max(8, innerHeight - frameBox.getBoundingClientRect().bottom + 8);
    if (readout.style.bottom !== `${bottom}px`) readout.style.bottom = `${bottom}px`;
  }
  const readoutPlacer = new ResizeObserver(placeReadout);
  for (const el of [readout, frameBox, scalesRow]) readoutPlacer.observe(el);
  addEventListener("resize", placeReadout);

  function button(id, text, title) {
    const b = document.createElement("button");
    b.id = id; b.textContent = text; b.title = title;
    bar.insertBefore(b, bar.firstChild);
    return b;
  }
  const clearButton = button("spot-clear", "Clear spot", "remove the spot and the box");
  const extremesButton = button("spot-extremes", "Hot/cold ✓",
    "show or hide the markers of the hottest and coldest spot of each eye");
  clearButton.onclick = () => clear();
  extremesButton.onclick = () => {
    state.extremes = !state.extremes;
    extremesButton.textContent = state.extremes ? "Hot/cold ✓" : "Hot/cold";
    extremesButton.setAttribute("aria-pressed", String(state.extremes));
    redraw();
  };
  extremesButton.setAttribute("aria-pressed", "true");

  fetch("/api/rig").then((r) => (r.ok ? r.json() : null)).then((rig) => {
    const name = rig && rig.eyes && rig.eyes.left && rig.eyes.left.color;
    const size = name && rig.sensors[name] && rig.sensors[name].image_size;
    if (size) { state.colorW = size[0]; state.colorH = size[1]; }
  }).catch(() => { /* the default head's size */ });

  // -- coordinates ------------------------------------------------------------------------------

  // The eye and colour pixel under a pointer at client (x, y), or null outside the picture.
  // `eye` forces that eye (a box stays in the eye it started in: clamped to its half).
  function toColorPixel(clientX, clientY, eye) {
    const rect = overlay.getBoundingClientRect();
    if (!rect.width || !rect.height) return null;
    const u = (clientX - rect.left) / rect.width;   // 0..1 across both eyes
    const v = (clientY - rect.top) / rect.height;
    if (!eye && (u < 0 || u >= 1 || v < 0 || v >= 1)) return null;
    const e = eye || (u < 0.5 ? "left" : "right");
    const within = (e === "left" ? u : u - 0.5) * 2;  // 0..1 across that eye
    const clamp = (a, n) => Math.min(n - 1, Math.max(0, Math.floor(a * n)));
    return { eye: e, x: clamp(within, state.colorW), y: clamp(v, state.colorH) };
  }

  // Overlay canvas coordinates of colour pixel (x, y) of `eye` (its centre).
  function toCanvas(eye, x, y) {
    const half = overlay.width / 2;
    return [(eye === "right" ? half : 0) + (x + 0.5) * half / state.colorW,
      (y + 0.5) * overlay.height / state.colorH];
  }

  // -- pointer: a click sets the spot, a drag draws a box ------------------------------------

  overlay.addEventListener("pointerdown", (ev) => {
    const p = toColorPixel(ev.clientX, ev.clientY);
    if (!p || ev.button > 0) return;
    overlay.setPointerCapture(ev.pointerId);
    state.drag = { eye: p.eye, x0: p.x, y0: p.y, x1: p.x, y1: p.y,
      startX: ev.clientX, startY: ev.clientY, moved: false };
    ev.preventDefault();
  });
  overlay.addEventListener("pointermove", (ev) => {
    const d = state.drag;
    if (!d) return;
    if (Math.hypot(ev.clientX - d.startX, ev.clientY - d.startY) > DRAG_PX) d.moved = true;
    const p = toColorPixel(ev.clientX, ev.clientY, d.eye);
    if (p) { d.x1 = p.x; d.y1 = p.y; }
    if (d.moved) redraw();
  });
  const release = (ev) => {
    const d = state.drag;
    if (!d) return;
    state.drag = null;
    if (ev.type === "pointercancel") { redraw(); return; }
    if (d.moved) setBox(d.eye, d.x0, d.y0, d.x1, d.y1);
    else setSpot(d.eye, d.x0, d.y0);
  };
  overlay.addEventListener("pointerup", release);
  overlay.addEventListener("pointercancel", release);

  function setSpot(eye, x, y) {
    state.spot = { eye, x, y };
    state.spotReading = null;
    poll();
  }

  function setBox(eye, x0, y0, x1, y1) {
    state.box = { eye, x0: Math.min(x0, x1), y0: Math.min(y0, y1),
      x1: Math.max(x0, x1), y1: Math.max(y0, y1) };
    state.boxReading = null;
    poll();
  }

  function clear() {
    state.spot = state.spotReading = state.box = state.boxReading = null;
    redraw();
  }

  // -- readings, 5 times a second ---------------------------------------------------------------

  let inFlight = false;

  async function getJson(path, params) {
    const r = await fetch(`${path}?${new URLSearchParams(params)}`);
    const body = await r.json().catch(() => ({}));
    if (!r.ok) throw new Error(typeof body.detail === "string" ? body.detail : `HTTP ${r.status}`);
    return body;
  }

  async function poll() {
    if (inFlight) return;
    inFlight = true;
    try {
      const spot = state.spot, box = state.box, xr = state.xr;
      const jobs = [];
      if (spot) {
        jobs.push(getJson("/api/spot", spot).then((a) => { if (state.spot === spot) state.spotReading = a; }));
      }
      if (box) {
        jobs.push(getJson("/api/area", box).then((a) => { if (state.box === box) state.boxReading = a; }));
      }
      const under = xr && (xr.px.left ? ["left", xr.px.left] : xr.px.right ? ["right", xr.px.right] : null);
      if (under) {
        const q = { eye: under[0], x: Math.round(under[1][0]), y: Math.round(under[1][1]) };
        jobs.push(getJson("/api/spot", q).then((a) => { state.xrReading = a; }));
      }
      const results = await Promise.allSettled(jobs);
      const failed = results.filter((r) => r.status === "rejected");
      state.errors += failed.length;
      state.lastError = failed.length ? String(failed[0].reason.message || failed[0].reason) : null;
    } finally {
      inFlight = false;
    }
    redraw();
  }
  setInterval(() => { if (state.spot || state.box || state.xr) poll(); }, POLL_MS);

  // -- text -------------------------------------------------------------------------------------

  const celsius = (k) => (k === null || k === undefined ? "–" : `${(k - K0).toFixed(1)} °C`);
  const metres = (r) => (r.distance_m !== null && r.distance_m !== undefined
    ? `${r.distance_m.toFixed(2)} m` : (r.depth === "fallback" ? "no depth" : "– m"));

  function readoutText() {
    const lines = [];
    const s = state.spot, r = state.spotReading;
    if (s) {
      lines.push(r ? `spot ${celsius(r.temperature_k)}, ${metres(r)} (${s.eye} ${s.x}, ${s.y})`
        : `spot (${s.eye} ${s.x}, ${s.y}): reading…`);
    }
    const b = state.box, a = state.boxReading;
    if (b) {
      lines.push(a && a.max ? `box max ${celsius(a.max.temperature_k)} ${metres(a.max)}, ` +
        `min ${celsius(a.min.temperature_k)} ${metres(a.min)}, mean ${celsius(a.mean_k)}`
        : a ? "box: no temperature in it" : "box: reading…");
    }
    const m = window.trifuseStats && window.trifuseStats.meta;
    const sp = m && m.spots;
    if (sp && state.extremes) {
      const e = (kind) => (sp[kind].left ? celsius(sp[kind].left.temperature_k) : "–");
      lines.push(`hot ${e("hot")}, cold ${e("cold")} (left eye)`);
    }
    if (state.lastError) lines.push(`⚠ ${state.lastError}`);
    return lines.length ? lines.join("\n") : "spot meter: click for a spot, drag for a box";
  }

  // -- drawing ---------------------------------------------------------------------------------

  // The rectangles [x0, y0, x1, y1] (canvas px) the overlay's redraw covers, while it draws:
  // the next redraw clears only them (clearing and re-compositing the whole 2560 x 960
  // overlay at every frame cost Chromium's software compositor about 3 ms a frame).
  let covered = null;
  const cover = (x0, y0, x1, y1) => { if (covered) covered.push([x0, y0, x1, y1]); };

  // Whether rectangles a and b ([x0, y0, x1, y1]) overlap or come within `pad` of each other.
  const near = (a, b, pad) =>
    a[0] < b[2] + pad && b[0] < a[2] + pad && a[1] < b[3] + pad && b[1] < a[3] + pad;

  // Where a label goes, [x0, y0, x1, y1]: the first of its places (`where(tw, th)`: top left
  // corners, the preferred first) that, kept within its eye's half of the picture (w x h),
  // meets neither a label placed before it nor a marker (`drawn`'s rectangles); else the
  // first that meets no label; else one of the first two moved down or up by a label's
  // height at a time until it meets none. A later label moves, the earlier ones keep their
  // place: labels never cover each other (nor the colour scale: it is under the picture).
  function place(ctx, text, where, eye, w, h, drawn) {
    const f = drawn.font;
    ctx.font = `600 ${f}px system-ui, sans-serif`;
    const tw = ctx.measureText(text).width + 0.8 * f, th = 1.5 * f, pad = 0.2 * f;
    const lo = eye === "right" ? w / 2 : 0, hi = lo + w / 2;
    const fit = ([x, y]) => {
      const lx = Math.max(lo, Math.min(hi - tw, x)), ly = Math.max(0, Math.min(h - th, y));
      return [lx, ly, lx + tw, ly + th];
    };
    const free = (r, rects) => rects.every((o) => !near(r, o, pad));
    const spots = where(tw, th).map(fit);
    let r = spots.find((a) => free(a, drawn.labels) && free(a, drawn.marks)) ||
      spots.find((a) => free(a, drawn.labels));
    for (let k = 1; !r && k * th < h; k += 1) {
      for (const a of spots.slice(0, 2)) {
        for (const dy of [k, -k]) {
          const m = fit([a[0], a[1] + dy * (th + pad)]);
          if (!r && free(m, drawn.labels)) r = m;
        }
      }
    }
    r = r || spots[0];
    drawn.labels.push(r);
    return r;
  }

  // A label with a dark background in rectangle r, its text `f` px high.
  function label(ctx, text, r, f, color) {
    ctx.font = `600 ${f}px system-ui, sans-serif`;
    ctx.fillStyle = "rgba(0,0,0,0.68)";
    ctx.fillRect(r[0], r[1], r[2] - r[0], r[3] - r[1]);
    cover(...r);
    ctx.fillStyle = color || "#fff";
    ctx.textAlign = "left";
    ctx.textBaseline = "middle";
    ctx.fillText(text, r[0] + 0.4 * f, (r[1] + r[3]) / 2);
  }

  // A marker's label places around its rectangle m, `g` off it: above it on the right, above
  // on the left, below on the right, below on the left, on its right, on its left.
  const around = (m, g) => (tw, th) => [
    [m[2] + g, m[1] - g - th], [m[0] - g - tw, m[1] - g - th],
    [m[2] + g, m[3] + g], [m[0] - g - tw, m[3] + g],
    [m[2] + g, (m[1] + m[3] - th) / 2], [m[0] - g - tw, (m[1] + m[3] - th) / 2],
  ];

  // A crosshair on (x, y); its rectangle.
  function crosshair(ctx, x, y, w) {
    const q = w / 100, r = 0.9 * q;
    const rect = [x - 1.7 * r, y - 1.7 * r, x + 1.7 * r, y + 1.7 * r];
    cover(...rect);
    for (const [color, width] of [["rgba(0,0,0,0.8)", 0.35 * q], ["#fff", 0.15 * q]]) {
      ctx.strokeStyle = color;
      ctx.lineWidth = width;
      ctx.beginPath();
      ctx.arc(x, y, r, 0, 2 * Math.PI);
      for (const [dx, dy] of [[1, 0], [-1, 0], [0, 1], [0, -1]]) {
        ctx.moveTo(x + dx * 0.5 * r, y + dy * 0.5 * r);
        ctx.lineTo(x + dx * 1.7 * r, y + dy * 1.7 * r);
      }
      ctx.stroke();
    }
    return rect;
  }

  // A triangle pointing up (hot) or down (cold) with its tip at (x, y); its rectangle.
  function triangle(ctx, x, y, w, hot) {
    const q = w / 100, s = 0.9 * q, dir = hot ? 1 : -1;
    const rect = [x - s, Math.min(y, y + dir * 1.6 * s), x + s, Math.max(y, y + dir * 1.6 * s)];
    cover(...rect);
    ctx.beginPath();
    ctx.moveTo(x, y);
    ctx.lineTo(x - s, y + dir * 1.6 * s);
    ctx.lineTo(x + s, y + dir * 1.6 * s);
    ctx.closePath();
    ctx.fillStyle = hot ? "#ff3b2f" : "#2f8cff";
    ctx.fill();
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = 0.15 * q;
    ctx.stroke();
    return rect;
  }

  // Pixel (x, y) of `eye` in a context of size w x h (the page's overlay or the XR texture).
  const at = (eye, x, y, w, h) => [(eye === "right" ? w / 2 : 0) + (x + 0.5) * (w / 2) / state.colorW,
    (y + 0.5) * h / state.colorH];

  // Each eye's place of a reading: its own pixel, or where the same point is in that eye.
  function places(r) {
    if (r.eyes_px && Object.keys(r.eyes_px).length) {
      return Object.entries(r.eyes_px).filter(([, p]) => p).map(([e, p]) => [e, p[0], p[1]]);
    }
    return [[r.eye, r.x, r.y]];
  }

  // Everything the spot meter shows, into a 2D context of the side-by-side picture (w x h):
  // the markers first, then their labels (text 1 % of w high, `minFont` px at least),
  // placed so that none covers another (place()); the labels, {text, eye, rect}.
  function drawAll(ctx, w, h, withXr, minFont = 0) {
    const q = w / 100;
    // rectangles: the labels placed, the markers; the labels' text size
    const drawn = { labels: [], marks: [], font: Math.max(q, minFont) };
    const labels = [];  // [text, where (place()), eye, color], in the order they are placed
    const m = window.trifuseStats && window.trifuseStats.meta;
    if (state.extremes && m && m.spots) {
      for (const kind of ["hot", "cold"]) {
        for (const eye of ["left", "right"]) {
          const s = m.spots[kind] && m.spots[kind][eye];
          if (!s) continue;
          const [x, y] = at(eye, s.x, s.y, w, h);
          const rect = triangle(ctx, x, y, w, kind === "hot");
          drawn.marks.push(rect);
          labels.push([`${kind === "hot" ? "▲" : "▼"} ${celsius(s.temperature_k)}`,
            around(rect, 0.3 * q), eye, kind === "hot" ? "#ffb3ad" : "#b3d4ff"]);
        }
      }
    }
    const b = state.drag && state.drag.moved ? state.drag : state.box;
    if (b) {
      const [x0, y0] = at(b.eye, Math.min(b.x0, b.x1) - 0.5, Math.min(b.y0, b.y1) - 0.5, w, h);
      const [x1, y1] = at(b.eye, Math.max(b.x0, b.x1) + 0.5, Math.max(b.y0, b.y1) + 0.5, w, h);
      ctx.setLineDash([w / 200, w / 300]);
      ctx.strokeStyle = "#fff";
      ctx.lineWidth = w / 1000;
      ctx.strokeRect(x0, y0, x1 - x0, y1 - y0);
      cover(x0, y0, x1, y1);
      ctx.setLineDash([]);
      const a = b === state.box ? state.boxReading : null;
      if (a && a.max) {
        for (const [r, hot] of [[a.max, true], [a.min, false]]) {
          for (const [eye, x, y] of places(r)) {  // a dot on the pixel, in both eyes
            const [cx, cy] = at(eye, x, y, w, h);
            ctx.fillStyle = hot ? "#ff3b2f" : "#2f8cff";
            ctx.strokeStyle = "#fff";
            ctx.lineWidth = w / 1500;
            ctx.beginPath();
            ctx.arc(cx, cy, w / 350, 0, 2 * Math.PI);
            const rect = [cx - w / 350, cy - w / 350, cx + w / 350, cy + w / 350];
            cover(...rect);
            drawn.marks.push(rect);
            ctx.fill();
            ctx.stroke();
          }
        }
        // the figures beside the box: max above it (else beside its top, or in it), min below
        // it (else beside its bottom, or in it)
        const g = 0.3 * q;
        labels.push([`max ${celsius(a.max.temperature_k)}`, (tw, th) => [
          [x0, y0 - g - th], [x1 - tw, y0 - g - th], [x0 - g - tw, y0], [x1 + g, y0], [x0 + g, y0 + g],
        ], b.eye, "#ffb3ad"]);
        labels.push([`min ${celsius(a.min.temperature_k)}`, (tw, th) => [
          [x0, y1 + g], [x1 - tw, y1 + g], [x0 - g - tw, y1 - th], [x1 + g, y1 - th], [x0 + g, y1 - g - th],
        ], b.eye, "#b3d4ff"]);
      }
    }
    const s = state.spot, r = state.spotReading;
    if (s) {
      const spots = r ? places(r) : [[s.eye, s.x, s.y]];
      for (const [eye, x, y] of spots) {
        const [cx, cy] = at(eye, x, y, w, h);
        const rect = crosshair(ctx, cx, cy, w);
        drawn.marks.push(rect);
        if (r) labels.push([`${celsius(r.temperature_k)}  ${metres(r)}`, around(rect, 0.2 * q), eye]);
      }
    }
    if (withXr && state.xr) {
      const xr = state.xr, xrR = state.xrReading;
      for (const eye of ["left", "right"]) {
        const p = xr.px[eye];
        if (!p) continue;
        const [cx, cy] = at(eye, p[0], p[1], w, h);
        const rect = crosshair(ctx, cx, cy, w);
        drawn.marks.push(rect);
        if (xrR) {
          labels.push([`${celsius(xrR.temperature_k)}  ${metres(xrR)}`, around(rect, 0.2 * q), eye]);
        }
      }
    }
    return labels.map(([text, where, eye, color]) => {
      const rect = place(ctx, text, where, eye, w, h, drawn);
      label(ctx, text, rect, drawn.font, color);
      return { text, eye, rect };
    });
  }

  // The overlay's size in device pixels: as shown (the picture's 2560 x 960 while hidden).
  // Drawn at the picture's size and scaled down, it cost the browser's compositor as much
  // as a second picture at every frame.
  function shownSize() {
    const r = window.devicePixelRatio || 1;
    const w = Math.round(overlay.clientWidth * r), h = Math.round(overlay.clientHeight * r);
    return w > 0 && h > 0 ? [w, h] : [view.width, view.height];
  }

  // Everything drawAll and readoutText read: the same inputs draw the same overlay.
  function inputs() {
    const m = window.trifuseStats && window.trifuseStats.meta;
    return JSON.stringify([overlay.width, overlay.height, state.extremes && m ? m.spots : null,
      state.drag && state.drag.moved ? state.drag : null, state.box, state.boxReading,
      state.spot, state.spotReading, state.lastError]);
  }

  // The overlay again if what it shows changed: only the rectangles drawn last time are
  // cleared (strokes, miters and anti-aliasing reach out a little: cleared with a margin).
  let drawnInputs = null, drawnRects = [];
  function redraw() {
    const [w, h] = shownSize();
    if (overlay.width !== w || overlay.height !== h) {
      overlay.width = w; overlay.height = h;  // cleared
      drawnInputs = null; drawnRects = [];
    }
    const now = inputs();
    if (now === drawnInputs) return;
    const pad = overlay.width / 100;
    for (const [x0, y0, x1, y1] of drawnRects) {
      g.clearRect(x0 - pad, y0 - pad, x1 - x0 + 2 * pad, y1 - y0 + 2 * pad);
    }
    covered = [];
    try {
      // labels of 11 CSS px at least: legible in a small window
      const minFont = 11 * (window.devicePixelRatio || 1);
      state.labels = drawAll(g, overlay.width, overlay.height, false, minFont);
    } finally {
      drawnRects = covered;
      covered = null;
    }
    drawnInputs = now;
    const text = readoutText();
    if (readout.textContent !== text) readout.textContent = text;
    state.drawn += 1;
  }

  // Redraw when a new frame came (its hot and cold spots) or the overlay changed size.
  let seenFrames = -1;
  function tick() {
    const stats = window.trifuseStats;
    const n = stats ? stats.frames : 0;
    const [w, h] = shownSize();
    if (n !== seenFrames || overlay.width !== w || overlay.height !== h) {
      seenFrames = n;
      redraw();
    }
    requestAnimationFrame(tick);
  }
  requestAnimationFrame(tick);

  // -- WebXR: the gaze or a controller's ray --------------------------------------------------

  // The colour pixel [x, y] (float) that direction `dir` ([x, y, z] in a view's eye space:
  // x right, y up, -z ahead) points at in that eye's picture, which viewer.js draws across
  // the view (a picture at infinity: only the direction matters), its colour scale's strip
  // under it, `below` picture heights high (0: none), filling the view's bottom; null off
  // the picture (on the scale) or behind. `proj`: the view's 4 x 4 projection matrix,
  // column-major (XRView's).
  function xrDirToPixel(proj, dir, colorW, colorH, below = 0) {
    const [x, y, z] = dir;
    const cx = proj[0] * x + proj[4] * y + proj[8] * z;
    const cy = proj[1] * x + proj[5] * y + proj[9] * z;
    const cw = proj[3] * x + proj[7] * y + proj[11] * z;
    if (!(cw > 0)) return null;
    const nx = cx / cw, ny = cy / cw;
    if (nx < -1 || nx > 1 || ny < -1 || ny > 1) return null;
    const py = (1 - ny) / 2 * colorH * (1 + below) - 0.5;
    if (py > colorH - 0.5) return null;
    return [(nx + 1) / 2 * colorW - 0.5, py];
  }

  // Vector `v` turned by unit quaternion `q` ({x, y, z, w}, DOMPointReadOnly).
  function rotate(q, v) {
    const [x, y, z] = v;
    const tx = 2 * (q.y * z - q.z * y), ty = 2 * (q.z * x - q.x * z), tz = 2 * (q.x * y - q.y * x);
    return [x + q.w * tx + (q.y * tz - q.z * ty), y + q.w * ty + (q.z * tx - q.x * tz),
      z + q.w * tz + (q.x * ty - q.y * tx)];
  }
  const conj = (q) => ({ x: -q.x, y: -q.y, z: -q.z, w: q.w });

  // Per XR frame (viewer.js): where the pointer is in each eye's picture (`below`: the
  // scale's strip under it, xrDirToPixel). A tracked controller's ray when there is one,
  // else the gaze (the viewer's forward direction).
  const sessions = new WeakSet();  // sessions whose end clears the XR pointer

  function xrFrame(frame, pose, space, below = 0) {
    const session = frame.session;
    if (session && !sessions.has(session)) {
      sessions.add(session);
      session.addEventListener("end", () => { state.xr = state.xrReading = null; redraw(); });
    }
    let dir = null, mode = "gaze";
    for (const src of (session && session.inputSources) || []) {
      if (src.targetRayMode !== "tracked-pointer" || !src.targetRaySpace) continue;
      const p = frame.getPose(src.targetRaySpace, space);
      if (p) { dir = rotate(p.transform.orientation, [0, 0, -1]); mode = "controller"; break; }
    }
    if (!dir) dir = rotate(pose.transform.orientation, [0, 0, -1]);
    const px = { left: null, right: null };
    for (const v of pose.views) {
      const eye = v.eye === "right" ? "right" : "left";
      px[eye] = xrDirToPixel(v.projectionMatrix, rotate(conj(v.transform.orientation), dir),
        state.colorW, state.colorH, below);
    }
    state.xr = { mode, px };
    return state.xr;
  }

  // Into the WebXR texture (viewer.js, with each new picture): the markers, the spot, the
  // box and the reading under the XR pointer.
  function drawXr(ctx, w, h) {
    drawAll(ctx, w, h, true);
  }

  window.trifuseSpot = {
    state, clear, setSpot, setBox, toColorPixel, toCanvas, xrDirToPixel, xrFrame, drawXr,
    readoutText,
  };
})();
