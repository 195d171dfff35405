// beehave plots: chosen blackboard values of the selected robot over time, drawn with
// uPlot (vendored: static/vendor/uplot, MIT). Live: from the timeline's history; in a
// recording: the whole recording (GET /api/robots/{robot}/series). A vertical line marks
// the moment the timeline shows.
"use strict";

(function () {
  const view = window.beehave, tl = window.beehaveTimeline;
  const MAX_POINTS = 2000;
  const COLOURS = ["#2f7de1", "#d1352b", "#2e9e4f", "#e08a1e", "#b4169a", "#444"];
  const plots = {keys: [], chart: null, recorded: {}, robot: null, timer: null};
  window.beehavePlots = plots;

  const panel = el("div", {class: "panel robot-panel", id: "plots-panel"});
  const input = el("input", {id: "plot-key", list: "plot-keys", placeholder: "blackboard key",
                             "aria-label": "key to plot"});
  const add = el("button", {id: "plot-add", type: "button", text: "Plot"});
  const chips = el("div", {id: "plot-chips", class: "plot-chips"});
  const box = el("div", {id: "plot", class: "plot"});
  const note = el("div", {id: "plot-note", class: "muted"});
  panel.append(el("h2", {}, "Plots ", input, add), el("datalist", {id: "plot-keys"}), chips, box, note);
  const side = $("#side");
  side.insertBefore(panel, side.children[5] || null);  // after the blackboard

  function robot() { return view.selected; }

  function numeric(v) {
    v = decode(v);
    if (typeof v === "boolean") return v ? 1 : 0;
    return typeof v === "number" && Number.isFinite(v) ? v : null;
  }

  // key -> [[t, v]] of the selected robot, t in seconds on the timeline's axis.
  async function seriesOf(keys) {
    const out = {};
    const name = robot();
    if (tl.recording) {
      const missing = keys.filter((k) => !(plots.recorded[name] && plots.recorded[name][k]));
      if (missing.length) {
        const got = await api(`/api/robots/${encodeURIComponent(name)}/series?keys=${missing.map(encodeURIComponent).join(",")}`);
        plots.recorded[name] = Object.assign(plots.recorded[name] || {}, got.series);
      }
      for (const k of keys) {
        const s = plots.recorded[name][k];
        out[k] = s.t.map((t, i) => [t, s.v[i]]);
      }
      return out;
    }
    const h = tl.robots[name];
    for (const k of keys) {
      out[k] = ((h && h.keys[k]) || []).map(([t, entry]) => [t, numeric(entry.value)])
        .filter(([, v]) => v !== null);
    }
    return out;
  }

  // One x axis for every key: the union of their times, each key held until it changes.
  function align(series, keys) {
    let times = [...new Set(keys.flatMap((k) => series[k].map((p) => p[0])))].sort((a, b) => a - b);
    if (times.length > MAX_POINTS) {
      const stride = times.length / MAX_POINTS;
      times = Array.from({length: MAX_POINTS}, (_, i) => times[Math.floor(i * stride)]).concat([times[times.length - 1]]);
    }
    const columns = keys.map((k) => {
      const s = series[k];
      let j = -1;
      return times.map((t) => {
        while (j + 1 < s.length && s[j + 1][0] <= t) j++;
        return j >= 0 ? s[j][1] : null;
      });
    });
    return [times, ...columns];
  }

  function cursorLine(u) {
    const t = tl.at;
    if (t === null || t === undefined) return;
    const x = u.valToPos(t, "x", true);
    if (!Number.isFinite(x)) return;
    const ctx = u.ctx;
    ctx.save();
    ctx.strokeStyle = "#d1352b";
    ctx.lineWidth = 2 * devicePixelRatio;
    ctx.beginPath();
    ctx.moveTo(x, u.bbox.top);
    ctx.lineTo(x, u.bbox.top + u.bbox.height);
    ctx.stroke();
    ctx.restore();
  }

  async function draw() {
    const keys = plots.keys.slice();
    chips.replaceChildren(...keys.map((k, i) => {
      const chip = el("span", {class: "chip", "data-key": k, style: `border-color:${COLOURS[i % COLOURS.length]}`}, k + " ");
      const remove = el("button", {type: "button", class: "chip-x", "aria-label": `remove ${k}`, text: "×"});
      remove.addEventListener("click", () => { plots.keys = plots.keys.filter((x) => x !== k); draw(); });
      chip.append(remove);
      return chip;
    }));
    if (!keys.length) {
      if (plots.chart) { plots.chart.destroy(); plots.chart = null; }
      box.dataset.points = "0";
      note.textContent = "pick a blackboard key with a number to plot it over time";
      return;
    }
    let data;
    try {
      data = align(await seriesOf(keys), keys);
    } catch (err) {
      note.textContent = err.message;
      return;
    }
    note.textContent = tl.recording ? "seconds since the start of the recording" : "wall time (live history)";
    const width = Math.max(200, box.clientWidth || panel.clientWidth - 20);
    const opts = {
      width, height: 170, legend: {show: true}, cursor: {drag: {x: true, y: false}},
      scales: {x: {time: !tl.recording}},
      series: [{}, ...keys.map((k, i) => ({label: k, stroke: COLOURS[i % COLOURS.length], width: 1.5, paths: uPlot.paths.stepped({align: 1})}))],
      hooks: {draw: [cursorLine]},
    };
    if (plots.chart && plots.chart.series.length === keys.length + 1 && plots.robot === robot() &&
        plots.chart.series.every((s, i) => i === 0 || s.label === keys[i - 1])) {
      plots.chart.setData(data);
    } else {
      if (plots.chart) plots.chart.destroy();
      plots.chart = new uPlot(opts, data, box);
    }
    plots.robot = robot();
    box.dataset.points = String(data[0].length);
    box.dataset.keys = keys.join(",");
  }
  plots.draw = draw;

  plots.add = (key) => {
    key = String(key || "").trim();
    if (!key) return;
    if (!plots.keys.includes(key)) plots.keys.push(key);
    draw();
  };
  add.addEventListener("click", () => { plots.add(input.value); input.value = ""; });
  input.addEventListener("keydown", (e) => { if (e.key === "Enter") { plots.add(input.value); input.value = ""; } });

  // The keys offered: the selected robot's keys holding a number now.
  async function offer() {
    const name = robot();
    let keys = [];
    if (tl.recording) {
      try { keys = (await api(`/api/robots/${encodeURIComponent(name)}/series`)).keys; } catch (e) { keys = []; }
    } else {
      const state = name && view.state[name];
      keys = Object.keys((state && state.blackboard) || {}).filter((k) => numeric(state.blackboard[k].value) !== null).sort();
    }
    $("#plot-keys").replaceChildren(...keys.map((k) => el("option", {value: k})));
  }

  tl.listeners.push(() => { if (plots.chart) plots.chart.redraw(false, false); });
  // Live: new values come in; redraw once a second (and the offered keys).
  plots.timer = setInterval(() => {
    offer();
    if (!tl.recording && plots.keys.length) draw();
  }, 1000);
  window.addEventListener("resize", () => { if (plots.chart) plots.chart.setSize({width: Math.max(200, box.clientWidth), height: 170}); });
  $("#robot-select").addEventListener("change", () => draw());
  draw();
})();
