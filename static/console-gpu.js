// The 3D console (/console/, Viser's page, which the console serves with this script):
// when the browser draws WebGL in software (no GPU: SwiftShader, llvmpipe), the scene is
// slow and takes the CPU the viewer's video needs. A note suggests the console's low
// bandwidth mode (every 2nd TOF pixel, small images once a second: less to draw), with a
// button that sets it (PUT /api/console/settings, for every browser) and one that hides
// the note for this browser. window.trifuseGpu: {renderer, software} (for the tests).
(() => {
  "use strict";
  const SOFTWARE = /swiftshader|llvmpipe|softpipe|software|basic render/i;
  const DISMISSED = "trifuse.softwareWebglNoteDismissed";

  // The WebGL renderer's name (unmasked where the browser tells it), or null.
  function rendererName() {
    try {
      const gl = document.createElement("canvas").getContext("webgl");
      if (!gl) return null;
      const info = gl.getExtension("WEBGL_debug_renderer_info");
      const name = gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER);
      const lose = gl.getExtension("WEBGL_lose_context");
      if (lose) lose.loseContext();
      return name ? String(name) : null;
    } catch (e) {
      return null;
    }
  }

  function button(text, onClick) {
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = text;
    Object.assign(b.style, {
      marginLeft: "0.6em", padding: "0.25em 0.7em", border: "0", borderRadius: "4px",
      background: "#228be6", color: "#fff", font: "inherit", cursor: "pointer",
    });
    b.addEventListener("click", onClick);
    return b;
  }

  function showNote(renderer) {
    const note = document.createElement("div");
    note.id = "software-webgl-note";
    note.setAttribute("role", "status");
    Object.assign(note.style, {
      position: "fixed", left: "12px", bottom: "12px", zIndex: "10000", maxWidth: "34em",
      padding: "0.7em 0.9em", borderRadius: "6px", background: "rgba(20,20,20,0.92)",
      color: "#eee", font: "13px/1.4 system-ui, sans-serif",
      boxShadow: "0 2px 8px rgba(0,0,0,0.4)",
    });
    const text = document.createElement("span");
    const what = (renderer.match(SOFTWARE) || [renderer])[0];
    text.textContent = `This browser draws the 3D scene without a GPU (${what}): it is ` +
      "slow here and takes CPU from the fused video. The low bandwidth mode sends a quarter " +
      "of the points and smaller images.";
    const row = document.createElement("div");
    row.style.marginTop = "0.5em";
    const use = button("Use low bandwidth", async () => {
      use.disabled = true;
      const r = await fetch("/api/console/settings", {
        method: "PUT", headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ bandwidth: "low" }),
      }).catch(() => null);
      text.textContent = r && r.ok
        ? "Low bandwidth is on, for every browser of this console (3D scene folder: Bandwidth)."
        : `Not changed: ${r ? r.status : "no answer"} (3D scene folder: Bandwidth).`;
      row.remove();
      setTimeout(() => note.remove(), 6000);
    });
    const hide = button("Dismiss", () => {
      try { localStorage.setItem(DISMISSED, "1"); } catch (e) { /* private mode */ }
      note.remove();
    });
    hide.style.background = "#555";
    row.append(use, hide);
    note.append(text, row);
    document.body.appendChild(note);
  }

  async function main() {
    const renderer = rendererName();
    const software = renderer !== null && SOFTWARE.test(renderer);
    window.trifuseGpu = { renderer, software };
    if (!software) return;
    try { if (localStorage.getItem(DISMISSED)) return; } catch (e) { /* private mode */ }
    const r = await fetch("/api/console/settings").catch(() => null);
    if (!r || !r.ok) return;
    const settings = await r.json();
    if (settings.bandwidth !== "low") showNote(renderer);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", main);
  else main();
})();
