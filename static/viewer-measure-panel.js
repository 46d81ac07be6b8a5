// The measurement panel's forms (issue 35), under viewer-measure.js's tools:
// - Object: the global surface (a material of GET /api/materials, or an emissivity), its
//   reflected temperature, the air's temperature and humidity, the distance used where the
//   TOF has none (PUT /api/object-parameters on each change);
// - Regions: one row per region: its name (PATCH /api/regions/{name}: the alarms watching it
//   follow), its surface (the global one, a material, or its own emissivity) and reflected
//   temperature (empty: the global one), its corrected max, min and mean (a * when some of
//   its pixels had no TOF distance: the default one was used), and × (DELETE);
// - Difference: two regions and a statistic for the overlay's Δ (GET
//   /api/measurements/delta);
// - Alarms: the rules (× removes one; a raised one in red) and a form adding one: a region,
//   above, below or a rise, the threshold in °C (a rise in K/s) (PUT /api/alarms); the newest
//   events.
// Temperatures are shown and typed in °C; the REST routes take kelvin. A field being typed
// in is never overwritten by a reading; a refused change shows the server's line and the
// field its value again.
"use strict";
(() => {
  const M = window.trifuseMeasure;
  const { state, call, K0, ruleText, ruleKey } = M;
  const c = M.celsius;
  const panel = document.getElementById("measure-panel");
  let materials = {};

  const el = (tag, props = {}, ...children) => {
    const { dataset, ...rest } = props;
    const e = Object.assign(document.createElement(tag), rest);
    Object.assign(e.dataset, dataset || {});
    e.append(...children);
    return e;
  };
  const section = (title) => {
    const s = el("fieldset", {}, el("legend", { textContent: title }));
    panel.appendChild(s);
    return s;
  };
  const number = (id, step, label, title) => el("label", { title }, label,
    el("input", { id, type: "number", step, inputMode: "decimal" }));
  const refused = (e) => { M.say(String(e.message || e)); M.poll(); };
  const fresh = (input) => input !== document.activeElement;

  // -- the global object parameters -----------------------------------------------------

  const obj = section("Object");
  const material = el("select", { id: "measure-material" });
  obj.append(
    el("label", { title: "a surface of the short table sets the emissivity" }, "Material",
      material),
    number("measure-emissivity", "0.01", "Emissivity", "0.01 to 1"),
    number("measure-reflected", "0.1", "Reflected °C",
      "the apparent temperature of what the surfaces reflect (a cold sky: far below zero)"),
    number("measure-air", "0.1", "Air °C", "the air's temperature"),
    number("measure-humidity", "1", "Humidity %", "relative humidity, 0 to 100"),
    number("measure-distance", "0.1", "No-TOF distance m",
      "the distance for the pixels the TOF has none for"),
  );
  const fields = {
    emissivity: [obj.querySelector("#measure-emissivity"), (v) => v, (v) => v],
    reflected_k: [obj.querySelector("#measure-reflected"), (k) => k - K0, (v) => v + K0],
    air_k: [obj.querySelector("#measure-air"), (k) => k - K0, (v) => v + K0],
    humidity_pct: [obj.querySelector("#measure-humidity"), (v) => v, (v) => v],
    default_distance_m: [obj.querySelector("#measure-distance"), (v) => v, (v) => v],
  };
  let params = null;
  function showParams(p) {
    params = p;
    for (const [key, [input, shown]] of Object.entries(fields)) {
      if (fresh(input)) input.value = +shown(p[key]).toFixed(2);
    }
    const name = Object.keys(materials).find((n) => materials[n] === p.emissivity);
    if (fresh(material)) material.value = name || "";
  }
  async function putParams(extra) {
    const body = { ...params };
    for (const [key, [input, , typed]] of Object.entries(fields)) {
      const v = parseFloat(input.value);
      if (Number.isFinite(v)) body[key] = typed(v);
    }
    try {
      showParams(await call("PUT", "/api/object-parameters", { ...body, ...extra }));
      M.say(null);
      M.poll();
    } catch (e) { refused(e); showParams(params); }
  }
  for (const [input] of Object.values(fields)) input.onchange = () => putParams({});
  material.onchange = () => material.value && putParams({ material: material.value });

  // -- the regions' table ---------------------------------------------------------------

  const reg = section("Regions");
  const table = el("table", { id: "measure-regions" });
  table.append(el("thead", {}, el("tr", {}, ...["Name", "Surface", "ε", "Refl. °C", "Max",
    "Min", "Mean", ""].map((t) => el("th", { textContent: t })))));
  const body = el("tbody");
  table.append(body);
  reg.append(table, el("p", { className: "empty", textContent:
    "No region: draw one with Spot, Polygon or a box (drag, then Box → region)." }));

  // PATCH the region called ``row.name`` (a rename renames the row too); refused: the rows
  // are made again with the values in force.
  const patch = async (row, edit) => {
    try {
      state.regions = await call("PATCH", `/api/regions/${encodeURIComponent(row.name)}`, edit);
      if (edit.name) row.name = edit.name;
      M.say(null);
      M.poll();
    } catch (e) { refused(e); rowsKey = null; }
  };
  const rows = new Map();  // region name -> its row's cells
  let rowsKey = null;  // the regions the rows were made for (JSON)
  function row(r) {
    const self = { name: r.name };
    const name = el("input", { value: r.name, title: "its name (Enter: renamed)",
      ariaLabel: "region name", size: 9 });
    name.onchange = () => name.value.trim() && patch(self, { name: name.value.trim() });
    const surface = el("select", { ariaLabel: `${r.name} surface` },
      el("option", { value: "global", textContent: "global" }),
      ...Object.keys(materials).map((m) => el("option", { value: m, textContent: m })),
      el("option", { value: "own", textContent: "own ε" }));
    const own = Object.keys(materials).find((m) => materials[m] === r.emissivity);
    surface.value = r.emissivity === null ? "global" : own || "own";
    const eps = el("input", { type: "number", step: "0.01", size: 4, ariaLabel: `${r.name} ε`,
      value: r.emissivity === null ? "" : r.emissivity, placeholder: "global" });
    surface.onchange = () => {
      if (surface.value === "own") { eps.focus(); return; }
      patch(self, surface.value === "global" ? { emissivity: null }
        : { material: surface.value });
    };
    eps.onchange = () => patch(self,
      { emissivity: eps.value === "" ? null : parseFloat(eps.value) });
    const refl = el("input", { type: "number", step: "0.1", size: 5,
      ariaLabel: `${r.name} reflected °C`, placeholder: "global",
      value: r.reflected_k === null ? "" : +(r.reflected_k - K0).toFixed(2) });
    refl.onchange = () => patch(self,
      { reflected_k: refl.value === "" ? null : parseFloat(refl.value) + K0 });
    const remove = el("button", { textContent: "×", title: `remove ${r.name}`,
      ariaLabel: `remove ${r.name}` });
    remove.onclick = async () => {
      try {
        state.regions = await call("DELETE", `/api/regions/${encodeURIComponent(self.name)}`);
        M.say(null);
        M.poll();
      } catch (e) { refused(e); }
    };
    const max = el("td"), min = el("td"), mean = el("td");
    const tr = el("tr", { dataset: { region: r.name } }, el("td", {}, name),
      el("td", {}, surface), el("td", {}, eps), el("td", {}, refl), max, min, mean,
      el("td", {}, remove));
    return Object.assign(self, { tr, max, min, mean, inputs: [name, surface, eps, refl] });
  }
  function showRegions() {
    const key = JSON.stringify(state.regions);
    const editing = [...rows.values()].some((r) => r.inputs.some((i) => !fresh(i)));
    if (rowsKey !== key && !editing) {
      rows.clear();
      rowsKey = key;
      body.replaceChildren();
      for (const r of state.regions) {
        const cells = row(r);
        rows.set(r.name, cells);
        body.append(cells.tr);
      }
    }
    reg.classList.toggle("none", !state.regions.length);
    const read = (state.readings && state.readings.regions) || {};
    const raised = new Set(state.active.map((k) => k.split(" ").slice(0, -2).join(" ")));
    for (const cells of rows.values()) {
      const name = cells.name;
      const o = read[name] && read[name].object;
      const guessed = read[name] ? read[name].default_distance_px : 0;
      cells.max.textContent = c(o && o.max_k);
      cells.min.textContent = c(o && o.min_k);
      cells.mean.textContent = c(o && o.mean_k) + (guessed ? "*" : "");
      cells.mean.title = guessed ? `${guessed} of ${o.pixels} pixels without a TOF distance: ` +
        "the air corrected over the default distance" : "";
      cells.tr.classList.toggle("alarm", raised.has(name));
      const error = state.readings && state.readings.errors[name];
      cells.tr.title = error || "";
    }
  }

  // -- the difference of two regions ----------------------------------------------------

  const diff = section("Difference");
  const pick = (id, label) => el("select", { id, ariaLabel: label });
  const a = pick("measure-delta-a", "first region"), b = pick("measure-delta-b", "second region");
  const stat = el("select", { id: "measure-delta-stat", ariaLabel: "statistic" },
    ...["mean", "max", "min"].map((s) => el("option", { value: s, textContent: s })));
  const deltaOut = el("output", { id: "measure-delta" });
  diff.append(a, " − ", b, stat, " ", deltaOut);
  const choose = () => {
    state.deltaPair = a.value && b.value && a.value !== b.value
      ? { a: a.value, b: b.value, stat: stat.value } : null;
    M.poll();
  };
  a.onchange = b.onchange = stat.onchange = choose;
  function fill(select, names, fallback) {
    const now = [...select.options].map((o) => o.value);
    if (JSON.stringify(now) !== JSON.stringify(names)) {
      select.replaceChildren(...names.map((n) => el("option", { value: n, textContent: n })));
    }
    if (!names.includes(select.value) || !select.value) select.value = fallback || "";
  }
  function showDelta() {
    const names = state.regions.map((r) => r.name), pair = state.deltaPair;
    fill(a, names, pair ? pair.a : names[0]);
    fill(b, names, pair ? pair.b : names[1]);
    diff.hidden = names.length < 2;
    const d = state.delta;
    deltaOut.textContent = d ? `${d.delta_k >= 0 ? "+" : "−"}${Math.abs(d.delta_k).toFixed(2)} K`
      : "—";
  }

  // -- alarms ---------------------------------------------------------------------------

  const alarms = section("Alarms");
  const rules = el("ul", { id: "measure-rules" });
  const on = pick("measure-alarm-region", "alarm region");
  const kind = el("select", { id: "measure-alarm-kind", ariaLabel: "alarm kind" },
    ...[["above", "max above"], ["below", "min below"], ["rise", "rising faster than"]]
      .map(([v, t]) => el("option", { value: v, textContent: t })));
  const threshold = el("input", { id: "measure-alarm-threshold", type: "number", step: "0.1",
    value: "60", size: 5, ariaLabel: "alarm threshold" });
  const unit = el("span", { textContent: "°C" });
  kind.onchange = () => { unit.textContent = kind.value === "rise" ? "K/s" : "°C"; };
  const add = el("button", { id: "measure-alarm-add", textContent: "Add alarm" });
  const events = el("ul", { id: "measure-events" });
  alarms.append(rules, el("div", { className: "row" }, on, kind, threshold, unit, add), events);
  const putRules = async (list) => {
    try {
      const answer = await call("PUT", "/api/alarms", list);
      state.rules = answer.rules;
      M.say(null);
      M.poll();
    } catch (e) { refused(e); }
  };
  add.onclick = () => {
    const v = parseFloat(threshold.value);
    if (!on.value) { M.say("an alarm watches a region: draw one first"); return; }
    if (!Number.isFinite(v)) { M.say("threshold: expected a number"); return; }
    putRules([...state.rules, { region: on.value, kind: kind.value,
      threshold: kind.value === "rise" ? v : v + K0 }]);
  };
  function showAlarms() {
    const key = JSON.stringify([state.rules, state.active]);
    if (rules.dataset.key !== key) {
      rules.dataset.key = key;
      const active = new Set(state.active);
      rules.replaceChildren(...state.rules.map((r, i) => {
        const x = el("button", { textContent: "×", ariaLabel: `remove alarm ${ruleText(r)}` });
        x.onclick = () => putRules(state.rules.filter((_, j) => j !== i));
        const raised = active.has(ruleKey(r));
        return el("li", { className: raised ? "alarm" : "" }, ruleText(r), " ", x);
      }));
    }
    fill(on, state.regions.map((r) => r.name), state.regions.length ? state.regions[0].name : "");
    events.replaceChildren(...state.events.slice(-3).reverse().map((e) => el("li", {
      textContent: `${e.state} ${e.region} ${e.kind}: ${e.kind === "rise"
        ? `${e.value.toFixed(2)} K/s` : `${c(e.value)} °C`}`,
    })));
  }

  M.onPoll.push(() => {
    if (panel.hidden) return;
    showRegions();
    showDelta();
    showAlarms();
  });
  (async () => {
    try {
      materials = await call("GET", "/api/materials");
      material.replaceChildren(el("option", { value: "", textContent: "(own emissivity)" }),
        ...Object.entries(materials).map(([n, e]) => el("option", { value: n,
          textContent: `${n} (${e})` })));
      showParams(await call("GET", "/api/object-parameters"));
    } catch (e) { M.say(String(e.message || e)); }
  })();
  // the global parameters may change elsewhere (the console): shown again every few seconds
  setInterval(() => {
    if (!panel.hidden) call("GET", "/api/object-parameters").then(showParams).catch(() => {});
  }, 3000);
})();
