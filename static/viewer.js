// The operator's stereo viewer: fused side-by-side frames, a colour scale under each eye (the
// metadata's palette and span; beside the picture, never over it; in the `registration` mode
// the registration σ's colour map, 0 … 2 colour pixels, with each eye's median and 95th
// percentile), an overlay of frame rates, data rate, latency, display mode and the sensors
// that are not ok (the metadata's `health`), the display mode (the "Mode" select: GET and
// PUT /api/fusion; its choices from the API's schema, /openapi.json), full screen, and WebXR.
//
// Two streams, picked with the "Stream" select (stored in localStorage; `?stream=jpeg|auto|
// 8|4|2|1` in the URL overrides it for the page; the console's default preset,
// GET /api/stream/settings, when neither says):
// - video (auto or a preset in Mbit/s): /stream.video, H.264 decoded with WebCodecs
//   (viewer-video.js); the console adapts the bitrate and picture size to the link;
// - JPEG: /stream, a JSON text message with the frame's metadata, then the JPEG as a binary
//   message, acknowledged once drawn so the server always sends the newest frame; MJPEG
//   (/stream.mjpg) when the WebSocket cannot open.
// Without WebCodecs (a plain-http page on another host, an old browser) or when the browser
// cannot decode the stream's codec, the viewer uses JPEG and says why.
//
// Frame rates, all over the same sliding window (the metadata's `rates.window_s`, 3 s):
// "received" counts the frames this browser drew; "stream" (frames the console published)
// and "new pictures" (of these, the ones fused anew rather than repeated) are the console's
// own figures, carried by each frame's metadata: the Source panel shows the same numbers.
//
// The calibration's health (GET /api/status `drift`, fetched every 2 s: whether each camera
// still sits where the rig says, app/server/runtime/drift_watch.py): one overlay line, and
// while a camera has turned against the rig an alert banner over the top of the picture.
"use strict";
const canvas = document.getElementById("view");
const ctx = canvas.getContext("2d");
// The canvas's backing store has the size the picture is shown at (CSS px x devicePixelRatio,
// never more than the picture's own), so the browser scales each frame once, as it draws it,
// and composites only the pixels shown: a 2560 x 960 store shown at half that had Chromium's
// software compositor scale 2.5 MP at every frame. `?canvas=full` in the URL (a comparison
// with the console's picture pixel for pixel) and a WebXR session (its texture) keep the
// picture's own size.
const picture = { width: canvas.width, height: canvas.height };  // the stream's picture (px)
const fullCanvas = new URLSearchParams(location.search).get("canvas") === "full";
let xrActive = false;

function canvasSize() {
  if (fullCanvas || xrActive) return [picture.width, picture.height];
  const r = window.devicePixelRatio || 1;
  const w = Math.round(canvas.clientWidth * r), h = Math.round(canvas.clientHeight * r);
  if (!(w > 0 && h > 0)) return [picture.width, picture.height];  // hidden (MJPEG)
  return [Math.min(w, picture.width), Math.min(h, picture.height)];
}

// The backing store at canvasSize(), showing what it showed (scaled) until the next frame.
function fitCanvas() {
  const [w, h] = canvasSize();
  if (canvas.width === w && canvas.height === h) return;
  const copy = document.createElement("canvas");
  copy.width = canvas.width; copy.height = canvas.height;
  copy.getContext("2d").drawImage(canvas, 0, 0);
  canvas.width = w; canvas.height = h;
  ctx.drawImage(copy, 0, 0, w, h);
}
new ResizeObserver(fitCanvas).observe(canvas);
const overlay = document.getElementById("overlay");
const pairBox = document.getElementById("pair");  // the picture and the scales' row under it
const scaleEls = [...document.querySelectorAll(".scale")];
const streamSelect = document.getElementById("stream");
const modeSelect = document.getElementById("mode");
const alertBox = document.getElementById("alert");
const stats = {
  frames: 0,        // frames drawn since the page opened
  fps: 0,           // frames drawn per second over the window ("received")
  drawTimes: [],    // performance.now() of the frames drawn within the window
  firstDraw: null,
  latencyMs: [],
  meta: null,
  lastFrameAt: null,
  rates: null,      // the console's stream rates of the newest frame
  scale: null,      // the colour scale shown (null: hidden)
  mode: "websocket",  // the transport: "websocket" or "mjpeg"
  codec: null,      // what the pictures arrive as: "H.264" or "JPEG" (null: none yet)
  mbps: 0,          // Mbit/s of the stream's binary messages over the window
  byteLog: [],      // [performance.now(), bytes] of the binary messages within the window
  bitrateBps: null, // video: the console's bitrate target for this viewer (bit/s)
  level: null,      // video: the ladder step in use ("8", "4", "2", "1")
  coded: null,      // video: the coded picture, "WxH"
  fpsTarget: null,  // video: the level's highest frame rate
  choice: null,     // the Stream select's value: "auto", "8", "4", "2", "1" or "jpeg"
  note: null,       // why the viewer shows JPEG although video was asked for
  decodeErrors: 0,  // video decoder errors (each answered by a key frame request)
  decodeMs: [],     // video: decode() to the decoded frame, ms, the newest 120 frames
  metaMode: null,   // the display mode of the newest frame's metadata
  modeError: null,  // why the Mode select's last change was refused
  drift: null,      // the status's `drift` block (the calibration's health), null: none yet
};
window.trifuseStats = stats;  // read by the browser tests and the benchmark

