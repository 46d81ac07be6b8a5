// The viewer's video path: /stream.video (docs/FORMATS.md, "The video stream") decoded with
// WebCodecs. Per frame the server sends a JSON text message (the /stream metadata plus
// codec, key, width, height, bitrate_bps, fps_target, preset, level), then the H.264 access
// unit in Annex B as one binary message. This side answers {"ack": seq, "recv_ms": t} once
// the frame is drawn (every frame received, in order, also the ones it could not decode: the
// server keeps a window of frames in flight; t: when the frame arrived, performance.now(),
// so that the server tells a queue on the link from a busy CPU here or there),
// {"keyframe": true} after a decoder error, and
// {"preset": P} when the operator picks another preset.
//
// Used by viewer.js (loaded after this file): `videoSupported()` and `openVideoStream()`.
"use strict";

// Whether this browser has WebCodecs' VideoDecoder (a secure context only: https, or
// http://127.0.0.1 / localhost).
function videoSupported() {
  return typeof window.VideoDecoder === "function" && typeof window.EncodedVideoChunk === "function";
}

const MAX_DECODER_FAILURES = 3;  // in a row, without a frame decoded: give up on video

// Opens /stream.video?preset=`preset` and decodes it. `hooks`:
//   draw(frame, meta, decodeMs)  a decoded VideoFrame (closed once it returns), with its
//                              metadata and the time it took to decode (ms)
//   received(nbytes)           a binary message arrived (the received Mbit/s)
//   unsupported(reason)        the browser cannot decode the stream (its codec, or the
//                              decoder fails again and again): the socket is closed, the
//                              caller falls back to JPEG
//   decodeError(message)       the decoder failed on a frame (a key frame was asked for)
//   closed(info)               the socket closed: {opened, framed, code, reason}
// Returns {ws, setPreset(p), stop()}; `stop()` closes without a `closed` call.
function openVideoStream(preset, hooks) {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(`${proto}//${location.host}/stream.video?preset=${encodeURIComponent(preset)}`);
  ws.binaryType = "arraybuffer";
  let opened = false, framed = false, stopped = false;
  let meta = null;          // the metadata of the next binary message
  let decoder = null, config = null;
  let needKey = true;       // drop delta chunks until the next key frame
  const pending = new Map();  // seq -> {meta, t: performance.now() at decode(), recv} decoding
  let chain = Promise.resolve();  // messages handled one after the other, in order
  let checkedCodec = null;  // the codec isConfigSupported said yes to
  let failures = 0;         // decoder errors since the last frame decoded

  const send = (obj) => { if (ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj)); };
  const ack = (seq, recv) => send(recv === undefined ? { ack: seq } : { ack: seq, recv_ms: recv });

  const onOutput = (frame) => {
    failures = 0;
    const seq = frame.timestamp;
    const item = pending.get(seq);
    for (const s of [...pending.keys()]) if (s <= seq) pending.delete(s);
    try {
      if (!stopped && item) hooks.draw(frame, item.meta, performance.now() - item.t);
    } finally {
      frame.close();
    }
    ack(seq, item && item.recv);  // after drawing: acknowledges the older frames too
  };

  const newDecoder = () => {
    if (decoder && decoder.state !== "closed") decoder.close();  // it threw rather than failed
    decoder = new VideoDecoder({ output: onOutput, error: onError });
    if (config) decoder.configure(config);
  };

  // A decoder error closes the decoder: a new one, configured as before; the frames being
  // decoded are lost (acknowledged now), and the next frame must be an IDR.
  function onError(err) {
    if (stopped) return;
    const message = (err && err.message) || String(err);
    console.warn("video decoder:", message);
    if (hooks.decodeError) hooks.decodeError(message);
    failures += 1;
    if (failures > MAX_DECODER_FAILURES) {  // not a damaged frame: this decoder cannot do it
      stopped = true;
      ws.close(1000, "decoder failing");
      hooks.unsupported(`the video decoder keeps failing (${message})`);
      return;
    }
    const lost = [...pending.keys()];
    pending.clear();
    if (lost.length) ack(Math.max(...lost));
    needKey = true;
    newDecoder();
    send({ keyframe: true });
  }

  async function handle(data, recv) {
    if (stopped) return;
    if (typeof data === "string") {
      try { meta = JSON.parse(data); } catch (e) { meta = null; }
      return;
    }
    hooks.received(data.byteLength);
    const m = meta;
    meta = null;
    if (!m || typeof m.seq !== "number") return;  // not the protocol: nothing to ack
    if (m.codec !== checkedCodec) {
      const want = { codec: m.codec, codedWidth: m.width, codedHeight: m.height };
      const ok = await VideoDecoder.isConfigSupported(want).then((r) => r.supported, () => false);
      if (stopped) return;
      if (!ok) {
        stopped = true;
        ws.close(1000, "codec not supported");
        hooks.unsupported(`this browser cannot decode ${m.codec}`);
        return;
      }
      checkedCodec = m.codec;
    }
    if (needKey && !m.key) { ack(m.seq, recv); return; }  // undecodable until the next IDR
    if (m.key) {
      const next = { codec: m.codec, codedWidth: m.width, codedHeight: m.height, optimizeForLatency: true };
      if (!decoder || decoder.state === "closed") { config = next; newDecoder(); }
      else if (!config || config.codec !== next.codec || config.codedWidth !== next.codedWidth
               || config.codedHeight !== next.codedHeight) {
        config = next;
        decoder.configure(config);
      }
      needKey = false;
    }
    framed = true;
    pending.set(m.seq, { meta: m, t: performance.now(), recv });
    try {
      decoder.decode(new EncodedVideoChunk({ type: m.key ? "key" : "delta", timestamp: m.seq, data }));
    } catch (err) {
      onError(err);
    }
  }

  ws.onopen = () => { opened = true; };
  ws.onmessage = (ev) => {
    const recv = performance.now();
    chain = chain.then(() => handle(ev.data, recv)).catch(onError);
  };
  ws.onclose = (ev) => {
    const was = stopped;
    stopped = true;
    if (decoder && decoder.state !== "closed") decoder.close();
    if (!was) hooks.closed({ opened, framed, code: ev.code, reason: ev.reason });
  };
  return {
    ws,
    setPreset(p) { send({ preset: p }); },
    stop() {
      stopped = true;
      if (decoder && decoder.state !== "closed") decoder.close();
      ws.close(1000, "viewer switched stream");
    },
  };
}
