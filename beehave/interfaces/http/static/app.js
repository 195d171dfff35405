// beehave live view: plain JavaScript + SVG, no build step (uPlot, for plots.js, is vendored).
// Data: REST under /api (behaviours, world, fleet, switch/stop) and the coalesced
// WebSocket /api/ws (one message per robot and turn: snapshot, blackboard, events).
"use strict";

const SVG = "http://www.w3.org/2000/svg";
const TRAIL_POINTS = 300;
const EVENTS_SHOWN = 200;
// Where a robot's pose, LEDs and battery are on its blackboard (the beehave HALs' keys).
const KEYS = {x: "odom/x_m", y: "odom/y_m", yaw: "odom/yaw_rad", battery: "battery/percentage",
              leds: ["leds/color", "leds/led1"]};

const view = {
  token: null, robots: [], selected: null, world: null, ws: null, retryMs: 500,
  remote: new Set(),  // robots of other processes (a fleet's): streamed while selected
  remoteWs: null,
  state: {},        // robot -> {snapshot, blackboard, events[], trail[], seq}
  behaviors: {},    // robot -> list from /behaviors
  renderQueued: false, updates: 0, dropped: 0, eventsDropped: 0,
};
window.beehave = view;  // for debugging from the console (and tests)

const $ = (sel) => document.querySelector(sel);
function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v; else if (k === "text") node.textContent = v;
    else node.setAttribute(k, v);
  }
  for (const child of children) node.append(child);
  return node;
}
function svg(tag, attrs = {}) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  return node;
}
// Writes that change nothing still cost the browser a style and layout pass: only
// write what differs (a live page writes the same values 20 times a second).
function setText(node, text) {
  if (node.textContent !== text) node.textContent = text;
}
function setAttr(node, name, v) {
  v = String(v);
  if (node.getAttribute(name) !== v) node.setAttribute(name, v);
}

// ---- token and REST -----------------------------------------------------------------------

