// voxelwatch view: the live page. One EventSource for everything live; the plan is built once and
// then only moved (markers and trails are reused, never piled up); the event list, the trails and
// the timeline are bounded, so a page left open for days keeps a flat memory.
"use strict";

(() => {
  const S = 100;              // plan units per metre (centimetres)
  const MARGIN = 0.3;         // metres around the volume
  const MAX_ROWS = 300;       // rows kept in the event list
  const BEEP_EVERY_MS = 2000;

  const st = {
    plan: null, alarmKinds: new Set(), trailNs: 10e9, name: "view",
    markers: new Map(),       // track id -> {g, circle, label, trail, points: [[t, x, y], ...], seen}
    alarms: [], filter: { kinds: null, since: null, until: null },
    audio: null, beepTimer: null, lastStamp: 0, framesSeen: 0,
  };
  const $ = (id) => document.getElementById(id);
  let X0 = 0, Y1 = 0;
  const px = (x, y) => [((x - X0 + MARGIN) * S).toFixed(1), ((Y1 - y + MARGIN) * S).toFixed(1)];

  // ---------------------------------------------------------------- the plan

  function buildPlan(plan) {
    const svg = $("plan");
    const [x0, y0] = plan.min_xy, [x1, y1] = plan.max_xy;
    X0 = x0; Y1 = y1;
    svg.setAttribute("viewBox", `0 0 ${((x1 - x0 + 2 * MARGIN) * S).toFixed(0)} ${((y1 - y0 + 2 * MARGIN) * S).toFixed(0)}`);
    const fov = VW.svg("g", { id: "fov", class: "fov" }, svg);
    for (const c of plan.cameras) {
      if (c.fov.length) VW.svg("polygon", { points: VW.polyPoints(c.fov, px), "data-camera": c.id }, fov);
    }
    VW.svg("polygon", { class: "outline", points: VW.polyPoints(plan.outline, px) }, svg);
    for (const a of plan.occluders) VW.svg("polygon", { class: "occluder", points: VW.polyPoints(a.polygon, px) }, svg)
      .appendChild(title(a.name));
    for (const a of plan.hotspots) labelled("hotspot", a, svg);
    for (const a of plan.doors) labelled("door", a, svg);
    for (const c of plan.cameras) {
      const [cx, cy] = px(c.position_m[0], c.position_m[1]);
      const g = VW.svg("g", { class: "camera", "data-camera": c.id, transform: `translate(${cx},${cy})` }, svg);
      if (c.heading_deg !== null) {  // a wedge pointing where the camera looks
        VW.svg("path", { class: "cone", d: "M0,0 L38,-18 L38,18 Z", transform: `rotate(${-c.heading_deg})` }, g);
      }
      VW.svg("circle", { r: 8 }, g);
      VW.svg("text", { y: -14, "text-anchor": "middle" }, g).textContent = c.id;
    }
    VW.svg("g", { id: "trails" }, svg);
    VW.svg("g", { id: "markers" }, svg);
    $("show-fov").addEventListener("change", () => fov.classList.toggle("on", $("show-fov").checked));
  }

  function title(text) { const t = VW.svg("title"); t.textContent = text; return t; }

  function labelled(cls, area, svg) {
    VW.svg("polygon", { class: cls, points: VW.polyPoints(area.polygon, px) }, svg);
    const n = area.polygon.length;
    const cx = area.polygon.reduce((s, p) => s + p[0], 0) / n, cy = area.polygon.reduce((s, p) => s + p[1], 0) / n;
    const [tx, ty] = px(cx, cy);
    VW.svg("text", { class: cls + "-name", x: tx, y: ty, "text-anchor": "middle" }, svg).textContent = area.name;
  }

  // ---------------------------------------------------------------- people

  function onFrame(frame) {
    if (!frame) return;
    st.framesSeen += 1;
    st.lastStamp = frame.stamp_ns;
    const seen = new Set();
    for (const t of frame.tracks) {
      seen.add(t.id);
      let m = st.markers.get(t.id);
      if (!m) m = newMarker(t.id);
      m.seen = frame.stamp_ns;
      m.points.push([frame.stamp_ns, t.x, t.y]);
      const [cx, cy] = px(t.x, t.y);
      m.g.setAttribute("transform", `translate(${cx},${cy})`);
      m.g.setAttribute("data-x", t.x); m.g.setAttribute("data-y", t.y);
      m.g.setAttribute("data-posture", t.posture);
      m.circle.setAttribute("fill", VW.POSTURE_COLOURS[t.posture] || "#888");
      m.circle.setAttribute("r", t.posture === "lying" ? 22 : 16);
      m.label.textContent = `${t.label} · ${t.posture}`;
      m.labelText = t.label; m.posture = t.posture;
    }
    const horizon = frame.stamp_ns - st.trailNs;
    for (const [id, m] of st.markers) {
      let k = 0;
      while (k < m.points.length && m.points[k][0] < horizon) k++;
      if (k) m.points.splice(0, k);
      if (!seen.has(id)) m.g.setAttribute("visibility", "hidden"); else m.g.removeAttribute("visibility");
      if (!seen.has(id) && m.seen < horizon) {
        m.g.remove(); m.trail.remove(); st.markers.delete(id);
        continue;
      }
      m.trail.setAttribute("points", m.points.map((p) => px(p[1], p[2]).join(",")).join(" "));
    }
    renderPeople(frame);
  }

  function newMarker(id) {
    const trail = VW.svg("polyline", { class: "trail", "data-track": id }, $("trails"));
    const g = VW.svg("g", { class: "person", "data-track": id }, $("markers"));
    const circle = VW.svg("circle", { r: 16, cx: 0, cy: 0 }, g);
    const label = VW.svg("text", { x: 22, y: -18 }, g);
    const m = { g, circle, label, trail, points: [], seen: 0 };
    st.markers.set(id, m);
    return m;
  }

  function renderPeople(frame) {
    const ul = $("people");
    const want = frame.tracks.map((t) => `${t.label}: ${t.posture}${t.still ? " (still)" : ""}`);
    while (ul.children.length > want.length) ul.lastChild.remove();
    while (ul.children.length < want.length) VW.el("li", {}, "", ul);
    want.forEach((text, i) => {
      const li = ul.children[i];
      if (li.textContent !== text) li.textContent = text;
      li.className = "posture-" + frame.tracks[i].posture;
    });
    if (!want.length) { VW.el("li", { class: "muted" }, "nobody in view", ul); }
  }

  // ---------------------------------------------------------------- alarms

  function onAlarms(list) {
    st.alarms = list || [];
    const box = $("alarm");
    if (!st.alarms.length) {
      box.hidden = true;
      document.body.classList.remove("alarmed");
      stopBeeping();
      return;
    }
    const a = st.alarms[0];
    box.hidden = false;
    box.dataset.event = a.id;
    document.body.classList.add("alarmed");
    $("alarm-title").textContent = a.kind.replace("_", " ").toUpperCase();
    $("alarm-detail").textContent = `${who(a)} at (${a.x.toFixed(1)}, ${a.y.toFixed(1)}) m, ${VW.clock(a.stamp_ns)}`;
    $("alarm-more").textContent = st.alarms.length > 1 ? `and ${st.alarms.length - 1} more` : "";
    $("ack-error").textContent = "";
    startBeeping();
  }

  async function acknowledge() {
    const id = $("alarm").dataset.event;
    if (!id) return;
    $("ack").disabled = true;
    try {
      await VW.getJSON("/api/ack", { method: "POST", headers: { "Content-Type": "application/json" },
                                     body: JSON.stringify({ event: id }) });
      onAlarms(st.alarms.filter((a) => a.id !== id));
    } catch (e) {
      $("ack-error").textContent = "Not acknowledged: " + e.message;
    } finally {
      $("ack").disabled = false;
    }
  }

  function startBeeping() {
    if (st.beepTimer) return;
    beep();
    st.beepTimer = setInterval(beep, BEEP_EVERY_MS);
  }

  function stopBeeping() {
    if (st.beepTimer) clearInterval(st.beepTimer);
    st.beepTimer = null;
  }

  function beep() {
    try {
      if (!st.audio) st.audio = new (window.AudioContext || window.webkitAudioContext)();
      const ctx = st.audio;
      $("sound").hidden = ctx.state === "running";
      if (ctx.state !== "running") return;
      const t = ctx.currentTime;
      for (const [start, f] of [[0, 880], [0.25, 660]]) {
        const osc = ctx.createOscillator(), gain = ctx.createGain();
        osc.frequency.value = f; osc.type = "square";
        gain.gain.setValueAtTime(0.0001, t + start);
        gain.gain.exponentialRampToValueAtTime(0.25, t + start + 0.02);
        gain.gain.exponentialRampToValueAtTime(0.0001, t + start + 0.2);
        osc.connect(gain).connect(ctx.destination);
        osc.start(t + start); osc.stop(t + start + 0.22);
      }
    } catch (e) { /* no audio on this device: the banner still shows */ }
  }

  // ---------------------------------------------------------------- events

  function who(e) {
    if (e.track < 0) return e.details && e.details.camera ? "camera " + e.details.camera : "";
    const m = st.markers.get(e.track);
    return (e.details && e.details.person) || (m && m.labelText) || "#" + e.track;
  }

  function matches(e) {
    const f = st.filter;
    if (f.kinds && !f.kinds.has(e.kind)) return false;
    if (f.since !== null && e.stamp_ns < f.since) return false;
    if (f.until !== null && e.stamp_ns >= f.until) return false;
    return true;
  }

  function eventRow(e) {
    const tr = VW.el("tr", { "data-kind": e.kind, "data-id": e.id, class: st.alarmKinds.has(e.kind) ? "is-alarm" : "" });
    VW.el("td", {}, VW.dateTime(e.stamp_ns), tr);
    VW.el("td", { class: "kind kind-" + e.kind }, e.kind.replace("_", " "), tr);
    VW.el("td", {}, who(e), tr);
    VW.el("td", {}, e.track >= 0 || e.kind === "visit" ? `(${e.x.toFixed(1)}, ${e.y.toFixed(1)})` : "", tr);
    const d = e.details || {};
    VW.el("td", { class: "details" }, Object.entries(d).filter(([k]) => !k.endsWith("_ns")).map(([k, v]) => `${k}=${v}`).join(", "), tr);
    return tr;
  }

  function addEvent(e, atTop) {
    if (!matches(e)) return;
    const body = $("events").tBodies[0];
    if (body.querySelector(`tr[data-id="${CSS.escape(e.id)}"]`)) return;
    const tr = eventRow(e);
    if (atTop) body.insertBefore(tr, body.firstChild); else body.appendChild(tr);
    while (body.rows.length > MAX_ROWS) body.lastChild.remove();
  }

  function localInputNs(input) {
    if (!input.value) return null;
    const ms = new Date(input.value).getTime();
    return Number.isFinite(ms) ? ms * 1e6 : null;
  }

  async function loadEvents() {
    const kinds = [...$("kinds").selectedOptions].map((o) => o.value);
    st.filter = { kinds: kinds.length ? new Set(kinds) : null, since: localInputNs($("since")), until: localInputNs($("until")) };
    const q = new URLSearchParams({ limit: "2000" });
    if (kinds.length) q.set("kind", kinds.join(","));
    if (st.filter.since !== null) q.set("since", BigInt(Math.round(st.filter.since)).toString());
    if (st.filter.until !== null) q.set("until", BigInt(Math.round(st.filter.until)).toString());
    const body = $("events").tBodies[0];
    try {
      const r = await VW.getJSON("/api/events?" + q.toString());
      body.replaceChildren();
      const list = r.events.slice(-MAX_ROWS).reverse();
      for (const e of list) addEvent(e, false);
      $("events-note").textContent = `${r.events.length} from the history` + (r.events.length > MAX_ROWS ? `, newest ${MAX_ROWS} shown` : "");
    } catch (e) {
      $("events-note").textContent = "history unavailable: " + e.message;
    }
  }

  function defaultSince() {
    const d = new Date(); d.setHours(0, 0, 0, 0);
    const pad = (n) => String(n).padStart(2, "0");
    $("since").value = `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())}T00:00:00`;
  }

  // ---------------------------------------------------------------- cameras

  function onStatus(status) {
    if (!status) return;
    const body = $("cameras").tBodies[0];
    const byId = new Map(status.cameras.map((c) => [c.cam, c]));
    const ids = st.plan.cameras.map((c) => c.id);
    for (const c of status.cameras) if (!ids.includes(c.cam)) ids.push(c.cam);
    while (body.rows.length > ids.length) body.lastChild.remove();
    ids.forEach((id, i) => {
      let tr = body.rows[i];
      if (!tr) { tr = VW.el("tr", {}, undefined, body); for (let k = 0; k < 7; k++) VW.el("td", {}, "", tr); }
      const c = byId.get(id);
      const cells = tr.cells;
      tr.dataset.camera = id;
      if (!cells[0].firstChild || cells[0].firstChild.textContent !== id) {
        cells[0].replaceChildren(VW.el("a", { href: "/install/" + encodeURIComponent(id) }, id));
      }
      const state = c ? c.state : "unknown";
      cells[1].textContent = state; cells[1].className = "state state-" + state;
      cells[2].textContent = c ? c.rate_hz.toFixed(1) + " /s" : "";
      cells[3].textContent = c ? c.latency_ms.toFixed(0) + " ms" : "";
      cells[4].textContent = c && c.last_seen_ns ? Math.max(0, (status.stamp_ns - c.last_seen_ns) / 1e9).toFixed(1) + " s ago" : "never";
      cells[5].textContent = c ? c.dropped : "";
      cells[6].textContent = c ? c.late : "";
    });
    $("fusion-counts").textContent = `${status.frame_sets} frame sets fused, ${status.frame_sets_dropped} dropped` +
      (status.events_not_stored ? `, ${status.events_not_stored} events not stored` : "");
  }

  function onFusion(alive) {
    const f = $("fusion");
    f.textContent = alive === null || alive === undefined ? "fusion ?" : alive ? "fusion up" : "fusion DOWN";
    f.className = "pill " + (alive ? "ok" : alive === false ? "bad" : "");
  }

  // ---------------------------------------------------------------- the timeline

  async function drawTimeline() {
    let tl;
    try { tl = await VW.getJSON("/api/timeline"); } catch (e) { return; }
    const canvas = $("timeline");
    const rows = tl.people.length + (tl.visits.length ? 1 : 0);
    const rowH = 26, top = 18, left = 90;
    const width = canvas.clientWidth || 600;
    const height = top + Math.max(1, rows) * rowH + 4;
    if (canvas.width !== width) canvas.width = width;
    if (canvas.height !== height) canvas.height = height;
    const ctx = canvas.getContext("2d");
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.font = "12px sans-serif";
    let t0 = Infinity, t1 = tl.now_ns || 0;
    for (const p of tl.people) {
      for (const r of p.runs) { t0 = Math.min(t0, r[0]); t1 = Math.max(t1, r[1]); }
      for (const d of p.dwells) t0 = Math.min(t0, d[0]);
      for (const m of p.marks) t0 = Math.min(t0, m[0]);
    }
    for (const v of tl.visits) t0 = Math.min(t0, v.stamp_ns);
    if (!Number.isFinite(t0)) { ctx.fillStyle = "#777"; ctx.fillText("nothing yet today", left, top + 14); return; }
    t1 = Math.max(t1, t0 + 60e9);
    const xOf = (t) => left + (width - left - 8) * (t - t0) / (t1 - t0);
    ctx.fillStyle = "#555";
    for (let k = 0; k <= 4; k++) {
      const t = t0 + (t1 - t0) * k / 4;
      ctx.fillText(VW.clock(t), Math.min(xOf(t), width - 60), 12);
    }
    tl.people.forEach((p, i) => {
      const y = top + i * rowH;
      ctx.fillStyle = "#222"; ctx.fillText(p.label, 4, y + 15);
      for (const r of p.runs) {
        ctx.fillStyle = VW.POSTURE_COLOURS[r[2]] || "#888";
        ctx.fillRect(xOf(r[0]), y + 2, Math.max(1, xOf(r[1]) - xOf(r[0])), 12);
      }
      ctx.fillStyle = "#17becf";
      for (const d of p.dwells) {
        const x = xOf(d[0]), x2 = xOf(d[1] === null ? t1 : d[1]);
        ctx.fillRect(x, y + 16, Math.max(1, x2 - x), 5);
      }
      for (const m of p.marks) {
        ctx.fillStyle = st.alarmKinds.has(m[1]) ? "#d62728" : "#333";
        ctx.fillRect(xOf(m[0]) - 1, y, 2, 22);
      }
    });
    if (tl.visits.length) {
      const y = top + tl.people.length * rowH;
      ctx.fillStyle = "#222"; ctx.fillText("visits", 4, y + 15);
      ctx.fillStyle = "#9467bd";
      for (const v of tl.visits) {
        const since = (v.details && v.details.since_ns) || v.stamp_ns;
        ctx.fillRect(xOf(since), y + 4, Math.max(2, xOf(v.stamp_ns) - xOf(since)), 12);
      }
    }
  }

  function legend() {
    const box = $("timeline-legend");
    for (const p of ["standing", "sitting", "bending", "lying"]) {
      const s = VW.el("span", { class: "swatch posture-" + p }, p, box);
      s.style.borderColor = VW.POSTURE_COLOURS[p];
    }
    VW.el("span", { class: "swatch dwell" }, "at a hot spot", box);
  }

  // ---------------------------------------------------------------- the stream

  function connect() {
    const es = new EventSource("/api/stream");
    es.addEventListener("open", () => { $("link").textContent = "live"; $("link").className = "pill ok"; });
    es.addEventListener("error", () => {
      $("link").textContent = "reconnecting"; $("link").className = "pill bad";
      fetch("/api/plan", { credentials: "same-origin" }).then((r) => { if (r.status === 401) location.href = "/login"; });
    });
    es.addEventListener("snapshot", (m) => {
      const s = JSON.parse(m.data);
      for (const [id, pts] of Object.entries(s.trails || {})) {
        const mk = st.markers.get(Number(id)) || newMarker(Number(id));
        mk.points = pts.map((p) => [p[0], p[1], p[2]]);
      }
      onFrame(s.frame);
      onAlarms(s.alarms);
      onStatus(s.status);
      onFusion(s.fusion_alive);
      for (const e of s.recent || []) addEvent(e, true);
    });
    es.addEventListener("tracks", (m) => onFrame(JSON.parse(m.data)));
    es.addEventListener("event", (m) => addEvent(JSON.parse(m.data), true));
    es.addEventListener("alarms", (m) => onAlarms(JSON.parse(m.data)));
    es.addEventListener("status", (m) => onStatus(JSON.parse(m.data)));
    es.addEventListener("fusion", (m) => onFusion(JSON.parse(m.data).alive));
    es.addEventListener("resync", () => loadEvents());
  }

  async function main() {
    const info = await VW.getJSON("/api/plan");
    st.plan = info.plan;
    st.alarmKinds = new Set(info.alarms);
    st.trailNs = info.trail_s * 1e9;
    st.name = info.name;
    $("site").textContent = info.plan.site;
    document.title = "voxelwatch: " + info.plan.site;
    $("who").textContent = "signed in as " + info.name;
    for (const k of info.kinds) VW.el("option", { value: k }, k.replace("_", " "), $("kinds"));
    buildPlan(info.plan);
    legend();
    defaultSince();
    $("ack").addEventListener("click", acknowledge);
    $("sound").addEventListener("click", () => { if (st.audio) st.audio.resume().then(() => { $("sound").hidden = true; beep(); }); });
    document.addEventListener("click", () => { if (st.audio && st.audio.state !== "running") st.audio.resume(); });
    $("filter").addEventListener("submit", (ev) => { ev.preventDefault(); loadEvents(); });
    connect();
    await loadEvents();
    drawTimeline();
    setInterval(drawTimeline, 5000);
  }

  window.voxelwatchView = st;  // for people who debug the page
  main().catch((e) => { document.body.appendChild(VW.el("p", { class: "error" }, "The view could not start: " + e.message)); });
})();