const DEFAULT_WINDOW_S = 3;
const MIN_SPAN_S = 0.2;

function windowS() {
  return (stats.rates && stats.rates.window_s) || DEFAULT_WINDOW_S;
}

// Frames per second over the window ending now: the console's formula (app/server/runtime/rates.py).
function receivedFps(now) {
  const w = windowS() * 1000;
  while (stats.drawTimes.length && stats.drawTimes[0] <= now - w) stats.drawTimes.shift();
  if (stats.firstDraw === null) return 0;
  return stats.drawTimes.length * 1000 / Math.min(w, Math.max(now - stats.firstDraw, MIN_SPAN_S * 1000));
}

// Every frame drawn, whatever its stream: the frame counts, latency, colour scale, overlay.
function frameDrawn(frameMeta) {
  const now = performance.now();
  stats.frames += 1;
  stats.drawTimes.push(now);
  if (stats.firstDraw === null) stats.firstDraw = now;
  stats.lastFrameAt = now;
  if (!frameMeta) return;
  stats.meta = frameMeta;
  stats.latencyMs.push(Date.now() - frameMeta.sent_ns / 1e6);
  if (stats.latencyMs.length > 120) stats.latencyMs.shift();
  const scaleBefore = stats.scale;
  showScale(scaleOf(frameMeta));
  if (frameMeta.mode !== stats.metaMode) { stats.metaMode = frameMeta.mode; syncMode(); }
  const fresh = frameMeta.rates && (!stats.rates || stats.rates.at_ns !== frameMeta.rates.at_ns);
  stats.rates = frameMeta.rates || null;
  // the console's new figures at once, as the Source panel shows them; a new stream or a new
  // scale (its legend lines) at once
  if (fresh || stats.codec !== overlayCodec || stats.scale !== scaleBefore) showOverlay();
}

function bytesReceived(n) {
  stats.byteLog.push([performance.now(), n]);
}

// Mbit/s of the binary messages over the window ending now (the same span as receivedFps).
function receivedMbps(now) {
  const w = windowS() * 1000;
  while (stats.byteLog.length && stats.byteLog[0][0] <= now - w) stats.byteLog.shift();
  if (stats.firstDraw === null) return 0;
  const bytes = stats.byteLog.reduce((sum, e) => sum + e[1], 0);
  return bytes * 8 / 1e6 / (Math.min(w, Math.max(now - stats.firstDraw, MIN_SPAN_S * 1000)) / 1000);
}

// -- the streams -----------------------------------------------------------------------------

const CHOICES = ["auto", "8", "4", "2", "1", "jpeg"];
const CHOICE_KEY = "trifuse.viewer.stream";
let current = null;  // the stream open now: {kind: "video"|"jpeg", stop(), setPreset?(p)}

function wsUrl(path) {
  return `${location.protocol === "https:" ? "wss:" : "ws:"}//${location.host}${path}`;
}

