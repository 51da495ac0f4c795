// voxelwatch view: the installer's page of one camera. The mask is fetched as a PNG about twice a
// second (a new image replaces the old one only once it has loaded); the outlines come once.
"use strict";

(() => {
  const cam = decodeURIComponent(location.pathname.split("/").pop());
  const $ = (id) => document.getElementById(id);
  let image = null, maskCount = 0, failures = 0;

  function draw(info) {
    const svg = $("image");
    svg.setAttribute("viewBox", `0 0 ${info.width} ${info.height}`);
    image = VW.svg("image", { x: 0, y: 0, width: info.width, height: info.height, preserveAspectRatio: "none" }, svg);
    VW.svg("rect", { class: "frame", x: 0, y: 0, width: info.width, height: info.height }, svg);
    const lines = (list, cls) => {
      for (const line of list) VW.svg("polyline", { class: cls, points: line.map((p) => p.join(",")).join(" ") }, svg);
    };
    lines(info.floor, "floor");
    for (const h of info.hotspots) { lines(h.lines, "hotspot-line"); label(h, "hotspot-name"); }
    for (const d of info.doors) { lines(d.lines, "door-line"); label(d, "door-name"); }
    function label(area, cls) {
      const pts = area.lines.flat();
      if (!pts.length) return;
      const x = pts.reduce((s, p) => s + p[0], 0) / pts.length, y = pts.reduce((s, p) => s + p[1], 0) / pts.length;
      VW.svg("text", { class: cls, x, y, "text-anchor": "middle" }, svg).textContent = area.name;
    }
  }

  function health(info) {
    const body = $("health").tBodies[0];
    body.replaceChildren();
    const row = (k, v) => { const tr = VW.el("tr", {}, undefined, body); VW.el("th", {}, k, tr); VW.el("td", { "data-field": k }, v, tr); };
    row("camera", `${cam} (${info.modality}, ${info.width}x${info.height}, ${info.fps} fps)`);
    const s = info.status;
    if (!s) { row("state", "no report from the fusion server yet"); return; }
    row("state", s.state);
    row("rate", s.rate_hz.toFixed(1) + " masks/s");
    row("latency", s.latency_ms.toFixed(0) + " ms");
    row("clock offset", s.clock_offset_ms.toFixed(0) + " ms");
    row("received", s.received);
    row("dropped", s.dropped);
    row("late", s.late);
    row("undecodable", s.undecodable);
    if (s.consistency !== undefined && s.consistency !== null) {
      const v = typeof s.consistency === "number" ? s.consistency.toFixed(2) : JSON.stringify(s.consistency);
      row("consistency", v);
    }
    if (typeof s.view_deg === "number") {
      row("view moved", s.view_deg.toFixed(2) + " degrees since its reference picture");
    }
  }

  function nextMask() {
    const url = `/api/mask/${encodeURIComponent(cam)}.png?n=${maskCount++}`;
    const probe = new Image();
    probe.onload = () => {
      image.setAttribute("href", url);
      failures = 0;
      $("mask-note").textContent = "mask updated " + new Date().toLocaleTimeString();
      setTimeout(nextMask, 500);
    };
    probe.onerror = () => {
      failures += 1;
      $("mask-note").textContent = "no mask from this camera yet (is its worker running, and may this reader receive masks?)";
      setTimeout(nextMask, Math.min(5000, 500 * failures));
    };
    probe.src = url;
  }

  async function main() {
    const [plan, info] = await Promise.all([VW.getJSON("/api/plan"), VW.getJSON("/api/install/" + encodeURIComponent(cam))]);
    $("title").textContent = `${plan.plan.site}: camera ${cam}`;
    document.title = `voxelwatch: camera ${cam}`;
    for (const c of plan.cameras) {
      const a = VW.el("a", { href: "/install/" + encodeURIComponent(c.id), class: c.id === cam ? "current" : "" }, c.id, $("cams"));
      a.insertAdjacentText("afterend", " ");
    }
    draw(info);
    health(info);
    nextMask();
    setInterval(async () => { try { health(await VW.getJSON("/api/install/" + encodeURIComponent(cam))); } catch (e) { /* next time */ } }, 2000);
  }

  main().catch((e) => { document.body.appendChild(VW.el("p", { class: "error" }, "The page could not start: " + e.message)); });
})();
