// The operator's stereo viewer: fused side-by-side frames from /stream (a JSON text message
// with the frame's metadata, then the JPEG as a binary message, acknowledged once drawn so
// the server always sends the newest frame), MJPEG as a fallback, an
// overlay of frame rate, latency, the colour span and the sensors that are not ok (the
// metadata's `health`), full screen, and WebXR.
"use strict";
const canvas = document.getElementById("view");
const ctx = canvas.getContext("2d");
const overlay = document.getElementById("overlay");
const stats = { frames: 0, fps: 0, latencyMs: [], meta: null, t0: performance.now(), mode: "websocket" };
let latestBitmap = null;
window.trifuseStats = stats;  // read by the browser tests

function connect() {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(`${proto}//${location.host}/stream`);
  ws.binaryType = "blob";
  let meta = null, opened = false;
  ws.onopen = () => { opened = true; };
  ws.onmessage = async (ev) => {
    if (typeof ev.data === "string") { meta = JSON.parse(ev.data); return; }
    const bitmap = await createImageBitmap(ev.data);
    if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
      canvas.width = bitmap.width; canvas.height = bitmap.height;
    }
    ctx.drawImage(bitmap, 0, 0);
    ws.send("ack");  // flow control: the server sends the newest frame after this
    if (latestBitmap) latestBitmap.close();
    latestBitmap = bitmap;
    stats.frames += 1;
    if (meta) {
      stats.meta = meta;
      stats.latencyMs.push(Date.now() - meta.sent_ns / 1e6);
      if (stats.latencyMs.length > 120) stats.latencyMs.shift();
    }
  };
  ws.onclose = () => {
    if (!opened) { useMjpeg(); return; }
    setTimeout(connect, 1000);
  };
}

function useMjpeg() {
  stats.mode = "mjpeg";
  canvas.style.display = "none";
  const img = document.getElementById("mjpeg");
  img.style.display = "block";
  img.src = "/stream.mjpg";
}

function median(a) {
  if (!a.length) return NaN;
  const s = [...a].sort((x, y) => x - y);
  return s[Math.floor(s.length / 2)];
}

setInterval(() => {
  const now = performance.now();
  stats.fps = stats.frames * 1000 / (now - stats.t0);
  stats.frames = 0; stats.t0 = now;
  const m = stats.meta || {};
  const span = m.span_k ? `${(m.span_k[0] - 273.15).toFixed(1)}–${(m.span_k[1] - 273.15).toFixed(1)} °C` : "–";
  // sensors that are not ok (silent, no frame yet, failing), one line each, from the frame's metadata
  const health = Object.values(m.health || {}).map((line) => `\n⚠ ${line}`).join("");
  overlay.textContent = `${stats.mode}  ${stats.fps.toFixed(1)} fps  latency ${median(stats.latencyMs).toFixed(0)} ms\n` +
    `mode ${m.mode || "–"}  span ${span}` + health;
}, 1000);

document.getElementById("fullscreen").onclick = () => {
  const el = stats.mode === "mjpeg" ? document.getElementById("mjpeg") : canvas;
  (el.requestFullscreen || el.webkitRequestFullscreen).call(el);
};

// WebXR: draw the left half to the left eye and the right half to the right eye.
async function setupVr() {
  const button = document.getElementById("vr");
  if (!navigator.xr || !(await navigator.xr.isSessionSupported("immersive-vr").catch(() => false))) {
    button.title = "WebXR immersive VR is not available in this browser (a headset needs HTTPS)";
    return;
  }
  button.disabled = false;
  button.onclick = async () => {
    const session = await navigator.xr.requestSession("immersive-vr");
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
    const onFrame = (t, frame) => {
      session.requestAnimationFrame(onFrame);
      const pose = frame.getViewerPose(space);
      if (!pose || !latestBitmap) return;
      const layer = session.renderState.baseLayer;
      gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, gl.RGBA, gl.UNSIGNED_BYTE, latestBitmap);
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

connect();
setupVr();