function connectJpeg() {
  const ws = new WebSocket(wsUrl("/stream"));
  ws.binaryType = "blob";
  const conn = { kind: "jpeg", stopped: false, stop() { conn.stopped = true; ws.close(); } };
  let meta = null, opened = false;
  ws.onopen = () => { opened = true; };
  ws.onmessage = async (ev) => {
    if (typeof ev.data === "string") { meta = JSON.parse(ev.data); return; }
    const frameMeta = meta;
    bytesReceived(ev.data.size);
    const bitmap = await createImageBitmap(ev.data);
    if (conn.stopped) { bitmap.close(); return; }
    if (picture.width !== bitmap.width || picture.height !== bitmap.height) {
      picture.width = bitmap.width; picture.height = bitmap.height;
      pairBox.style.setProperty("--ar", String(bitmap.width / bitmap.height));
      fitCanvas();
    }
    ctx.drawImage(bitmap, 0, 0, canvas.width, canvas.height);
    ws.send("ack");  // flow control: the server sends the newest frame after this
    bitmap.close();
    stats.codec = "JPEG";
    frameDrawn(frameMeta);
  };
  ws.onclose = () => {
    if (conn.stopped) return;
    if (!opened) { useMjpeg(); return; }
    setTimeout(() => { if (current === conn) current = connectJpeg(); }, 1000);
  };
  return conn;
}

// MJPEG (/stream.mjpg) in a plain <img>, where the WebSocket cannot open: no metadata.
function useMjpeg() {
  stats.mode = "mjpeg";
  canvas.style.display = "none";
  showScale(null);  // MJPEG carries no metadata: no span to show
  const img = document.getElementById("mjpeg");
  img.style.display = "block";
  img.src = "/stream.mjpg";
}

// Back from MJPEG to the canvas (the operator picked another stream).
function leaveMjpeg() {
  if (stats.mode !== "mjpeg") return;
  stats.mode = "websocket";
  const img = document.getElementById("mjpeg");
  img.removeAttribute("src");
  img.style.display = "none";
  canvas.style.display = "";
}

// The video stream at `preset`; JPEG instead when the browser cannot decode it.
function connectVideo(preset) {
  const conn = { kind: "video", stopped: false };
  const fallBack = (why) => {
    stats.note = why;
    if (current === conn) current = connectJpeg();
  };
  const stream = openVideoStream(preset, {
    draw(frame, meta, decodeMs) {
      // scaled to the canvas (canvasSize): a smaller level as the full picture
      ctx.drawImage(frame, 0, 0, canvas.width, canvas.height);
      stats.codec = "H.264";
      stats.note = null;
      stats.bitrateBps = meta.bitrate_bps;
      stats.level = meta.level;
      stats.fpsTarget = meta.fps_target;
      stats.coded = `${meta.width}x${meta.height}`;
      stats.decodeMs.push(decodeMs);
      if (stats.decodeMs.length > 120) stats.decodeMs.shift();
      frameDrawn(meta);
    },
    received: bytesReceived,
    decodeError() { stats.decodeErrors += 1; },
    unsupported: fallBack,
    closed(info) {
      if (conn.stopped) return;
      if (!info.opened) { fallBack("the console has no video stream"); return; }
      if (info.code === 1008 || info.code === 1011) {  // refused or failed: say why, use JPEG
        fallBack(`video stream closed: ${info.reason || info.code}`);
        return;
      }
      setTimeout(() => { if (current === conn) current = connectVideo(preset); }, 1000);
    },
  });
  conn.stop = () => { conn.stopped = true; stream.stop(); };
  conn.setPreset = (p) => { preset = p; stream.setPreset(p); };
  return conn;
}

// Open the stream `choice` names: a preset change on an open video stream is a message on
// it; a change between video and JPEG closes one stream and opens the other.
function useStream(choice) {
  stats.choice = choice;
  const video = choice !== "jpeg" && videoSupported();
  stats.note = choice !== "jpeg" && !video ? "no WebCodecs in this browser (it needs https or localhost)" : null;
  if (current && current.kind === "video" && video) { current.setPreset(choice); return; }
  if (current && current.kind === "jpeg" && !video) return;
  if (current) current.stop();
  leaveMjpeg();
  stats.bitrateBps = null; stats.level = null; stats.coded = null; stats.fpsTarget = null;
  current = video ? connectVideo(choice) : connectJpeg();
}

// The stream to open first: the URL's ?stream=, the operator's last pick, the console's
// default preset, or auto.
async function initialChoice() {
  const fromUrl = new URLSearchParams(location.search).get("stream");
  if (CHOICES.includes(fromUrl)) return fromUrl;
  const stored = localStorage.getItem(CHOICE_KEY);
  if (CHOICES.includes(stored)) return stored;
  try {
    const r = await fetch("/api/stream/settings");
    if (r.ok) {
      const body = await r.json();
      if (CHOICES.includes(body.preset)) return body.preset;
    }
  } catch (e) { /* an older console: auto */ }
  return "auto";
}

