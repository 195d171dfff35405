// beehave graphs: the decision engines of a robot drawn as graphs (cytoscape.js; state
// machines laid out by dagre through cytoscape-dagre, trees by d3-hierarchy's tidy tree;
// all vendored under /static/vendor, see its README).
//
// State machines: one node per state, transitions as edges labelled "on [when] [not
// unless]", the initial state marked, the active state highlighted. Trees: drawn as trees
// (parent above child), each node coloured by its py_trees status. Nested engines (a
// state or leaf that runs a behaviour with its own engine) sit inside their parent's box.
// Click a box's title or a tree composite to collapse / expand it; wheel / pinch zooms,
// dragging the background pans; double-click a state or node to toggle a breakpoint.
//
// The structure of an engine comes once per structure_id (GET .../structure); updates
// only change classes, so a 300-node tree costs its statuses per update, not a layout.
//
// API (also for other panels, e.g. a timeline showing a past snapshot):
//   beehaveGraph.render(container, snapshot, {robot, structures, breakpoints, onToggle})
//     snapshot: a /snapshot or WebSocket update's snapshot ({engines: [...]});
//     structures: optional list as GET /structure returns it (else fetched and cached);
//     breakpoints: optional {state: [...], node: [...], action_type: [...]} to mark.
//   beehaveGraph.inspect(container) -> {nodes, edges, zoom, pan} (tests, debugging)
//   beehaveGraph.destroy(container): ends the view (its cytoscape instance) and empties it.
//   beehaveGraph.breakpointsPanel(container, robot) -> the breakpoint controls.
"use strict";

