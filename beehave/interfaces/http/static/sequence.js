// beehave fleet: the robots and agents of a fleet process as a list that opens each one's
// full view, and the agents' messages as a sequence diagram (hand-drawn SVG: one lifeline
// per agent, one arrow per message and receiver, oldest at the top), filtered by
// conversation or by agent. Fed by app.js's renderFleet (hook: beehaveSequence.render).
"use strict";

(function () {
  const MAX_MESSAGES = 80, COL_W = 130, ROW_H = 26, TOP = 34;
  const seq = {conversation: "", agent: "", fleet: null};
  window.beehaveSequence = seq;

  const panel = el("div", {class: "panel", id: "sequence-panel", hidden: ""});
  const list = el("ul", {id: "fleet-members", class: "fleet-members"});
  const conv = el("select", {id: "seq-conversation", "aria-label": "conversation"});
  const agent = el("select", {id: "seq-agent", "aria-label": "agent"});
  const holder = el("div", {id: "sequence", class: "sequence"});
  panel.append(el("h2", {text: "Fleet members"}), list,
               el("h2", {}, "Messages ", conv, agent), holder);
  $("#side").append(panel);
  conv.addEventListener("change", () => { seq.conversation = conv.value; draw(); });
  agent.addEventListener("change", () => { seq.agent = agent.value; draw(); });

  function receivers(m) { return String(m.to || "").split(",").map((s) => s.trim()).filter(Boolean); }

  function options(select, values, all, current) {
    const keep = values.includes(current) ? current : "";
    select.replaceChildren(el("option", {value: "", text: all}),
      ...values.map((v) => el("option", {value: v, text: v})));
    select.value = keep;
    return keep;
  }

  // Robots (open their full view) and agents (filter the messages by them).
  function members(fleet) {
    const robots = (fleet.robots || []).map((r) => String(r.atv || r.robot || r.name)).filter(Boolean);
    const agents = (fleet.agents || []).map((a) => String(a.agent || a.name)).filter(Boolean);
    const names = [...new Set([...robots, ...agents])].sort();
    list.replaceChildren(...names.map((name) => {
      const isRobot = robots.includes(name) || view().robots.includes(name);
      const item = el("li", {"data-member": name, class: isRobot ? "robot" : "agent"});
      const button = el("button", {type: "button", text: name,
        title: isRobot ? "open its full view" : "show its messages"});
      button.addEventListener("click", () => {
        if (view().robots.includes(name)) select(name);
        seq.agent = name;
        agent.value = name;
        draw();
      });
      item.append(button, el("span", {class: "muted", text: isRobot ? " robot" : " agent"}));
      return item;
    }));
  }

  function view() { return window.beehave; }

  function draw() {
    const fleet = seq.fleet || {};
    // The fleet is polled every second: redraw only when what is drawn would change.
    const drawn = JSON.stringify([fleet.messages, seq.conversation, seq.agent]);
    if (drawn === seq.drawn && holder.firstChild) return;
    seq.drawn = drawn;
    const all = (Array.isArray(fleet.messages) ? fleet.messages : []).slice().reverse();  // oldest first
    // An agent's filter keeps the arrows it sends or receives.
    const mine = (m, to) => !seq.agent || m.from === seq.agent || to === seq.agent;
    const shown = all.filter((m) => (!seq.conversation || m.conversation === seq.conversation) &&
      receivers(m).some((to) => mine(m, to))).slice(-MAX_MESSAGES);
    const arrows = shown.flatMap((m) => receivers(m).filter((to) => mine(m, to)).map((to) => ({m, to})));
    const lanes = [];
    for (const {m, to} of arrows) for (const who of [m.from, to]) if (who && !lanes.includes(who)) lanes.push(who);
    const width = Math.max(lanes.length, 1) * COL_W, height = TOP + arrows.length * ROW_H + 14;
    const s = svg("svg", {id: "sequence-svg", width, height, viewBox: `0 0 ${width} ${height}`,
                          role: "img", "aria-label": "sequence diagram of the agents' messages"});
    s.append(svgEl("defs", {}, svgEl("marker", {id: "seq-arrow", viewBox: "0 0 10 10", refX: "9", refY: "5",
      markerWidth: "7", markerHeight: "7", orient: "auto-start-reverse"}, svgEl("path", {d: "M0,0 L10,5 L0,10 z", class: "seq-head"}))));
    const x = (who) => lanes.indexOf(who) * COL_W + COL_W / 2;
    for (const who of lanes) {
      s.append(svgEl("line", {class: "seq-life", x1: x(who), y1: TOP - 8, x2: x(who), y2: height - 4}));
      const name = svgEl("text", {class: "seq-name", x: x(who), y: 16, "text-anchor": "middle", "data-lane": who});
      name.textContent = who.length > 18 ? who.slice(0, 17) + "…" : who;
      s.append(name);
    }
    arrows.forEach(({m, to}, i) => {
      const y = TOP + i * ROW_H + 14;
      const x1 = x(m.from), x2 = x(to);
      const g = svgEl("g", {class: `seq-msg ${m.performative || ""}`, "data-from": m.from, "data-to": to,
        "data-performative": m.performative || "", "data-conversation": m.conversation || ""});
      const title = svgEl("title", {});
      title.textContent = `${m.sent || ""} ${m.from} → ${to}: ${m.performative} ${m.protocol || ""} ${m.conversation || ""}\n${m.content || ""}`;
      g.append(title);
      if (x1 === x2) {
        g.append(svgEl("path", {class: "seq-line", d: `M${x1},${y - 6} h28 v12 h-26`, "marker-end": "url(#seq-arrow)"}));
      } else {
        g.append(svgEl("line", {class: "seq-line", x1, y1: y, x2: x2 + (x2 > x1 ? -2 : 2), y2: y, "marker-end": "url(#seq-arrow)"}));
      }
      const label = svgEl("text", {class: "seq-label", x: (x1 + x2) / 2 + (x1 === x2 ? 34 : 0), y: y - 4, "text-anchor": x1 === x2 ? "start" : "middle"});
      label.textContent = m.performative || "";
      g.append(label);
      s.append(g);
    });
    holder.replaceChildren(shown.length ? s : el("div", {class: "muted", text: "no message (of this conversation)"}));
    holder.dataset.messages = String(shown.length);
  }

  function svgEl(tag, attrs, ...children) {
    const node = svg(tag, attrs);
    for (const child of children) node.append(child);
    return node;
  }

  seq.render = (fleet) => {
    seq.fleet = fleet || {};
    panel.hidden = false;
    members(seq.fleet);
    const messages = Array.isArray(seq.fleet.messages) ? seq.fleet.messages : [];
    const conversations = [...new Set(messages.map((m) => m.conversation).filter(Boolean))].sort();
    const agents = [...new Set(messages.flatMap((m) => [m.from, ...receivers(m)]).filter(Boolean))].sort();
    seq.conversation = options(conv, conversations, "every conversation", seq.conversation);
    seq.agent = options(agent, agents, "every agent", seq.agent);
    draw();
  };
  seq.draw = draw;
})();