async function startStream() {
  if (!videoSupported()) {
    for (const opt of streamSelect.options) if (opt.value !== "jpeg") opt.disabled = true;
  }
  const choice = await initialChoice();
  streamSelect.value = choice;
  streamSelect.onchange = () => {
    localStorage.setItem(CHOICE_KEY, streamSelect.value);
    useStream(streamSelect.value);
  };
  useStream(choice);
}

function median(a) {
  if (!a.length) return NaN;
  const s = [...a].sort((x, y) => x - y);
  return s[Math.floor(s.length / 2)];
}

// -- the colour scale ------------------------------------------------------------------------

const K0 = 273.15;

// A round tick step giving about `target` ticks over `range`.
function niceStep(range, target) {
  const raw = range / target;
  const p = 10 ** Math.floor(Math.log10(raw));
  for (const m of [1, 2, 2.5, 5]) if (m * p >= raw) return m * p;
  return 10 * p;
}

function decimalsOf(step) {
  let d = 0;
  while (d < 3 && Math.abs(step * 10 ** d - Math.round(step * 10 ** d)) > 1e-6) d += 1;
  return d;
}

// What the scale shows for a frame's metadata, or null (no palette colour in the picture).
// Ticks: the span's ends (°C, 0.1) and, with a linear AGC, round values between them, away
// from the ends; under equalization (`agc` plateau or dde) the palette is not linear in
// temperature, so the ticks sit at evenly spaced palette positions labelled with the
// temperature there (the metadata's `palette_ticks_k`).
function scaleOf(m) {
  if (m && m.registration) return registrationScaleOf(m.registration);
  if (!m || !m.palette || !m.span_k || !m.palette_rgb || m.palette_rgb.length !== 1536) return null;
  const low = m.span_k[0] - K0, high = m.span_k[1] - K0;
  if (!(high > low)) return null;
  const ticks = [
    { frac: 1, label: high.toFixed(1), end: "high" },
    { frac: 0, label: low.toFixed(1), end: "low" },
  ];
  const agc = m.agc || "linear";
  const at = m.palette_ticks_k;
  if (agc !== "linear" && Array.isArray(at) && at.length > 2) {
    for (let i = 1; i < at.length - 1; i += 1) {
      ticks.push({ frac: i / (at.length - 1), label: (at[i] - K0).toFixed(1), end: "" });
    }
  } else {
    const step = niceStep(high - low, 5);
    const d = decimalsOf(step);
    for (let k = Math.ceil(low / step); k * step < high; k += 1) {
      const frac = (k * step - low) / (high - low);
      if (frac > 0.09 && frac < 0.91) ticks.push({ frac, label: (k * step).toFixed(d), end: "" });
    }
  }
  const side = m.span_auto ? "auto" : "manual";
  return {
    key: `${m.palette}|${agc}|${ticks.map((t) => t.label).join(",")}|${m.span_auto}|${m.mark_fallback}`,
    kind: "temperature", palette: m.palette, rgb: m.palette_rgb, lowC: low, highC: high,
    auto: !!m.span_auto, ticks, agc, marking: !!m.mark_fallback, unit: "°C", sides: [side, side],
    label: `colour scale ${m.palette}, ${ticks[1].label} to ${ticks[0].label} °C`,
  };
}

// The `registration` mode's scale (the metadata's `registration`): its colour map over the
// fixed scale `scale_px` (colour pixels, clipped above), ticks every 0.5 px, and under each
// eye its median and 95th percentile (`eyes`: null before the eye's first estimate).
function registrationScaleOf(r) {
  if (!r.colormap_rgb || r.colormap_rgb.length !== 1536 || !Array.isArray(r.scale_px)) return null;
  const [low, high] = r.scale_px;
  if (!(high > low)) return null;
  const ticks = [
    { frac: 1, label: `${high} px`, end: "high" },
    { frac: 0, label: `${low}`, end: "low" },
  ];
  for (let v = low + 0.5; v < high - 1e-9; v += 0.5) ticks.push({ frac: (v - low) / (high - low), label: `${v}`, end: "" });
  const eyes = r.eyes || {};
  const figures = (e) => (e && typeof e.median_px === "number"
    ? `median ${e.median_px.toFixed(2)} · p95 ${e.p95_px.toFixed(2)}` : (e ? "no estimate" : "computing…"));
  const sides = [figures(eyes.left), figures(eyes.right)];
  const covariance = ["left", "right"].every((k) => !eyes[k] || eyes[k].calibration_covariance);
  return {
    key: `registration|${low}|${high}|${sides.join("|")}|${covariance}`,
    kind: "registration", palette: r.colormap || "sigma", rgb: r.colormap_rgb, ticks,
    unit: "registration σ", sides, eyes, covariance, lowPx: low, highPx: high,
    label: `registration σ, colour pixels ${low} … ${high}`,
  };
}