window.beehaveGraph = (() => {
  const STATUS_COLOURS = {RUNNING: "#2f7de1", SUCCESS: "#2e9e4f", FAILURE: "#d1352b",
                          INVALID: "#b9bcc2"};
  const ACTIVE = "#f2b01e";
  const structures = new Map();   // structure_id -> structure
  // Laid out by dagre once per structure (and set of collapsed boxes): a second view of it
  // (another robot's with the same engine, a past moment, collapse and expand back) reuses
  // the positions. Positions only depend on the structure; the view fits them to its size.
  const LAYOUTS_KEPT = 32;
  const layouts = new Map();      // v.key + collapsed ids -> {node id: position}
  const pending = new Map();      // robot -> Promise (one structure fetch at a time)
  const views = new WeakMap();    // container -> view
  const doc = document;

  function token() {
    return (window.beehave && window.beehave.token) || sessionStorage.getItem("beehave-token");
  }

  async function request(path, options = {}) {
    const headers = {"Accept": "application/json"};
    const t = token();
    if (t) headers["Authorization"] = `Bearer ${t}`;
    if (options.body !== undefined) headers["Content-Type"] = "application/json";
    const response = await fetch(path, Object.assign({}, options, {headers}));
    let body = null;
    try { body = await response.json(); } catch (e) { body = null; }
    if (!response.ok) {
      const error = new Error(body && body.detail ? body.detail : `HTTP ${response.status}`);
      error.status = response.status;
      throw error;
    }
    return body;
  }

  function fetchStructures(robot) {
    if (!pending.has(robot)) {
      const p = request(`/api/robots/${encodeURIComponent(robot)}/structure`)
        .then((body) => { for (const s of body.engines || []) structures.set(s.structure_id, s); })
        .finally(() => pending.delete(robot));
      pending.set(robot, p);
    }
    return pending.get(robot);
  }

  // Every property a rule gives costs each element it matches at its first style pass
  // (cytoscape applies it, dirties the element's caches and its edges' and tells the
  // renderer): what is a default is not written again, and a tree's edges, most of the
  // elements of a big tree, get five properties, not twenty.
  const STYLE = [
    {selector: "node", style: {
      "label": "data(label)", "text-valign": "center",
      "text-wrap": "wrap", "text-max-width": 150, "font-size": 11, "color": "#1f2328",
      "shape": "round-rectangle",
      "background-color": "#ffffff", "border-width": 1.5, "border-color": "#8a8f96",
      "min-zoomed-font-size": 5}},  // labels too small to read are not drawn (zoom in)
    {selector: "node[w]", style: {"width": "data(w)", "height": "data(h)"}},
    {selector: "node.engine", style: {
      "label": "data(label)", "text-valign": "top", "text-halign": "center",
      "font-weight": "bold", "background-color": "#f4f6f9", "background-opacity": 0.6,
      "border-style": "dashed", "border-color": "#a9afb8", "padding": 12}},
    {selector: "node.engine.collapsed", style: {"border-style": "solid",
      "background-color": "#e8eefc", "text-valign": "center"}},
    {selector: "node.initial", style: {"shape": "ellipse", "width": 10, "height": 10,
      "label": "", "background-color": "#1f2328", "border-width": 0}},
    {selector: "node.any", style: {"border-style": "dotted", "color": "#6b7077"}},
    {selector: "node.state.final", style: {"border-width": 4, "border-style": "double"}},
    // Live classes (active, statuses, last) change colours only: a border width or a
    // font weight would have cytoscape measure the node and its edges again at every
    // update (its bounding boxes), a colour only repaints.
    {selector: "node.state.active", style: {"background-color": ACTIVE,
      "border-color": "#9a6a00"}},
    {selector: "node.composite", style: {"shape": "cut-rectangle"}},
    {selector: "node.st-RUNNING", style: {"background-color": STATUS_COLOURS.RUNNING,
      "color": "#ffffff", "border-color": "#1b4f91"}},
    {selector: "node.st-SUCCESS", style: {"background-color": STATUS_COLOURS.SUCCESS,
      "color": "#ffffff", "border-color": "#1d6433"}},
    {selector: "node.st-FAILURE", style: {"background-color": STATUS_COLOURS.FAILURE,
      "color": "#ffffff", "border-color": "#7e1f19"}},
    {selector: "node.collapsed", style: {"border-width": 3, "border-style": "double"}},
    {selector: "node.bp", style: {"outline-width": 3, "outline-color": "#d1352b",
      "outline-offset": 2, "outline-style": "solid"}},
    {selector: "node.hit", style: {"outline-width": 5, "outline-color": "#b4169a",
      "underlay-color": "#b4169a", "underlay-padding": 8, "underlay-opacity": 0.35}},
    {selector: "edge", style: {"width": 2, "line-color": "#8a8f96", "curve-style": "bezier"}},
    {selector: "edge.tree-edge", style: {"curve-style": "taxi", "taxi-direction": "downward"}},
    {selector: "edge.transition, edge.start", style: {"target-arrow-color": "#8a8f96",
      "target-arrow-shape": "triangle", "arrow-scale": 0.9}},
    {selector: "edge.transition", style: {
      "label": "data(label)", "font-size": 10,
      "text-background-color": "#ffffff", "text-background-opacity": 0.9,
      "text-background-padding": 2, "color": "#444a52", "min-zoomed-font-size": 6}},
    {selector: "edge.last", style: {"line-color": ACTIVE, "target-arrow-color": "#9a6a00"}},
    {selector: "edge.nested", style: {"line-style": "dashed", "target-arrow-shape": "none"}},
  ];

  // -- building the elements of one structure set -------------------------------------------
  const idOf = (...parts) => parts.map((p) => String(p).replace(/[^A-Za-z0-9_-]/g, (c) =>
    `_${c.charCodeAt(0).toString(16)}_`)).join("__");

  function parentEngine(path, paths) {
    let best = null;
    for (const p of paths) {
      if (p !== path && path.startsWith(p + "/") && (!best || p.length > best.length)) best = p;
    }
    return best;
  }

  function sized(data) {
    // The box around a label (cytoscape's "label" size is deprecated): ~6.3 px a character.
    const lines = String(data.label || "").split("\n");
    data.w = Math.min(170, Math.max(40, 14 + 6.3 * Math.max(...lines.map((l) => l.length))));
    data.h = 12 + 13 * Math.min(lines.length, 4);
    return data;
  }

  // Trees alone (no state machine, no nested box) are laid out before they are added: a
  // tidy tree (d3-hierarchy: Reingold–Tilford in Buchheim's linear time), parent centred
  // above its children, siblings left to right in tick order, each subtree as narrow as
  // its nodes allow. The elements go into cytoscape once, with their positions, classes
  // and statuses: one style pass, no layout pass, the viewport fitted from the positions
  // (cytoscape's own fit would measure every element first).
  const TREE_GAP_X = 18;   // px between neighbours (twice that between cousins)
  const TREE_GAP_Y = 40;   // px between rows
  const PADDING = 16;

  const treesAlone = (engines) => Boolean(window.d3 && window.d3.tree) && engines.every((e) =>
    e.kind === "behaviour_tree" && !parentEngine(e.path, engines.map((x) => x.path)));

  // items: [{id, parent (an id or null), w, h}], parents before children, siblings in tick
  // order (the order of the structure's nodes). Several roots sit side by side.
  function tidy(items) {
    const ROOT = "\u0000";
    const roots = items.filter((d) => d.parent === null);
    const all = roots.length === 1 ? items : [{id: ROOT, parent: null, w: 0, h: 0},
      ...items.map((d) => (d.parent === null ? Object.assign({}, d, {parent: ROOT}) : d))];
    const root = window.d3.stratify().id((d) => d.id).parentId((d) => d.parent)(all);
    // nodeSize 1: x comes out in the separation's unit, pixels.
    window.d3.tree().nodeSize([1, 1]).separation((a, b) =>
      (a.data.w + b.data.w) / 2 + (a.parent === b.parent ? TREE_GAP_X : 2 * TREE_GAP_X))(root);
    const rowH = [];
    root.each((n) => { rowH[n.depth] = Math.max(rowH[n.depth] || 0, n.data.h); });
    const rowY = [];
    let y = 0;
    for (let d = 0; d < rowH.length; d++) { rowY[d] = y + rowH[d] / 2; y += rowH[d] + TREE_GAP_Y; }
    const positions = new Map();
    root.each((n) => { if (n.id !== ROOT) positions.set(n.id, {x: n.x, y: rowY[n.depth]}); });
    return positions;
  }

  // The viewport that fits boxes of known sizes: what cy.fit() does without asking
  // cytoscape for every element's bounding box (which styles and measures them all first).
  // A hidden view (no size yet) is fitted when it gets one (makeView: on "resize").
  function fitBoxes(v, boxes) {
    const cy = v.cy;
    const width = cy.width(), height = cy.height();
    v.unfitted = !width || !height;
    if (v.unfitted || !boxes.length) return;
    let x1 = Infinity, y1 = Infinity, x2 = -Infinity, y2 = -Infinity;
    for (const b of boxes) {
      x1 = Math.min(x1, b.x - b.w / 2); x2 = Math.max(x2, b.x + b.w / 2);
      y1 = Math.min(y1, b.y - b.h / 2); y2 = Math.max(y2, b.y + b.h / 2);
    }
    const border = 2;
    x1 -= border; y1 -= border; x2 += border; y2 += border;
    const zoom = Math.min(cy.maxZoom(), Math.max(cy.minZoom(), Math.min(
      (width - 2 * PADDING) / (x2 - x1), (height - 2 * PADDING) / (y2 - y1))));
    cy.viewport({zoom, pan: {x: width / 2 - zoom * (x1 + x2) / 2,
                             y: height / 2 - zoom * (y1 + y2) / 2}});
  }

  // Lays out the tree nodes the graph holds now (what collapsing left) and fits them.
  function layoutTrees(v) {
    const cy = v.cy;
    const items = [];
    cy.nodes(".tnode").forEach((n) => {
      const d = n.data();
      items.push({id: d.id, parent: d.up === undefined || cy.getElementById(d.up).empty()
        ? null : d.up, w: d.w, h: d.h, order: d.order, engine: d.engine});
    });
    // engines in their order, then each tree's nodes in tick order
    const engineOrder = new Map(v.lastEngines.map((e, i) => [e.path, i]));
    items.sort((a, b) => (engineOrder.get(a.engine) - engineOrder.get(b.engine)) || (a.order - b.order));
    const positions = tidy(items);
    cy.batch(() => cy.nodes(".tnode").positions((n) => positions.get(n.id())));
    fitBoxes(v, items.map((d) => Object.assign({w: d.w, h: d.h}, positions.get(d.id))));
  }

  function build(engines, v) {
    const els = [];
    const paths = engines.map((e) => e.path);
    const alone = treesAlone(engines);
    for (const engine of engines) {
      // A nested engine (a sub-machine, a tree below a state) sits in a collapsible box;
      // a top-level one needs none (and dagre lays out compounds much more slowly).
      const outer = parentEngine(engine.path, paths);
      const box = outer ? idOf("e", engine.path) : undefined;
      if (box) {
        const title = `${engine.path} — ${engine.kind === "state_machine" ? "state machine" : engine.kind === "behaviour_tree" ? "tree" : engine.kind}`;
        els.push({group: "nodes", classes: "engine", data: {id: box, engine: engine.path,
          kind: "engine", label: title, full: title}});
      }
      const s = structures.get(engine.structure_id);
      if (!s) continue;
      if (s.kind === "state_machine") {
        const init = idOf("i", engine.path);
        els.push({group: "nodes", data: {id: init, parent: box, engine: engine.path}, classes: "initial"});
        for (const [order, state] of s.states.entries()) {
          const starts = (state.starts || []).map((x) => `▶ ${x.label}`).join("\n");
          els.push({group: "nodes", classes: `state${state.final ? " final" : ""}`, data: sized({
            id: idOf("s", engine.path, state.name), parent: box, label: starts ? `${state.name}\n${starts}` : state.name,
            engine: engine.path, state: state.name, bpKind: "state", bpTarget: state.name, order})});
        }
        els.push({group: "edges", classes: "start", data: {id: idOf("ie", engine.path), source: init,
          target: idOf("s", engine.path, s.initial), label: ""}});
        if (s.transitions.some((t) => t.source === "*")) {
          els.push({group: "nodes", classes: "any", data: sized({id: idOf("s", engine.path, "*"),
            parent: box, label: "any state", engine: engine.path})});
        }
        s.transitions.forEach((t, i) => {
          els.push({group: "edges", classes: "transition", data: {
            id: idOf("t", engine.path, i), source: idOf("s", engine.path, t.source),
            target: idOf("s", engine.path, t.dest), label: t.label || "", on: t.on || "",
            from: t.source, to: t.dest}});
        });
      } else if (s.kind === "behaviour_tree") {
        const edges = [];
        const live = engine.nodes || [];
        const composite = new Set(s.nodes.map((n) => n.parent));
        s.nodes.forEach((node, i) => {
          const type = composite.has(i) && node.type ? ` (${node.type}${node.memory ? ", memory" : ""})` : "";
          const hasParent = node.parent !== null && node.parent !== undefined;
          // Its status now, in its first style pass (statusUpdate finds nothing to change).
          const status = live[i] && live[i].status;
          if (status) v.statuses.set(`n:${engine.path}:${i}`, status);
          els.push({group: "nodes", classes: `tnode${composite.has(i) ? " composite" : ""}${status ? ` st-${status}` : ""}`,
            data: sized({
              id: idOf("n", engine.path, i), parent: box, label: `${node.name}${type}`,
              full: `${node.name}${type}`, up: hasParent ? idOf("n", engine.path, node.parent) : undefined,
              engine: engine.path, path: node.path, name: node.name, index: i, order: i, status,
              bpKind: "node", bpTarget: node.path, actionType: node.action_type || ""})});
          if (hasParent) {
            edges.push({group: "edges", classes: "tree-edge", data: {
              id: idOf("te", engine.path, i), source: idOf("n", engine.path, node.parent),
              target: idOf("n", engine.path, i), label: ""}});
          }
        });
        // dagre orders siblings by the edges it meets, and places the first met
        // rightmost: given last child first, the children read left to right as ticked.
        els.push(...(alone ? edges : edges.reverse()));
      }
    }
    if (alone) {
      // Laid out here without what is collapsed (its subtree goes aside right after).
      const hidden = new Set();
      const items = [];
      for (const e of els) {
        if (e.group !== "nodes") continue;
        const d = e.data;
        if (d.up !== undefined && (hidden.has(d.up) || v.collapsed.has(d.up))) { hidden.add(d.id); continue; }
        items.push({id: d.id, parent: d.up === undefined ? null : d.up, w: d.w, h: d.h});
      }
      const positions = tidy(items);
      for (const e of els) {
        if (e.group !== "nodes") continue;
        e.position = Object.assign({}, positions.get(e.data.id) || {x: 0, y: 0});
      }
      // A collapsed node's label grows ("(+N)"): then laid out again once it is collapsed.
      if (!items.some((d) => v.collapsed.has(d.id))) {
        v.fitTo = items.map((d) => Object.assign({w: d.w, h: d.h}, positions.get(d.id)));
      }
    }
    return els;
  }

  // -- a view: one cytoscape instance in one container ---------------------------------------
  function makeView(container) {
    container.classList.add("bh-graph");
    const toolbar = doc.createElement("div");
    toolbar.className = "bh-graph-tools";
    const canvas = doc.createElement("div");
    canvas.className = "bh-graph-canvas";
    const mk = (text, title, fn) => {
      const b = doc.createElement("button");
      b.type = "button"; b.textContent = text; b.title = title; b.dataset.action = title;
      b.addEventListener("click", fn);
      toolbar.append(b);
      return b;
    };
    container.replaceChildren(toolbar, canvas);
    const cy = window.cytoscape({container: canvas, style: STYLE, elements: [],
      minZoom: 0.05, maxZoom: 4, boxSelectionEnabled: false,
      autoungrabify: true});
    const v = {container, canvas, cy, key: null, collapsed: new Set(), aside: new Map(), options: {},
               statuses: new Map(), bp: null, hit: null, marked: 0};
    mk("fit", "fit", () => cy.fit(cy.elements(":visible"), 20));
    mk("+", "zoom in", () => cy.zoom({level: cy.zoom() * 1.25, renderedPosition: center(cy)}));
    mk("−", "zoom out", () => cy.zoom({level: cy.zoom() / 1.25, renderedPosition: center(cy)}));
    cy.on("tap", "node.engine, node.composite", (evt) => toggle(v, evt.target.id()));
    cy.on("resize", () => {
      if (v.unfitted && cy.width() && cy.height()) { v.unfitted = false; cy.fit(undefined, PADDING); }
    });
    cy.on("dbltap", "node[bpKind]", (evt) => {
      const d = evt.target.data();
      if (v.options.onToggle) v.options.onToggle(d.bpKind, d.bpTarget);
    });
    views.set(container, v);
    return v;
  }

  const center = (cy) => ({x: cy.width() / 2, y: cy.height() / 2});

  // Collapsing takes a box's content (a composite's subtree) out of the graph and keeps
  // it aside; expanding puts it back. (Hidden elements would still shape a compound box
  // and the layout.) Collapsed ids survive status updates and rebuilds.
  function collapse(v, id) {
    const node = v.cy.getElementById(id);
    if (node.empty() || v.aside.has(id)) return;
    const inner = node.hasClass("engine") ? node.descendants() : node.successors().nodes();
    const gone = inner.union(inner.connectedEdges());
    // Content collapsed inside it stays aside on its own; it comes back with its box.
    v.aside.set(id, gone.remove());
    node.addClass("collapsed");
    node.data("label", `${node.data("full")} (+${inner.length})`);
    node.data(sized({label: node.data("label")}));
  }

  function expand(v, id) {
    const node = v.cy.getElementById(id);
    const gone = v.aside.get(id);
    v.aside.delete(id);
    if (gone) gone.restore();
    v.marked += 1;  // what comes back may carry marks from before: walked again
    node.removeClass("collapsed");
    node.data("label", node.data("full"));
    node.data(sized({label: node.data("full")}));
    v.statuses.clear();  // what came back shows the statuses of now
    if (v.lastEngines) statusUpdate(v, v.lastEngines);
  }

  function layout(v) {
    const cy = v.cy;
    if (v.alone) { layoutTrees(v); return; }  // linear: nothing worth keeping
    const key = `${v.key}#${[...v.collapsed].sort().join(",")}`;
    const known = layouts.get(key);
    if (known && cy.nodes().every((n) => known[n.id()])) {
      cy.layout({name: "preset", positions: (n) => known[n.id()], fit: true, padding: 16,
                 animate: false}).run();
      return;
    }
    run(cy);
    if (!cy.width() || !cy.height()) return;  // a hidden view: laid out again when shown
    const positions = {};
    cy.nodes().forEach((n) => { positions[n.id()] = Object.assign({}, n.position()); });
    layouts.delete(key);
    layouts.set(key, positions);
    if (layouts.size > LAYOUTS_KEPT) layouts.delete(layouts.keys().next().value);  // oldest
  }

  function run(cy) {
    // State machines (and trees nested in them) get dagre's best ranker.
    const trees = cy.nodes(".state").empty();
    cy.layout({name: "dagre", rankDir: "TB", nodeSep: 18, rankSep: 40, edgeSep: 8,
               ranker: trees ? "longest-path" : "network-simplex",
               fit: true, padding: 16, animate: false}).run();
  }

  function toggle(v, id) {
    if (v.collapsed.has(id)) { v.collapsed.delete(id); expand(v, id); }
    else { v.collapsed.add(id); collapse(v, id); }
    layout(v);
    markBreakpoints(v, true);
  }

  function statusUpdate(v, engines) {
    const cy = v.cy;
    cy.batch(() => {
      for (const engine of engines) {
        if (engine.kind === "state_machine") {
          const active = engine.state ? idOf("s", engine.path, engine.state) : null;
          const key = `sm:${engine.path}`;
          const was = v.statuses.get(key);
          if (was !== active) {
            if (was) cy.getElementById(was).removeClass("active");
            if (active) cy.getElementById(active).addClass("active");
            v.statuses.set(key, active);
          }
          const t = engine.last_transition;
          const lastKey = `last:${engine.path}`;
          const tKey = t ? `${t.source}>${t.dest}>${t.trigger}>${t.time}` : "";
          if (v.statuses.get(`lt:${engine.path}`) === tKey) continue;
          v.statuses.set(`lt:${engine.path}`, tKey);
          const edge = t ? cy.edges().filter((e) => (e.data("from") === t.source || e.data("from") === "*") && e.data("to") === t.dest && (e.data("on") === t.trigger || !e.data("on") && t.trigger === "when") && e.source().data("engine") === engine.path) : null;
          const lastId = edge && edge.nonempty() ? edge[0].id() : null;
          const wasLast = v.statuses.get(lastKey);
          if (wasLast !== lastId) {
            if (wasLast) cy.getElementById(wasLast).removeClass("last");
            if (lastId) cy.getElementById(lastId).addClass("last");
            v.statuses.set(lastKey, lastId);
          }
        } else if (engine.kind === "behaviour_tree") {
          const nodes = engine.nodes || [];
          for (let i = 0; i < nodes.length; i++) {
            const key = `n:${engine.path}:${i}`;
            const status = nodes[i].status;
            const was = v.statuses.get(key);
            if (was === status) continue;
            const n = cy.getElementById(idOf("n", engine.path, i));
            if (was) n.removeClass(`st-${was}`);
            n.addClass(`st-${status}`);
            n.data("status", status);
            v.statuses.set(key, status);
          }
        }
      }
    });
  }

  function markBreakpoints(v, again = false) {
    const bp = v.options.breakpoints || {};
    const hit = v.options.hit || null;
    const sig = JSON.stringify([bp, hit]);
    if (sig === v.bp && !again) return;
    v.bp = sig;
    const states = new Set(bp.state || []);
    const nodes = new Set(bp.node || []);
    const types = new Set(bp.action_type || []);
    // Nothing to mark and nothing marked (the usual case): no walk over every node.
    if (!states.size && !nodes.size && !types.size && !hit && !v.marked) return;
    let marked = 0;
    v.cy.batch(() => {
      v.cy.nodes("[bpKind]").forEach((n) => {
        const d = n.data();
        const on = d.bpKind === "state" ? states.has(d.state)
          : nodes.has(d.path) || nodes.has(d.name) || (d.actionType && types.has(d.actionType));
        if (on) n.addClass("bp"); else n.removeClass("bp");
        marked += on ? 1 : 0;
        // hit.path: the behaviour whose engine entered it (the action, for a type).
        const isHit = hit && (hit.path === d.engine || hit.path.startsWith(d.engine + "/")) && (
          (hit.kind === "state" && d.bpKind === "state" && d.state === hit.target && hit.path === d.engine)
          || (hit.kind === "node" && d.bpKind === "node" && hit.path === d.engine
              && (d.path === hit.target || d.name === hit.target))
          || (hit.kind === "action_type" && d.actionType === hit.target));
        if (isHit) n.addClass("hit"); else n.removeClass("hit");
        marked += isHit ? 1 : 0;
      });
    });
    v.marked = marked;
  }

  function render(container, snapshot, options = {}) {
    const started = performance.now();
    const engines = ((snapshot && snapshot.engines) || []).filter((e) => e.structure_id);
    let v = views.get(container);
    if (!v) v = makeView(container);
    v.options = options;
    for (const s of options.structures || []) structures.set(s.structure_id, s);
    v.snapshot = snapshot;
    const missing = engines.filter((e) => !structures.has(e.structure_id));
    if (missing.length && options.robot) {
      // Drawn again (with the newest snapshot, not this one) only when the fetch brought
      // one of them: an engine that ended before its structure was asked is not asked
      // for again and again. A failed fetch is kept on the container
      // (data-structure-error), not dropped.
      fetchStructures(options.robot).then(() => {
        delete container.dataset.structureError;
        if (missing.some((e) => structures.has(e.structure_id))) render(container, v.snapshot, v.options);
      }, (err) => { container.dataset.structureError = err.message; });
    }
    const key = engines.map((e) => `${e.path}@${structures.has(e.structure_id) ? e.structure_id : "?"}`).join("|");
    container.dataset.engines = String(engines.length);
    if (key !== v.key) {
      v.key = key;
      v.statuses.clear();
      v.bp = null;
      v.marked = 0;
      v.aside.clear();
      v.alone = treesAlone(engines);
      v.fitTo = null;
      v.lastEngines = engines;
      v.cy.batch(() => {
        v.cy.elements().remove();
        v.cy.add(build(engines, v));
        for (const id of v.collapsed) collapse(v, id);
      });
      statusUpdate(v, engines);
      if (v.fitTo) fitBoxes(v, v.fitTo);  // trees alone: laid out in build
      else if (engines.length) layout(v);
      v.lastLayoutMs = performance.now() - started;
    } else {
      statusUpdate(v, engines);
    }
    v.lastEngines = engines;
    markBreakpoints(v);
    container.dataset.nodes = String(v.cy.nodes().length);
    v.lastRenderMs = performance.now() - started;
    return v.lastRenderMs;
  }

  function inspect(container) {
    const v = views.get(container);
    if (!v) return null;
    const cy = v.cy;
    const box = v.canvas.getBoundingClientRect();
    // What a press at a point of the page would hit: the element with its label.
    const pageBox = (ele) => {
      const b = ele.renderedBoundingBox({includeLabels: true, includeOverlays: false});
      return {x1: box.left + b.x1, y1: box.top + b.y1, x2: box.left + b.x2, y2: box.top + b.y2};
    };
    return {
      zoom: cy.zoom(), pan: cy.pan(), layoutMs: v.lastLayoutMs, renderMs: v.lastRenderMs,
      canvas: {x: box.left, y: box.top, width: box.width, height: box.height},
      nodes: cy.nodes().map((n) => {
        const bb = n.renderedBoundingBox({includeLabels: false, includeOverlays: false});
        return {id: n.id(), label: n.data("label") || "", classes: n.classes(),
                visible: n.visible(), status: n.data("status") || null,
                state: n.data("state") || null, path: n.data("path") || null,
                engine: n.data("engine") || null,
                center: {x: box.left + (bb.x1 + bb.x2) / 2, y: box.top + (bb.y1 + bb.y2) / 2},
                size: {w: bb.w, h: bb.h}, box: pageBox(n)};
      }),
      edges: cy.edges().map((e) => ({id: e.id(), source: e.source().id(), target: e.target().id(),
        label: e.data("label") || "", visible: e.visible(), classes: e.classes(),
        box: pageBox(e)})),
    };
  }

  // Ends a view: its cytoscape instance (frame loop, observers, canvases) and its state.
  function destroy(container) {
    const v = views.get(container);
    if (!v) return;
    v.cy.destroy();
    views.delete(container);
    container.replaceChildren();
    container.classList.remove("bh-graph");
  }

  function tap(container, id) {
    const v = views.get(container);
    if (v) toggle(v, id);
  }

  // -- the breakpoint controls ---------------------------------------------------------------
  function breakpointsPanel(container, robot, onChange) {
    const el = (tag, attrs = {}, ...kids) => {
      const n = doc.createElement(tag);
      for (const [k, val] of Object.entries(attrs)) {
        if (k === "text") n.textContent = val; else n.setAttribute(k, val);
      }
      n.append(...kids);
      return n;
    };
    const kind = el("select", {"aria-label": "breakpoint kind", class: "bp-kind"},
      el("option", {value: "state", text: "state"}), el("option", {value: "node", text: "tree node"}),
      el("option", {value: "action_type", text: "action type"}));
    const list = el("datalist", {id: `bp-choices-${Math.random().toString(36).slice(2)}`});
    const target = el("input", {"aria-label": "breakpoint target", class: "bp-target",
                                list: list.id, placeholder: "state, node or action type"});
    const add = el("button", {type: "button", class: "bp-add", text: "Break here"});
    const cont = el("button", {type: "button", class: "bp-continue", text: "Continue", disabled: ""});
    const hit = el("div", {class: "bp-hit", role: "status"});
    const set = el("ul", {class: "bp-list"});
    const msg = el("div", {class: "bp-msg", role: "status"});
    container.replaceChildren(el("div", {class: "bp-row"}, kind, target, list, add, cont), hit, set, msg);
    const state = {robot, data: null};
    const base = () => `/api/robots/${encodeURIComponent(state.robot)}`;
    const fill = (data) => {
      state.data = data;
      list.replaceChildren(...((data.choices || {})[kind.value] || []).map((c) => el("option", {value: c})));
      set.replaceChildren(...Object.entries(data.breakpoints || {}).flatMap(([k, targets]) =>
        targets.map((t) => {
          const rm = el("button", {type: "button", class: "bp-remove", title: "remove", text: "×"});
          rm.addEventListener("click", () => call("/breakpoints/remove", {kind: k, target: t}));
          return el("li", {"data-kind": k, "data-target": t}, `${k}: ${t} `, rm);
        })));
      const h = data.hit;
      hit.textContent = h ? `Paused at ${h.kind === "action_type" ? "action type" : h.kind} “${h.target}” (${h.path})` : "";
      hit.dataset.hit = h ? `${h.kind}:${h.target}` : "";
      if (h || data.paused) cont.removeAttribute("disabled"); else cont.setAttribute("disabled", "");
      if (onChange) onChange(data);
    };
    // Answers may come back out of order (a loaded server): the list shows the answer to
    // the latest request, never an older one that arrives after it (a GET sent before an
    // add, answered after it, hid the breakpoint just set).
    let asked = 0, shown = 0;
    const newest = (n, data) => { if (n > shown) { shown = n; fill(data); } };
    const call = async (path, body) => {
      const n = ++asked;
      try {
        const out = await request(base() + path, {method: "POST", body: JSON.stringify(body || {})});
        msg.textContent = ""; msg.className = "bp-msg";
        if (out && out.breakpoints) newest(n, out); else await refresh();
      } catch (err) {
        msg.textContent = `${err.status || ""} ${err.message}`; msg.className = "bp-msg error";
      }
    };
    const refresh = async () => {
      const n = ++asked;
      try { newest(n, await request(base() + "/breakpoints")); } catch (err) { msg.textContent = err.message; }
    };
    kind.addEventListener("change", () => state.data && fill(state.data));
    add.addEventListener("click", () => call("/breakpoints", {kind: kind.value, target: target.value.trim()}));
    cont.addEventListener("click", () => call("/continue").then(refresh));
    refresh();
    return {
      refresh,
      toggle: (k, t) => {
        const on = state.data && (state.data.breakpoints[k] || []).includes(t);
        return call(on ? "/breakpoints/remove" : "/breakpoints", {kind: k, target: t});
      },
      setRobot: (name) => { state.robot = name; refresh(); },
      get data() { return state.data; },
    };
  }

  return {render, inspect, tap, destroy, breakpointsPanel, structures, layouts, STATUS_COLOURS,
          ACTIVE};
})();

// The page's hook (app.js calls window.beehaveGraphHook(robot, snapshot) after each render
// of the selected robot; see index.html's "graphs" panel).
(() => {
  let panel = null;
  let robot = null;
  let paused = null;
  let bpData = null;
  window.beehaveGraphHook = (name, snapshot) => {
    const box = document.getElementById("graphs");
    const bpBox = document.getElementById("breakpoints");
    if (!box || !window.cytoscape) return;
    if (bpBox && (!panel || robot !== name)) {
      if (!panel) panel = window.beehaveGraph.breakpointsPanel(bpBox, name, (d) => { bpData = d; draw(); });
      else panel.setRobot(name);
      robot = name;
    }
    const isPaused = Boolean(snapshot && snapshot.paused);
    if (panel && paused !== isPaused) { paused = isPaused; panel.refresh(); }
    last = snapshot;
    draw();
  };
  let last = null;
  function draw() {
    const box = document.getElementById("graphs");
    if (!box || !last) return;
    window.beehaveGraph.render(box, last, {
      robot, breakpoints: bpData && bpData.breakpoints, hit: bpData && bpData.hit,
      onToggle: (k, t) => panel && panel.toggle(k, t)});
  }
})();
