// beehave timeline: scrub back through a live robot's history, or play a recording
// (`beehave view FILE.mcap`). Plain JavaScript; it feeds app.js's renderer a past state
// through two hooks: view.onUpdate (each update received) and view.past (robot -> the
// state to show instead of now; null: live). docs/http.md "Timeline".
"use strict";

(function () {
  const view = window.beehave;
  // Bounded memory (documented in docs/http.md): the last HISTORY_S seconds, at most
  // SNAPS_MAX pictures of what runs (one per SNAP_EVERY_S), CHANGES_MAX changes per
  // blackboard key, EVENTS_MAX events and TRAIL_MAX poses per robot.
  const HISTORY_S = 600, SNAP_EVERY_S = 0.1, SNAPS_MAX = 6000, CHANGES_MAX = 2000;
  const EVENTS_MAX = 2000, TRAIL_MAX = 3000, TRAIL_SHOWN = 300, EVENTS_SHOWN = 200;

  const tl = {
    robots: {},        // robot -> {snaps: [[t, snapshot]], keys: {key: [[t, entry]]}, events: [], trail: [[t, x, y]]}
    at: null,          // the moment shown (seconds: wall time live, since the start in a recording); null: live
    recording: null,   // GET /api/robots's "recording" in `beehave view`
    playing: false, speed: 1, inflight: false, wanted: null, lastFrame: null,
    limits: {HISTORY_S, SNAP_EVERY_S, SNAPS_MAX, CHANGES_MAX, EVENTS_MAX, TRAIL_MAX},
    listeners: [],     // called with the moment whenever it changes (plots.js)
  };
  window.beehaveTimeline = tl;

  function history(name) {
    if (!tl.robots[name]) tl.robots[name] = {snaps: [], keys: {}, events: [], trail: []};
    return tl.robots[name];
  }

  // The last item of a time-sorted list whose time is <= t (index), -1 when none.
  function before(list, t) {
    let lo = 0, hi = list.length - 1, found = -1;
    while (lo <= hi) {
      const mid = (lo + hi) >> 1;
      if (list[mid][0] <= t) { found = mid; lo = mid + 1; } else hi = mid - 1;
    }
    return found;
  }

  function trim(list, max, oldest) {
    let cut = 0;
    while (cut < list.length && list[cut][0] < oldest) cut++;
    cut = Math.max(cut, list.length - max);
    if (cut > 0) list.splice(0, cut);
  }

  // ---- live: keep the history --------------------------------------------------------------

  view.onUpdate = (message, state) => {
    if (tl.recording) return;
    const t = typeof message.stamp === "number" ? message.stamp : Date.now() / 1000;
    const h = history(message.robot);
    if (message.snapshot) {
      const last = h.snaps[h.snaps.length - 1];
      if (last && t - last[0] < SNAP_EVERY_S && last[1].behavior === message.snapshot.behavior) {
        last[1] = message.snapshot;  // one picture per SNAP_EVERY_S: the newest of it
      } else h.snaps.push([t, message.snapshot]);
    }
    if (message.blackboard) {
      for (const [key, entry] of Object.entries(message.blackboard)) {
        const series = h.keys[key] || (h.keys[key] = []);
        const last = series[series.length - 1];
        if (!last || last[1].stamp !== entry.stamp || last[1].stale !== entry.stale) {
          series.push([t, entry]);
          if (series.length > CHANGES_MAX) series.splice(0, series.length - CHANGES_MAX);
        }
      }
    }
    for (const event of message.events || []) h.events.push([event.stamp || t, event]);
    const x = value(state.blackboard, KEYS.x), y = value(state.blackboard, KEYS.y);
    if (typeof x === "number" && typeof y === "number") {
      const last = h.trail[h.trail.length - 1];
      if (!last || Math.hypot(x - last[1], y - last[2]) > 0.02) h.trail.push([t, x, y]);
    }
    const oldest = t - HISTORY_S;
    trim(h.snaps, SNAPS_MAX, oldest);
    trim(h.events, EVENTS_MAX, oldest);
    trim(h.trail, TRAIL_MAX, oldest);
    for (const series of Object.values(h.keys)) {
      // A key's last value stays, however old: it is what the board held since.
      while (series.length > 1 && series[1][0] < oldest) series.shift();
    }
    if (tl.at === null) updateBar();
  };

  // Every robot as it was at t (wall seconds), from the kept history.
  function pastAt(t) {
    const past = {};
    for (const [name, h] of Object.entries(tl.robots)) {
      const i = before(h.snaps, t);
      const board = {};
      for (const [key, series] of Object.entries(h.keys)) {
        const j = before(series, t);
        if (j < 0) continue;
        const [when, entry] = series[j];
        board[key] = Object.assign({}, entry,
          {age_s: entry.age_s == null ? null : entry.age_s + Math.max(0, t - when)});
      }
      const e = before(h.events, t);
      const k = before(h.trail, t);
      past[name] = {
        snapshot: i >= 0 ? h.snaps[i][1] : null, blackboard: board, seq: 0,
        events: h.events.slice(Math.max(0, e + 1 - EVENTS_SHOWN), e + 1).map((p) => p[1]),
        trail: h.trail.slice(Math.max(0, k + 1 - TRAIL_SHOWN), k + 1).map((p) => [p[1], p[2]]),
      };
    }
    return past;
  }

  function span() {
    if (tl.recording) return [0, tl.recording.duration_s];
    let first = Infinity, last = -Infinity;
    for (const h of Object.values(tl.robots)) {
      if (h.snaps.length) { first = Math.min(first, h.snaps[0][0]); last = Math.max(last, h.snaps[h.snaps.length - 1][0]); }
    }
    return first === Infinity ? [0, 0] : [first, last];
  }

  // ---- the bar -----------------------------------------------------------------------------

  const bar = el("div", {id: "timeline", class: "timeline", role: "group", "aria-label": "timeline"});
  const play = el("button", {id: "tl-play", type: "button", title: "play / pause", text: "▶"});
  const speed = el("select", {id: "tl-speed", "aria-label": "playback speed"},
    ...[0.25, 0.5, 1, 2, 5, 10, 30].map((s) => el("option", {value: String(s), text: `×${s}`})));
  speed.value = "1";
  const slider = el("input", {id: "tl-slider", type: "range", min: "0", max: "0", step: "0.01",
                              value: "0", "aria-label": "moment shown"});
  const clock = el("span", {id: "tl-time", class: "tl-time", text: "live"});
  const live = el("button", {id: "tl-live", type: "button", text: "Live", "aria-pressed": "true"});
  bar.append(play, speed, slider, clock, live);
  play.hidden = true; speed.hidden = true;
  $("#map-panel").append(bar);

  function label(t) {
    if (tl.recording) return `${t.toFixed(2)} / ${tl.recording.duration_s.toFixed(2)} s`;
    const [, last] = span();
    return `${new Date(t * 1000).toLocaleTimeString()} (−${Math.max(0, last - t).toFixed(1)} s)`;
  }

  // Live, the bar follows every update: write only what changed (no needless DOM work,
  // and nothing rewritten under a finger or a screen reader).
  function put(target, key, value) { if (target[key] !== value) target[key] = value; }

  function updateBar() {
    const [first, last] = span();
    const t = tl.at === null ? last : tl.at;
    put(slider, "max", String(Math.max(0, last - first).toFixed(2)));
    const at = (t - first).toFixed(2);
    if (Number(slider.value).toFixed(2) !== at) slider.value = at;
    put(clock, "textContent", tl.at === null ? "live" : label(t));
    put(bar.dataset, "at", tl.at === null ? "live" : String(tl.recording ? t : t - first));
    const pressed = String(tl.at === null);
    if (live.getAttribute("aria-pressed") !== pressed) live.setAttribute("aria-pressed", pressed);
  }

  // Show the moment t (wall seconds live; seconds since the start in a recording).
  function show(t) {
    tl.at = t;
    if (tl.recording) { seek(t); return; }
    view.past = t === null ? null : pastAt(t);
    updateBar();
    render();  // the graphs too: app.js's render() gives graph.js the snapshot shown
    for (const listener of tl.listeners) listener(t);
  }
  tl.show = show;

  slider.addEventListener("input", () => {
    const [first] = span();
    tl.playing = false; play.textContent = "▶";
    show(first + Number(slider.value));
  });
  live.addEventListener("click", () => show(null));

  // ---- a recording (`beehave view`) ----------------------------------------------------------

  // One request at a time; a seek while one is out waits and only the newest is asked.
  async function seek(t) {
    tl.wanted = t;
    updateBar();
    if (tl.inflight) return;
    tl.inflight = true;
    try {
      while (tl.wanted !== null) {
        const asked = tl.wanted;
        tl.wanted = null;
        const moment = await api(`/api/recording/at?t=${asked.toFixed(6)}`);
        view.past = {};
        for (const [name, s] of Object.entries(moment.robots)) {
          view.past[name] = Object.assign({seq: 0}, s);
          view.state[name] = view.past[name];
        }
        bar.dataset.shown = String(asked);
        render();
        for (const listener of tl.listeners) listener(asked);
      }
    } catch (err) {
      clock.textContent = `error: ${err.message}`;
    } finally {
      tl.inflight = false;
    }
  }

  function frame(now) {
    if (!tl.playing) { tl.lastFrame = null; return; }
    if (tl.lastFrame !== null) {
      const t = Math.min(tl.recording.duration_s, tl.at + (now - tl.lastFrame) / 1000 * tl.speed);
      tl.at = t;
      seek(t);  // while one is out, the newest is asked next: the last frame's too
      if (t >= tl.recording.duration_s) { tl.playing = false; play.textContent = "▶"; }
    }
    tl.lastFrame = now;
    requestAnimationFrame(frame);
  }

  play.addEventListener("click", () => {
    tl.playing = !tl.playing;
    play.textContent = tl.playing ? "⏸" : "▶";
    if (tl.playing && tl.at >= tl.recording.duration_s) tl.at = 0;
    if (tl.playing) requestAnimationFrame(frame);
  });
  speed.addEventListener("change", () => { tl.speed = Number(speed.value); });

  view.onRecording = (info) => {
    tl.recording = info.recording;
    document.body.classList.add("recording");
    document.title = "beehave — recording";
    play.hidden = false; speed.hidden = false; live.hidden = true;
    setConn(true, `recording: ${tl.recording.files[0].split("/").pop()}`);
    show(0);
  };
})();