// The palette as a 256 x 1 image, cold end at the left.
function rampCanvas(hex) {
  const c = document.createElement("canvas");
  c.width = 256; c.height = 1;
  const g = c.getContext("2d");
  const img = g.createImageData(256, 1);
  for (let i = 0; i < 256; i += 1) {
    const at = i * 6;
    for (let ch = 0; ch < 3; ch += 1) img.data[i * 4 + ch] = parseInt(hex.substr(at + 2 * ch, 2), 16);
    img.data[i * 4 + 3] = 255;
  }
  g.putImageData(img, 0, 0);
  return c;
}

// Which ticks to label on a ramp `length` long (px): both ends, and each other tick whose
// label (`widths[i]` px wide, centred on its place) keeps `gap` px from the ones kept; the
// others would collide in a small window.
function keptTicks(ticks, widths, length, gap) {
  const span = (i) => {
    const x = ticks[i].frac * length;
    return [x - widths[i] / 2 - gap / 2, x + widths[i] / 2 + gap / 2];
  };
  const kept = ticks.map((t) => !!t.end);
  const taken = ticks.map((t, i) => i).filter((i) => kept[i]).map(span);
  const inner = ticks.map((t, i) => i).filter((i) => !kept[i]).sort((a, b) => ticks[a].frac - ticks[b].frac);
  for (const i of inner) {
    const [a, b] = span(i);
    if (taken.every(([c, d]) => b <= c || d <= a)) { kept[i] = true; taken.push([a, b]); }
  }
  return kept;
}

// Hide the tick labels that would collide at the scales' size now (called again on resize).
function thinTicks() {
  const model = stats.scale;
  if (!model) return;
  for (const el of scaleEls) {
    const spans = [...el.querySelectorAll(".tick")];
    const ramp = el.querySelector(".ramp");
    if (spans.length !== model.ticks.length || !ramp) continue;
    for (const s of spans) s.classList.remove("crowded");
    const widths = spans.map((s) => s.getBoundingClientRect().width);
    const gap = parseFloat(getComputedStyle(el).fontSize) * 0.6;
    const kept = keptTicks(model.ticks, widths, ramp.getBoundingClientRect().width, gap);
    spans.forEach((s, i) => s.classList.toggle("crowded", !kept[i]));
  }
}
new ResizeObserver(thinTicks).observe(document.getElementById("scales"));

function showScale(model) {
  const key = model ? model.key : null;
  if (stats.scale && key === stats.scale.key) return;
  if (!model) {
    for (const el of scaleEls) el.hidden = true;
    pairBox.classList.add("no-scale");  // the picture takes the scales' row
    stats.scale = null;
    return;
  }
  const rampChanged = !stats.scale || stats.scale.rgb !== model.rgb;
  for (const el of scaleEls) {
    if (rampChanged || !el.firstChild) {
      el.replaceChildren();
      const ramp = rampCanvas(model.rgb);
      ramp.className = "ramp";
      const ticks = document.createElement("div");
      ticks.className = "ticks";
      const unit = document.createElement("div");
      unit.className = "caption unit";
      const mode = document.createElement("div");
      mode.className = "caption mode";
      el.append(unit, ramp, ticks, mode);
    }
    el.querySelector(".caption.unit").textContent = model.unit;
    const ticks = el.querySelector(".ticks");
    ticks.replaceChildren(...model.ticks.map((t) => {
      const s = document.createElement("span");
      s.className = t.end ? `tick end ${t.end}` : "tick";
      s.style.left = `${(100 * t.frac).toFixed(3)}%`;
      s.textContent = t.label;
      return s;
    }));
    const i = scaleEls.indexOf(el);
    el.querySelector(".caption.mode").textContent = model.sides[i];
    el.dataset.palette = model.palette;
    el.dataset.kind = model.kind;
    el.setAttribute("aria-label", model.kind === "registration" ? `${model.label}; ${model.sides[i]}` : model.label);
    el.hidden = false;
  }
  pairBox.classList.remove("no-scale");
  stats.scale = model;
  thinTicks();
}

// The scales' strip in the WebXR texture, under the picture (`w` its width): its height (px).
// Its font is 1.2 % of the picture's width, 31 px of 2560: with an eye's half (1280 px)
// over about 100 degrees of a headset's view, some 2.4 degrees, digits about 1.7 degrees
// high: legible (the page's font at its smallest, 11 px at arm's length, is about 0.4).
const xrFont = (w) => 1.2 * w / 100;
const xrStrip = (w) => Math.round(3.3 * xrFont(w));