function readToken() {
  const match = /(?:^|[#&])token=([^&]+)/.exec(location.hash);
  if (match) {
    sessionStorage.setItem("beehave-token", decodeURIComponent(match[1]));
    history.replaceState(null, "", location.pathname + location.search);  // off the screen
  }
  view.token = sessionStorage.getItem("beehave-token");
}

class ApiError extends Error {
  constructor(status, body) {
    super(body && body.detail ? body.detail : `HTTP ${status}`);
    this.status = status;
    this.body = body;
  }
}

async function api(path, options = {}) {
  const headers = Object.assign({"Accept": "application/json"}, options.headers || {});
  if (view.token) headers["Authorization"] = `Bearer ${view.token}`;
  if (options.body !== undefined) headers["Content-Type"] = "application/json";
  const response = await fetch(path, Object.assign({}, options, {headers}));
  let body = null;
  try { body = await response.json(); } catch (e) { body = null; }
  if (response.status === 401) askToken();
  if (!response.ok) throw new ApiError(response.status, body);
  return body;
}

function askToken() {
  const form = $("#token-form");
  form.hidden = false;
  setConn(false, "token needed");
}

$("#token-form").addEventListener("submit", (event) => {
  event.preventDefault();
  view.token = $("#token-input").value.trim() || null;
  if (view.token) sessionStorage.setItem("beehave-token", view.token);
  $("#token-form").hidden = true;
  start();
});

function setConn(up, text) {
  const node = $("#conn");
  node.className = `conn ${up ? "up" : "down"}`;
  node.textContent = text;
}

// ---- the WebSocket stream -----------------------------------------------------------------

function openStream(query) {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const protocols = ["beehave"];
  if (view.token) protocols.push(`bearer.${view.token}`);
  return new WebSocket(`${scheme}://${location.host}/api/ws${query}`, protocols);
}

function connect() {
  const ws = openStream("");  // this process's robots
  view.ws = ws;
  ws.onopen = () => { view.retryMs = 500; setConn(true, "live"); };
  ws.onmessage = (message) => receive(JSON.parse(message.data));
  ws.onclose = () => {
    if (view.ws !== ws) return;
    setConn(false, "reconnecting…");
    // A refused handshake (401) closes at once: ask REST why, then retry.
    api("/api/robots").catch(() => {});
    setTimeout(connect, view.retryMs);
    view.retryMs = Math.min(view.retryMs * 2, 5000);
  };
}

// A robot of another process (a fleet's): its stream is relayed by this server while it
// is the selected one; another selection closes it.
function connectRemote(name) {
  const ws = openStream(`?robots=${encodeURIComponent(name)}`);
  view.remoteWs = ws;
  ws.onopen = () => { view.retryMs = 500; setConn(true, `live: ${name}`); };
  ws.onmessage = (message) => receive(JSON.parse(message.data));
  ws.onclose = () => {
    if (view.remoteWs !== ws) return;
    setConn(false, `reconnecting to ${name}…`);
    api("/api/robots").catch(() => {});
    setTimeout(() => { if (view.remoteWs === ws) connectRemote(name); }, view.retryMs);
    view.retryMs = Math.min(view.retryMs * 2, 5000);
  };
}

function leaveRemote(name) {
  // What was streamed of it goes stale the moment its stream closes: forget it (the
  // fleet's rows draw its marker again).
  const ws = view.remoteWs;
  view.remoteWs = null;
  if (ws) ws.close();
  delete view.state[name];
  for (const node of document.querySelectorAll(`#robot-layer [data-robot="${CSS.escape(name)}"], #trail-layer [data-robot="${CSS.escape(name)}"]`)) node.remove();
}

function robotState(name) {
  if (!view.state[name]) {
    view.state[name] = {snapshot: null, blackboard: {}, events: [], trail: [], seq: 0};
  }
  return view.state[name];
}

function receive(message) {
  if (message.type !== "update") return;
  const state = robotState(message.robot);
  if (message.snapshot) state.snapshot = message.snapshot;
  if (message.blackboard) state.blackboard = message.blackboard;
  if (message.seq) state.seq = message.seq;
  // This connection's counts: sent when they change (a client that keeps up gets the
  // one message the server built for every client).
  if (message.dropped !== undefined) view.dropped = message.dropped;
  if (message.events_dropped !== undefined) view.eventsDropped = message.events_dropped;
  for (const event of message.events || []) state.events.push(event);
  if (state.events.length > EVENTS_SHOWN) state.events.splice(0, state.events.length - EVENTS_SHOWN);
  const pose = poseOf(state.blackboard);
  if (pose) {
    const last = state.trail[state.trail.length - 1];
    if (!last || Math.hypot(pose.x - last[0], pose.y - last[1]) > 0.02) {
      state.trail.push([pose.x, pose.y]);
      if (state.trail.length > TRAIL_POINTS) state.trail.shift();
    }
  }
  if (!view.robots.includes(message.robot)) { view.robots.push(message.robot); fillRobotSelect(); }
  view.updates += 1;
  // Timeline hook (timeline.js): keeps the history this update adds to.
  if (view.onUpdate) view.onUpdate(message, state);
  // The DOM follows at the next frame, once however many messages arrived since the last
  // (updates faster than frames are coalesced; the panels only write what changed).
  queueRender();
}

function queueRender() {
  if (view.renderQueued) return;
  view.renderQueued = true;
  const run = () => { if (view.renderQueued) render(); };
  requestAnimationFrame(run);
  // A hidden tab gets no frames: its DOM still follows, at most 100 ms late.
  setTimeout(run, 100);
}

// ---- values -------------------------------------------------------------------------------

function value(board, key) {
  const entry = board && board[key];
  return entry ? decode(entry.value) : undefined;
}
function decode(v) {
  if (v && typeof v === "object" && !Array.isArray(v) && Object.keys(v).length === 1 && "$float" in v) {
    return {inf: Infinity, "-inf": -Infinity, nan: NaN}[v.$float];
  }
  return v;
}
function show(v) {
  v = decode(v);
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toFixed(3);
  if (typeof v === "string") return v;
  return JSON.stringify(v, (k, x) => (typeof x === "number" && !Number.isInteger(x) ? +x.toFixed(3) : decode(x)));
}
function poseOf(board) {
  const x = value(board, KEYS.x), y = value(board, KEYS.y);
  if (typeof x !== "number" || typeof y !== "number") return null;
  const yaw = value(board, KEYS.yaw);
  return {x, y, yaw: typeof yaw === "number" ? yaw : 0};
}
function ledColour(board) {
  for (const key of KEYS.leds) {
    const v = value(board, key);
    if (Array.isArray(v) && v.length >= 3) {
      const c = v.slice(0, 3).map((f) => Math.round(Math.max(0, Math.min(1, f)) * 255));
      return `rgb(${c[0]},${c[1]},${c[2]})`;
    }
    if (typeof v === "string" && v !== "off" && v !== "mixed") return v;
  }
  return "#cfcfcf";
}

// ---- the map ------------------------------------------------------------------------------

function drawWorld(world) {
  const layer = $("#world-layer");
  layer.replaceChildren();
  const [w, h] = world.floor.size_m;
  const Y = (y) => h - y;  // the world's y points up, the SVG's down
  $("#map").setAttribute("viewBox", `-0.3 -0.3 ${w + 0.6} ${h + 0.6}`);
  view.flip = Y;
  view.flipKey = `world ${w} ${h}`;
  layer.append(svg("rect", {class: "floor", x: 0, y: 0, width: w, height: h}));
  for (const hole of world.holes || []) {
    const [cx, cy] = hole.center_m, [sx, sy] = hole.size_m;
    layer.append(svg("rect", {class: "hole", x: cx - sx / 2, y: Y(cy + sy / 2), width: sx, height: sy}));
  }
  for (const zone of world.zones || []) {
    // A speed zone: a polygon drawn under everything else, with its limit.
    const points = zone.points_m || [];
    if (points.length < 3) continue;
    const shape = svg("polygon", {class: "zone", "data-zone": zone.name,
      points: points.map(([x, y]) => `${x},${Y(y)}`).join(" ")});
    const top = Math.max(...points.map(([, y]) => y));
    const left = Math.min(...points.map(([x]) => x));
    const label = svg("text", {class: "zone-label", x: left + 0.05, y: Y(top) + 0.3});
    label.textContent = zone.max_speed_mps ? `${zone.name} ≤ ${zone.max_speed_mps} m/s` : zone.name;
    layer.append(shape, label);
  }
  for (const lane of world.lanes || []) {
    layer.append(svg("polyline", {class: "lane", "stroke-width": lane.width_m || 0.05,
      points: lane.points_m.map(([x, y]) => `${x},${Y(y)}`).join(" ")}));
  }
  for (const station of world.stations || []) {
    const [cx, cy] = station.center_m, [sx, sy] = station.size_m || [1, 1];
    const rect = svg("rect", {class: `station ${station.kind}`, x: cx - sx / 2, y: Y(cy) - sy / 2,
      width: sx, height: sy, transform: `rotate(${-(station.yaw_deg || 0)} ${cx} ${Y(cy)})`,
      "data-station": station.name});
    const label = svg("text", {x: cx - sx / 2 + 0.05, y: Y(cy) + sy / 2 - 0.08});
    label.textContent = station.name;
    layer.append(rect, label);
  }
  for (const machine of world.machines || []) {
    // A machine of a factory world: its footprint and its name (a fleet view adds the level).
    const [cx, cy] = machine.center_m, [sx, sy] = machine.size_m || [1.6, 1.2];
    const rect = svg("rect", {class: "machine", x: cx - sx / 2, y: Y(cy) - sy / 2,
      width: sx, height: sy, transform: `rotate(${-(machine.yaw_deg || 0)} ${cx} ${Y(cy)})`,
      "data-machine": machine.name});
    const label = svg("text", {class: "machine-label", x: cx - sx / 2 + 0.05, y: Y(cy) + 0.1,
      "data-machine-label": machine.name});
    label.textContent = machine.name;
    layer.append(rect, label);
  }
  for (const box of world.shelves || []) layer.append(boxShape(box, "shelf", Y));
  for (const ob of world.obstacles || []) {
    if (ob.radius_m !== undefined) {
      layer.append(svg("circle", {class: "obstacle", cx: ob.center_m[0], cy: Y(ob.center_m[1]), r: ob.radius_m}));
    } else layer.append(boxShape(ob, "obstacle", Y));
  }
  for (const wall of world.walls || []) {
    layer.append(svg("line", {class: "wall", x1: wall.from_m[0], y1: Y(wall.from_m[1]),
      x2: wall.to_m[0], y2: Y(wall.to_m[1]), "stroke-width": wall.thickness_m || 0.2}));
  }
  $("#map-note").textContent = world.name ? `world: ${world.name}` : "";
}

function boxShape(box, cls, Y) {
  const [cx, cy] = box.center_m, [sx, sy] = box.size_m;
  return svg("rect", {class: cls, x: cx - sx / 2, y: Y(cy) - sy / 2, width: sx, height: sy,
    transform: `rotate(${-(box.yaw_deg || 0)} ${cx} ${Y(cy)})`});
}

function fitWithoutWorld() {
  // No world map: frame the robots' trails.
  let xs = [], ys = [];
  for (const s of Object.values(view.state)) for (const [x, y] of s.trail) { xs.push(x); ys.push(y); }
  if (!xs.length) return;
  const x0 = Math.min(...xs) - 2, x1 = Math.max(...xs) + 2;
  const y0 = Math.min(...ys) - 2, y1 = Math.max(...ys) + 2;
  view.flip = (y) => y1 - y + y0;
  view.flipKey = `${x0} ${y0} ${x1 - x0} ${y1 - y0}`;  // the trails follow a new frame
  setAttr($("#map"), "viewBox", view.flipKey);
}

function drawRobots() {
  if (!view.world) fitWithoutWorld();
  const Y = view.flip || ((y) => 12 - y);
  const robots = $("#robot-layer"), trails = $("#trail-layer");
  // Timeline hook: view.past (robot -> state) is a past moment being shown, else now.
  for (const [name, state] of Object.entries(view.past || view.state)) {
    const pose = poseOf(state.blackboard);
    let group = robots.querySelector(`[data-robot="${CSS.escape(name)}"]`);
    if (!pose) { if (group) group.remove(); continue; }
    let trail = trails.querySelector(`[data-robot="${CSS.escape(name)}"]`);
    if (!group) {
      group = svg("g", {class: "robot", "data-robot": name, id: `robot-${name}`});
      const turning = svg("g", {class: "turning"});
      turning.append(svg("circle", {class: "body", r: 0.3}),
                     svg("line", {class: "heading", x1: 0, y1: 0, x2: 0.45, y2: 0}));
      group.append(turning,
                   svg("rect", {class: "battery-bg", x: -0.3, y: -0.55, width: 0.6, height: 0.09}),
                   svg("rect", {class: "battery", x: -0.3, y: -0.55, width: 0.6, height: 0.09}),
                   svg("text", {class: "label", x: -0.3, y: 0.62}));
      group.addEventListener("click", () => select(name));
      robots.append(group);
      trail = svg("polyline", {class: "trail", "data-robot": name});
      trails.append(trail);
    }
    // Only the body turns: the battery bar and the label stay upright.
    setAttr(group, "transform", `translate(${pose.x} ${Y(pose.y)})`);
    setAttr(group.querySelector(".turning"), "transform", `rotate(${-pose.yaw * 180 / Math.PI})`);
    setAttr(group, "data-x", pose.x.toFixed(3));
    setAttr(group, "data-y", pose.y.toFixed(3));
    setAttr(group, "data-yaw", pose.yaw.toFixed(3));
    const selected = name === view.selected;
    if (group.classList.contains("selected") !== selected) group.classList.toggle("selected", selected);
    setAttr(group.querySelector(".body"), "fill", ledColour(state.blackboard));
    const battery = value(state.blackboard, KEYS.battery);
    const bar = group.querySelector(".battery");
    setAttr(bar, "width", typeof battery === "number" ? 0.6 * Math.max(0, Math.min(100, battery)) / 100 : 0);
    const low = typeof battery === "number" && battery < 20;
    if (bar.classList.contains("low") !== low) bar.classList.toggle("low", low);
    setAttr(group, "data-battery", typeof battery === "number" ? battery.toFixed(1) : "");
    setText(group.querySelector(".label"), typeof battery === "number" ? `${name} ${battery.toFixed(0)}%` : name);
    // 300 points joined and re-parsed at every frame only when the trail moved on.
    const tip = state.trail[state.trail.length - 1];
    const trailKey = `${state.trail.length}:${tip ? tip.join(",") : ""}:${view.flipKey || ""}`;
    if (trail.__key !== trailKey) {
      trail.__key = trailKey;
      trail.setAttribute("points", state.trail.map(([x, y]) => `${x},${Y(y)}`).join(" "));
    }
  }
}

// ---- the selected robot -------------------------------------------------------------------

function select(name) {
  if (!name || name === view.selected) return;
  if (view.selected && view.remote.has(view.selected)) leaveRemote(view.selected);
  view.selected = name;
  robotState(name);  // its panels start empty, not with the previous robot's
  if (view.remote.has(name)) connectRemote(name);
  $("#robot-select").value = name;
  $("#control-msg").textContent = "";
  loadBehaviors(name);
  render();
}

function fillRobotSelect() {
  const select_ = $("#robot-select");
  const current = select_.value;
  select_.replaceChildren(...view.robots.map((n) => el("option", {value: n, text: n})));
  select_.value = current || view.selected || view.robots[0] || "";
}

$("#robot-select").addEventListener("change", (e) => select(e.target.value));

async function loadBehaviors(name) {
  try {
    view.behaviors[name] = await api(`/api/robots/${encodeURIComponent(name)}/behaviors`);
  } catch (err) {
    message(err.message, true);
    return;
  }
  if (name !== view.selected) return;
  const choice = $("#behavior-choice");
  const keep = choice.value;
  choice.replaceChildren(...view.behaviors[name].map((b) => el("option", {value: b.name, text: b.name})));
  const current = view.behaviors[name].find((b) => b.current);
  choice.value = keep && view.behaviors[name].some((b) => b.name === keep) ? keep
    : (current ? current.name : choice.value);
  showParams();
}

function showParams() {
  const list = view.behaviors[view.selected] || [];
  const chosen = list.find((b) => b.name === $("#behavior-choice").value);
  const box = $("#params");
  box.replaceChildren();
  $("#behavior-doc").textContent = chosen ? `${chosen.class} — ${chosen.doc || ""}` : "";
  if (!chosen) return;
  for (const p of chosen.parameters) {
    const input = el("input", {name: p.name, "data-param": p.name,
      placeholder: p.required ? `required${p.type ? " " + p.type : ""}` : `${JSON.stringify(p.default)}${p.type ? " (" + p.type + ")" : ""}`});
    box.append(el("label", {}, el("span", {text: p.name}), input));
  }
}

$("#behavior-choice").addEventListener("change", showParams);

function message(text, error) {
  const node = $("#control-msg");
  node.textContent = text;
  node.className = error ? "error" : "ok";
}

function paramValue(text) {
  // JSON where it parses (numbers, true, lists, objects), else the text itself.
  try { return JSON.parse(text); } catch (e) { return text; }
}

$("#switch-btn").addEventListener("click", async () => {
  const name = view.selected;
  const behavior = $("#behavior-choice").value;
  const params = {};
  for (const input of $("#params").querySelectorAll("input")) {
    if (input.value.trim() !== "") params[input.dataset.param] = paramValue(input.value.trim());
  }
  try {
    const answer = await api(`/api/robots/${encodeURIComponent(name)}/switch`,
                             {method: "POST", body: JSON.stringify({behavior, params})});
    message(`switching ${name} to ${answer.requested}`, false);
  } catch (err) {
    message(`${err.status || ""} ${err.message}`, true);
  }
});

$("#stop-btn").addEventListener("click", async () => {
  try {
    await api(`/api/robots/${encodeURIComponent(view.selected)}/stop`, {method: "POST", body: "{}"});
    message(`${view.selected}: stopping (idle: every action to its safe state)`, false);
  } catch (err) {
    message(`${err.status || ""} ${err.message}`, true);
  }
});

// One button: Pause while running, Resume while paused (the state's "paused" decides).
$("#pause-btn").addEventListener("click", async () => {
  const name = view.selected;
  const state = name && view.state[name];
  const paused = Boolean(state && state.snapshot && state.snapshot.paused);
  const verb = paused ? "resume" : "pause";
  try {
    await api(`/api/robots/${encodeURIComponent(name)}/${verb}`, {method: "POST", body: "{}"});
    message(paused ? `${name}: resumed` : `${name}: pausing (every action to a safe stop)`, false);
  } catch (err) {
    message(`${err.status || ""} ${err.message}`, true);
  }
});

// ---- panels -------------------------------------------------------------------------------

function renderEngines(snapshot) {
  const box = $("#engines");
  const engines = (snapshot && snapshot.engines) || [];
  if (!engines.length) {
    if (box.dataset.key !== "") {
      box.dataset.key = "";
      box.replaceChildren(el("span", {class: "muted", text: "no decision engine runs"}));
    }
    return;
  }
  // Rebuilt only when the engines or their states / nodes change; otherwise the rows are
  // updated in place (a 300-node tree at 20 Hz must not rebuild 300 rows per update).
  const key = engines.map((e) => `${e.path}|${e.kind}|${e.structure_id || ""}|${
    e.kind === "state_machine" ? (e.states || []).map((s) => typeof s === "string" ? s : s.name).join(",")
    : e.kind === "behaviour_tree" ? (e.nodes || []).length : JSON.stringify(e)}`).join("\n");
  if (box.dataset.key !== key) {
    box.dataset.key = key;
    box.replaceChildren(...engines.map(engineView));
  }
  engines.forEach((engine, i) => updateEngine(box.children[i], engine));
}

function engineView(engine) {
  const part = el("div", {class: `engine ${engine.kind}`, "data-engine": engine.path});
  part.append(el("h3", {text: `${engine.path} — ${engine.kind || "engine"}`}));
  if (engine.kind === "state_machine") {
    const row = el("div", {class: "sm"});
    for (const state of engine.states || []) {
      const name = typeof state === "string" ? state : state.name;
      row.append(el("span", {class: "sm-state", "data-state": name, text: name}));
    }
    part.append(row, el("div", {class: "muted last"}));
  } else if (engine.kind === "behaviour_tree") {
    for (const node of engine.nodes || []) {
      const depth = (node.path.match(/\//g) || []).length;
      part.append(el("div", {class: "bt-node", "data-node": node.path,
                             style: `padding-left:${depth * 14}px`},
                     el("span", {class: "dot"}), node.name));
    }
    part.append(el("div", {class: "muted tick"}));
  } else {
    const rest = Object.assign({}, engine);
    delete rest.path; delete rest.kind;
    part.append(el("pre", {class: "muted", text: JSON.stringify(rest, null, 1)}));
  }
  return part;
}

function updateEngine(part, engine) {
  if (!part) return;
  if (engine.kind === "state_machine") {
    if (part.__active !== engine.state) {
      part.__active = engine.state;
      for (const span of part.querySelectorAll(".sm-state")) {
        const active = span.dataset.state === engine.state;
        if (span.classList.contains("active") !== active) span.classList.toggle("active", active);
      }
    }
    const t = engine.last_transition;
    const text = t ? `last: ${t.source || "?"} → ${t.dest || "?"}${t.trigger ? " on " + t.trigger : ""}` : "";
    setText(part.querySelector(".last"), text);
  } else if (engine.kind === "behaviour_tree") {
    const rows = part.querySelectorAll(".bt-node");
    (engine.nodes || []).forEach((node, i) => {
      const row = rows[i];
      if (!row || row.dataset.status === node.status) return;
      row.dataset.status = node.status;
      row.className = `bt-node status-${node.status}`;
      row.firstChild.className = `dot status-${node.status}`;
    });
    setText(part.querySelector(".tick"), `tick ${engine.tick}`);
  }
}

const shownChildren = (node) =>
  (node.children || []).filter((c) => c.status === "RUNNING" || c.status === "STUCK").slice(-20);

function treeItem(node) {
  const item = el("li", {class: `status-${node.status}`, "data-path": node.path, "data-status": node.status});
  const extra = node.action_type ? ` [${node.action_type}]` : "";
  item.append(el("span", {class: "node"}, el("span", {class: "dot"}),
    el("span", {class: "kind", text: node.kind === "action" ? "action" : "behaviour"}),
    el("b", {text: node.name}), `${extra} ${node.status} `,
    el("span", {class: "elapsed", text: `${(node.elapsed_s || 0).toFixed(1)} s`})));
  const children = shownChildren(node);
  if (children.length) item.append(el("ul", {}, ...children.map(treeItem)));
  return item;
}

// What the running tree shows apart from its durations: while it stays, only the
// durations are written (the tree is rebuilt when an item starts, ends or changes status).
function treeKey(node) {
  return `${node.path}|${node.name}|${node.kind}|${node.status}|${node.action_type || ""}(${
    shownChildren(node).map(treeKey).join(",")})`;
}

function treeDurations(item, node) {
  setText(item.querySelector(":scope > .node > .elapsed"), `${(node.elapsed_s || 0).toFixed(1)} s`);
  const children = shownChildren(node);
  const list = children.length ? item.querySelector(":scope > ul").children : [];
  children.forEach((child, i) => treeDurations(list[i], child));
}

function renderRunning(snapshot) {
  const box = $("#tree");
  const tree = snapshot && snapshot.tree;
  const key = tree ? treeKey(tree) : "";
  if (box.__key !== key) {
    box.__key = key;
    box.replaceChildren(...(tree ? [treeItem(tree)] : []));
  } else if (tree) {
    treeDurations(box.firstChild, tree);
  }
  const locks = (snapshot && snapshot.lock_details) || {};
  const body = $("#locks tbody");
  const lockKey = Object.entries(locks).map(([type, lock]) => `${type}|${lock.holder}|${lock.status}`).join("\n");
  if (body.__key !== lockKey) {
    body.__key = lockKey;
    body.replaceChildren(...Object.entries(locks).map(([type, lock]) =>
      el("tr", {"data-lock": type}, el("td", {text: type}), el("td", {text: lock.holder}),
         el("td", {text: lock.status}), el("td", {text: `${(lock.held_s || 0).toFixed(1)} s`}))));
  } else {
    Object.values(locks).forEach((lock, i) =>
      setText(body.children[i].children[3], `${(lock.held_s || 0).toFixed(1)} s`));
  }
  const stuck = (snapshot && snapshot.stuck) || [];
  setText($("#stuck"), stuck.length ? `STUCK: ${stuck.join(", ")}` : "");
}

function renderLow(snapshot) {
  const low = snapshot && snapshot.low;
  const box = $("#logics");
  // Rebuilt only when the low level's state changed (it rarely does between updates).
  const key = low ? JSON.stringify(low) : "";
  if (box.__key === key) return;
  box.__key = key;
  if (!low) { box.replaceChildren(el("span", {class: "muted", text: "no low level in this process"})); return; }
  const parts = [el("div", {}, "logic ", el("b", {id: "current-logic-name", text: low.current || "–"}),
                    ` (registered: ${(low.registered || []).join(", ")})`)];
  const walk = (logic, depth) => {
    if (!logic) return;
    parts.push(el("div", {class: "bt-node", style: `padding-left:${depth * 14}px`},
      el("span", {class: `dot status-${logic.status}`}), `${logic.name} ${logic.status}`));
    for (const child of logic.children || []) walk(child, depth + 1);
  };
  walk(low.logic, 0);
  const hals = low.hals && (low.hals.loaded || low.hals);
  if (hals && typeof hals === "object") {
    parts.push(el("div", {class: "muted", text: `HALs: ${Object.keys(hals).join(", ")}`}));
  }
  if (low.loop_blocked) parts.push(el("div", {class: "error", text: `loop blocked by ${low.loop_blocked.culprit} at ${low.loop_blocked.where}`}));
  box.replaceChildren(...parts);
}

function renderBlackboard(board) {
  const body = $("#blackboard tbody");
  const filter = $("#bb-filter").value.trim();
  const keys = Object.keys(board || {}).filter((k) => !filter || k.includes(filter)).sort();
  const rows = new Map([...body.children].map((r) => [r.dataset.key, r]));
  let previous = null;
  for (const key of keys) {
    const entry = board[key];
    let row = rows.get(key);
    if (!row) {
      row = el("tr", {"data-key": key}, el("td", {text: key}), el("td", {class: "value"}),
               el("td", {class: "age"}), el("td", {class: "writer"}));
    }
    rows.delete(key);
    setText(row.children[1], show(entry.value));
    setText(row.children[2], entry.age_s == null ? "–" : `${entry.age_s.toFixed(1)} s`);
    setText(row.children[3], entry.writer || "");
    if (row.classList.contains("stale") !== !!entry.stale) row.classList.toggle("stale", !!entry.stale);
    setAttr(row, "data-stale", entry.stale ? "true" : "false");
    // Keep the rows in key order without rebuilding the table (no flicker).
    if (previous ? previous.nextSibling !== row : body.firstChild !== row) {
      if (previous) previous.after(row); else body.prepend(row);
    }
    previous = row;
  }
  for (const row of rows.values()) row.remove();
}

$("#bb-filter").addEventListener("input", () => render());

function eventItem(e) {
  const warn = /stuck|failed|rejected|blocked/.test(e.kind) || e.status === "FAILED";
  const time = new Date(e.stamp * 1000).toLocaleTimeString();
  return el("li", {class: warn ? "warn" : "", "data-seq": e.seq, "data-kind": e.kind},
    `${time} ${e.source} ${e.kind} ${e.subject}${e.status ? " " + e.status : ""}${e.error ? " " + e.error : ""}`);
}

function renderEvents(name, state) {
  const list = $("#events");
  const shown = state.events.slice(-EVENTS_SHOWN).reverse();
  setText($("#dropped"), view.dropped ? `${view.dropped} updates skipped (slow link)` : "");
  // Keyed by the event's seq (one robot's events): new events are added at the top and
  // old ones dropped at the bottom; the items in between are left alone.
  const keyed = shown.every((e) => e.seq !== undefined && e.seq !== null);
  if (!keyed || list.__robot !== name) {
    list.__robot = keyed ? name : null;
    list.replaceChildren(...shown.map(eventItem));
    return;
  }
  const items = new Map([...list.children].map((li) => [li.dataset.seq, li]));
  let previous = null;
  for (const e of shown) {
    const seq = String(e.seq);
    let item = items.get(seq);
    if (item) items.delete(seq); else item = eventItem(e);
    if (previous ? previous.nextSibling !== item : list.firstChild !== item) {
      if (previous) previous.after(item); else list.prepend(item);
    }
    previous = item;
  }
  for (const item of items.values()) item.remove();
}

function render() {
  view.renderQueued = false;  // whatever was queued is drawn now
  drawRobots();
  const name = view.selected;
  const state = name && (view.past || view.state)[name];  // timeline hook: a past moment
  if (!state) return;
  const snap = state.snapshot;
  const current = snap ? (snap.behavior || "switching…") + (snap.paused ? " (paused)" : "") : "–";
  const pauseBtn = $("#pause-btn");
  const paused = Boolean(snap && snap.paused);
  if (pauseBtn.getAttribute("aria-pressed") !== String(paused)) {
    pauseBtn.setAttribute("aria-pressed", String(paused));
    pauseBtn.textContent = paused ? "Resume" : "Pause";
  }
  const badge = $("#current-behavior");
  if (badge.textContent !== current) {
    badge.textContent = current;
    if (snap && snap.behavior) loadBehaviors(name);  // "current" flags changed
  }
  setText($("#current-logic"), snap && snap.low && snap.low.current ? `logic: ${snap.low.current}` : "");
  renderEngines(snap);
  if (window.beehaveGraphHook) window.beehaveGraphHook(name, snap);  // graph.js: graphs, breakpoints
  renderRunning(snap);
  renderLow(snap);
  renderBlackboard(state.blackboard);
  renderEvents(name, state);
}

// ---- the fleet ----------------------------------------------------------------------------

// A fleet process whose robots run elsewhere: the rows of its "robots" section that carry
// x_m/y_m (and no robot of this server has that name) are drawn on the map as markers.
function drawFleetRobots(rows) {
  const layer = $("#robot-layer");
  const Y = view.flip || ((y) => 12 - y);
  const seen = new Set();
  for (const row of Array.isArray(rows) ? rows : []) {
    const name = row && (row.atv || row.robot || row.name);
    if (!name || typeof row.x_m !== "number" || typeof row.y_m !== "number" || view.state[name]) continue;
    seen.add(String(name));
    let group = layer.querySelector(`[data-fleet-robot="${CSS.escape(String(name))}"]`);
    if (!group) {
      group = svg("g", {class: "robot fleet-robot", "data-fleet-robot": String(name)});
      group.append(svg("circle", {class: "body", r: 0.3}), svg("text", {class: "label", x: -0.3, y: 0.62}));
      // A robot this server forwards to: clicking it shows its full view.
      group.addEventListener("click", () => { if (view.robots.includes(group.dataset.fleetRobot)) select(group.dataset.fleetRobot); });
      layer.append(group);
    }
    group.setAttribute("transform", `translate(${row.x_m} ${Y(row.y_m)})`);
    group.dataset.x = row.x_m.toFixed(3);
    group.dataset.y = row.y_m.toFixed(3);
    const pct = row.battery_pct;
    group.querySelector(".label").textContent = typeof pct === "number" ? `${name} ${pct.toFixed(0)}%` : String(name);
  }
  for (const group of layer.querySelectorAll("[data-fleet-robot]")) {
    if (!seen.has(group.dataset.fleetRobot)) group.remove();
  }
}

function labelMachines(rows) {
  // The fleet's "machines" rows ({machine, level, capacity}) label the map's machines.
  for (const row of Array.isArray(rows) ? rows : []) {
    const name = row && (row.machine || row.name);
    if (!name) continue;
    const label = document.querySelector(`[data-machine-label="${CSS.escape(String(name))}"]`);
    if (!label) continue;
    const level = typeof row.level === "number" ? ` ${row.level.toFixed(0)}` : "";
    const capacity = typeof row.capacity === "number" ? `/${row.capacity}` : "";
    label.textContent = `${name}${level}${level ? capacity : ""}`;
  }
}

function renderFleet(fleet) {
  drawFleetRobots(fleet && fleet.robots);
  labelMachines(fleet && fleet.machines);
  const box = $("#fleet");
  const parts = [];
  for (const [section, items] of Object.entries(fleet || {})) {
    parts.push(el("h3", {text: section}));
    if (Array.isArray(items) && items.length && typeof items[0] === "object") {
      const cols = [...new Set(items.flatMap((i) => Object.keys(i)))].slice(0, 8);
      const table = el("table", {"data-section": section},
        el("thead", {}, el("tr", {}, ...cols.map((c) => el("th", {text: c})))),
        el("tbody", {}, ...items.slice(-100).map((i) => el("tr", {}, ...cols.map((c) => el("td", {text: show(i[c] === undefined ? "" : i[c])}))))));
      parts.push(el("div", {class: "scroll"}, table));  // wide tables scroll, the page not
    } else {
      parts.push(el("pre", {class: "muted", text: JSON.stringify(items, null, 1)}));
    }
  }
  box.replaceChildren(...parts);
  if (window.beehaveSequence) window.beehaveSequence.render(fleet);  // hook: sequence.js
}

async function pollFleet() {
  try {
    renderFleet(await api("/api/fleet"));
    $("#fleet-panel").hidden = false;
  } catch (err) {
    if (err.status === 404) return;  // not a fleet process
  }
  setTimeout(pollFleet, 1000);
}

// ---- start --------------------------------------------------------------------------------

async function start() {
  let info;
  try {
    info = await api("/api/robots");
  } catch (err) {
    setConn(false, err.status === 401 ? "token needed" : "no server");
    if (err.status !== 401) setTimeout(start, 2000);
    return;
  }
  view.robots = info.robots.map((r) => r.name);
  view.remote = new Set(info.robots.filter((r) => r.remote).map((r) => r.name));
  const local = view.robots.filter((n) => !view.remote.has(n));
  fillRobotSelect();
  if (info.world) {
    try { view.world = await api("/api/world"); drawWorld(view.world); } catch (err) { view.world = null; }
  }
  if (info.fleet) pollFleet();
  select(view.selected || view.robots[0]);
  if (info.recording && view.onRecording) {  // timeline hook: `beehave view FILE.mcap`
    view.onRecording(info);
    return;
  }
  if (view.ws) { const old = view.ws; view.ws = null; old.close(); }
  // A fleet process whose robots run elsewhere serves the fleet and the map, and the
  // robots it was given the addresses of (picked with the selector or on the map). Without
  // any robot, the robot panels (and Switch, Stop) would only be empty or answer "unknown
  // robot": they are hidden, by a class on the body, so that a panel a later script adds
  // (plots.js, which may run after this answer came) is hidden too.
  document.body.classList.toggle("no-robots", !view.robots.length);
  $("#robot-label").hidden = !view.robots.length;
  if (local.length) connect();
  else if (!view.remote.has(view.selected)) setConn(true, "fleet view");
}

view.render = render;  // for the console: time a redraw with performance.now()
readToken();
// Start once every script of the page has run: timeline.js, plots.js and sequence.js come
// after this one and hook into `view` (onRecording, onUpdate). Started at once, the
// answer of /api/robots could come while the parser still waited for one of them, and a
// recording opened as a live page that never showed (seen on a loaded host).
if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
else start();