// The same scales drawn into a 2D context (the WebXR texture) as the page shows them: under
// each eye's half of the picture (`w` x `h`), in the strip of xrStrip(w) px below it. The
// ramps' ends, [x0, x1] (px).
function drawScales(g, model, w, h, ramp) {
  const f = xrFont(w), font = (weight) => `${weight} ${f}px system-ui, sans-serif`;
  g.fillStyle = "#000";
  g.fillRect(0, h, w, xrStrip(w));
  g.font = font(600);
  const widths = model.ticks.map((t) => g.measureText(t.label).width);
  const unitW = Math.max(3 * f, g.measureText(model.unit).width);
  g.font = font(400);
  const modeW = Math.max(3 * f, ...model.sides.map((t) => g.measureText(t).width));
  const ends = [];
  for (const [eye, left] of [0, w / 2].entries()) {
    const mode = model.sides[eye];
    // the captions 0.4 f from the eye's edges and 0.6 f from the ramp (the page's padding and gap)
    const x0 = left + unitW + 1.0 * f, x1 = left + w / 2 - modeW - 1.0 * f, top = h + 0.4 * f;
    ends.push([x0, x1]);
    g.imageSmoothingEnabled = true;
    g.drawImage(ramp, x0, top, x1 - x0, 0.9 * f);
    g.strokeStyle = "rgba(255,255,255,0.85)";
    g.lineWidth = Math.max(1, 0.08 * f);
    g.strokeRect(x0, top, x1 - x0, 0.9 * f);
    g.fillStyle = "#fff";
    g.textBaseline = "middle";
    g.textAlign = "right";
    g.font = font(600);
    g.fillText(model.unit, x0 - 0.6 * f, top + 0.45 * f);
    g.textAlign = "left";
    g.font = font(400);
    g.fillText(mode, x1 + 0.6 * f, top + 0.45 * f);
    g.textAlign = "center";
    const kept = keptTicks(model.ticks, widths, x1 - x0, 0.6 * f);
    model.ticks.forEach((t, i) => {
      if (!kept[i]) return;
      const x = x0 + t.frac * (x1 - x0), y = h + 1.3 * f;
      g.fillRect(x - g.lineWidth / 2, y, g.lineWidth, 0.4 * f);
      g.font = font(t.end ? 800 : 600);
      g.fillText(t.label, x, y + 1.0 * f);
    });
  }
  return ends;
}
// for a check of the WebXR rendering on a 2D canvas
window.trifuseXrScales = { drawScales, rampCanvas, xrStrip, xrFont };

// -- the overlay -----------------------------------------------------------------------------

function ratesLine(now) {
  const r = stats.rates;
  if (stats.lastFrameAt !== null && now - stats.lastFrameAt > windowS() * 1000) {
    return `no frame for ${((now - stats.lastFrameAt) / 1000).toFixed(0)} s`;
  }
  if (!r) return "stream –";
  const repeat = r.stream_fps - r.new_fps;
  const why = repeat >= 0.05 ? " (the others repeat an unchanged picture)" : "";
  return `stream ${r.stream_fps.toFixed(1)} fps, new pictures ${r.new_fps.toFixed(1)} fps${why}`;
}

// The video stream's figures (the console's target for this viewer), or why there is none.
function videoLine() {
  if (stats.codec === "H.264" && stats.bitrateBps !== null) {
    return `video: target ${(stats.bitrateBps / 1e6).toFixed(2)} Mbit/s, level ${stats.level} ` +
      `(${stats.coded}, up to ${stats.fpsTarget} fps), stream ${stats.choice}, ` +
      `decoding ${median(stats.decodeMs).toFixed(0)} ms\n`;
  }
  return stats.note ? `JPEG: ${stats.note}\n` : "";
}

let overlayCodec = null;  // the codec the overlay names

function showOverlay() {
  const now = performance.now();
  overlayCodec = stats.codec;
  stats.fps = receivedFps(now);
  if (stats.mode === "mjpeg") {
    overlay.textContent = "mjpeg: no frame information (rates, colour scale) without the WebSocket";
    return;
  }
  const m = stats.meta || {};
  const sc = stats.scale;
  let scale = "no colour scale", legend = "";
  if (sc && sc.kind === "registration") {
    scale = `${sc.label} (clipped above)`;
    legend = `\n${registrationLines(sc)}`;
  } else if (sc) {
    scale = `${sc.palette}, ${sc.auto ? "auto" : "manual"} span, ${sc.agc} AGC`;
    // the legend of the marking: what the muted and the uncoloured pixels mean
    legend = `\nplain colour: no thermal view${sc.marking ? "; muted colours: no TOF depth (registration approximate)" : ""}`;
  }
  const balance = sc && sc.kind === "temperature" && m.balance ? `\n${balanceLine(m.balance)}` : "";
  const modeNote = stats.modeError ? `\nmode not changed: ${stats.modeError}` : "";
  // sensors that are not ok (silent, no frame yet, failing), one line each, from the frame's metadata
  const health = Object.values(m.health || {}).map((line) => `\n⚠ ${line}`).join("");
  const calibration = stats.drift ? `\ncalibration health: ${stats.drift.summary}` : "";
  stats.mbps = receivedMbps(now);
  overlay.textContent =
    `${stats.codec || "–"} (${stats.mode}): received ${stats.fps.toFixed(1)} fps, ` +
    `${stats.mbps.toFixed(2)} Mbit/s, latency ${median(stats.latencyMs).toFixed(0)} ms\n` +
    videoLine() + `console: ${ratesLine(now)}\nrates over the last ${windowS()} s; mode ${m.mode || "–"}, ${scale}` + legend + balance + health + calibration + modeNote;
}
setInterval(showOverlay, 500);

// The calibration's health from the console's status: the overlay's line and the alert
// banner (one line per drifted camera; hidden when none).
async function pollDrift() {
  try {
    const r = await fetch("/api/status");
    if (!r.ok) return;
    stats.drift = (await r.json()).drift || null;
  } catch (e) { return; /* the next poll tries again */ }
  const lines = (stats.drift && stats.drift.alerts) || [];
  alertBox.textContent = lines.join("\n");
  alertBox.hidden = !lines.length;
  showOverlay();
}
setInterval(pollDrift, 2000);
pollDrift();

// The overlay's lines in the `registration` mode: each eye's figures, what the plain colour
// means, and whether the calibration's share is in.
function registrationLines(sc) {
  const eye = (k) => {
    const e = sc.eyes[k];
    if (!e) return `${k} not estimated yet`;
    if (typeof e.median_px !== "number") return `${k} no cell with depth`;
    return `${k} median ${e.median_px.toFixed(2)} px, p95 ${e.p95_px.toFixed(2)} px (${e.cells} cells)`;
  };
  const lines = [`registration σ: ${eye("left")}; ${eye("right")}`,
    "plain colour: no estimate (no TOF depth, no thermal view, depth edge)"];
  if (!sc.covariance) lines.push("no calibration covariance in the rig: only range and footprint shares");
  return lines.join("\n");
}

// -- the display mode ------------------------------------------------------------------------

// The modes the console's API takes (its schema's FusionSettings.mode), into the select.
async function loadModes() {
  try {
    const r = await fetch("/openapi.json");
    if (!r.ok) return;
    const schema = await r.json();
    const modes = schema.components.schemas.FusionSettings.properties.mode.enum;
    modeSelect.replaceChildren(...modes.map((mode) => new Option(mode, mode)));
    await syncMode();
    modeSelect.disabled = false;
  } catch (e) { /* an older console: no select */ }
}

// The select shows the console's mode (another viewer or the 3D console may change it).
async function syncMode() {
  if (!modeSelect.options.length || document.activeElement === modeSelect) return;
  try {
    const r = await fetch("/api/fusion");
    if (r.ok) modeSelect.value = (await r.json()).mode;
  } catch (e) { /* the next frame's mode tries again */ }
}

modeSelect.onchange = async () => {
  const mode = modeSelect.value;
  try {
    const r = await fetch("/api/fusion");
    if (!r.ok) throw new Error(`GET /api/fusion: ${r.status}`);
    const put = await fetch("/api/fusion", {
      method: "PUT", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ ...(await r.json()), mode }),
    });
    if (!put.ok) throw new Error(`${put.status} ${await put.text()}`);
    stats.modeError = null;
  } catch (e) {
    stats.modeError = String(e.message || e);
    syncMode();
  }
  modeSelect.blur();
};

// The thermal balance between the two imagers the picture shows (the metadata's `balance`).
function balanceLine(b) {
  const k = (v) => `${v >= 0 ? "+" : "−"}${Math.abs(v).toFixed(2)} K`;
  const fix = `left − right corrected by ${k(b.correction_k)}`;
  if (b.mode === "auto") return `thermal balance: automatic, ${fix}`;
  if (b.mode === "rig") return `thermal balance: the rig's, ${fix}`;
  if (b.mode === "applied") return `thermal balance: applied once, ${fix}`;
  const d = typeof b.difference_k === "number" ? ` (left − right ${k(b.difference_k)} measured)` : "";
  return `thermal balance: off, the eyes may differ in colour${d}`;
}

document.getElementById("fullscreen").onclick = () => {
  const el = document.getElementById("stage");  // the picture with its colour scales
  (el.requestFullscreen || el.webkitRequestFullscreen).call(el);
};

// WebXR: draw the left half to the left eye and the right half to the right eye, each with
// its colour scale under it (composed on a 2D canvas as on the page: each eye's view shows
// its half of the picture above its scale).
async function setupVr() {
  const button = document.getElementById("vr");
  if (!navigator.xr || !(await navigator.xr.isSessionSupported("immersive-vr").catch(() => false))) {
    button.title = "WebXR immersive VR is not available in this browser (a headset needs HTTPS)";
    return;
  }
  button.disabled = false;
  button.onclick = async () => {
    const session = await navigator.xr.requestSession("immersive-vr");
    xrActive = true;  // the texture at the picture's own size
    fitCanvas();
    session.addEventListener("end", () => { xrActive = false; fitCanvas(); });
    const glCanvas = document.createElement("canvas");
    const gl = glCanvas.getContext("webgl", { xrCompatible: true });
    session.updateRenderState({ baseLayer: new XRWebGLLayer(session, gl) });
    const space = await session.requestReferenceSpace("local");
    const prog = program(gl);
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    const composite = document.createElement("canvas");
    const g = composite.getContext("2d");
    let shown = null, ramp = null, rampRgb = null;
    let below = 0;  // the scales' strip under the picture in the texture, in picture heights
    const onFrame = (t, frame) => {
      session.requestAnimationFrame(onFrame);
      const pose = frame.getViewerPose(space);
      if (!pose || !stats.frames) return;
      if (window.trifuseSpot) window.trifuseSpot.xrFrame(frame, pose, space, below);  // gaze/controller (viewer-spot.js)
      if (shown !== stats.frames) {  // compose each new picture once (JPEG or video: the page's canvas)
        shown = stats.frames;
        const strip = stats.scale ? xrStrip(canvas.width) : 0;
        composite.width = canvas.width; composite.height = canvas.height + strip;
        below = strip / canvas.height;
        g.drawImage(canvas, 0, 0);
        if (stats.scale) {
          if (rampRgb !== stats.scale.rgb) { ramp = rampCanvas(stats.scale.rgb); rampRgb = stats.scale.rgb; }
          drawScales(g, stats.scale, canvas.width, canvas.height, ramp);
        }
        if (window.trifuseSpot) window.trifuseSpot.drawXr(g, canvas.width, canvas.height);  // spot meter
        gl.bindTexture(gl.TEXTURE_2D, tex);
        gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, gl.RGBA, gl.UNSIGNED_BYTE, composite);
      }
      const layer = session.renderState.baseLayer;
      gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      for (const view of pose.views) {
        const vp = layer.getViewport(view);
        gl.viewport(vp.x, vp.y, vp.width, vp.height);
        gl.uniform1f(prog.half, view.eye === "right" ? 0.5 : 0.0);
        gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
      }
    };
    session.requestAnimationFrame(onFrame);
  };
}

function program(gl) {
  const vs = "attribute vec2 p; varying vec2 uv; uniform float half;" +
    "void main(){ uv = vec2(half + (p.x + 1.0) * 0.25, (1.0 - p.y) * 0.5); gl_Position = vec4(p, 0.0, 1.0); }";
  const fs = "precision mediump float; varying vec2 uv; uniform sampler2D img;" +
    "void main(){ gl_FragColor = texture2D(img, uv); }";
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const sh = gl.createShader(type); gl.shaderSource(sh, src); gl.compileShader(sh); gl.attachShader(prog, sh);
  }
  gl.linkProgram(prog); gl.useProgram(prog);
  const buf = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, buf);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
  const loc = gl.getAttribLocation(prog, "p");
  gl.enableVertexAttribArray(loc);
  gl.vertexAttribPointer(loc, 2, gl.FLOAT, false, 0, 0);
  return { half: gl.getUniformLocation(prog, "half") };
}

startStream();
loadModes();
setupVr();
