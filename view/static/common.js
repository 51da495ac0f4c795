// voxelwatch view: helpers shared by the live page and the installer's page.
"use strict";

const VW = (() => {
  const SVGNS = "http://www.w3.org/2000/svg";
  const POSTURE_COLOURS = {
    standing: "#2b7bb9", walking: "#2b7bb9", sitting: "#e69f00", bending: "#8e6bbf",
    lying: "#d62728", unknown: "#888888",
  };

  function svg(tag, attrs, parent) {
    const el = document.createElementNS(SVGNS, tag);
    for (const [k, v] of Object.entries(attrs || {})) el.setAttribute(k, v);
    if (parent) parent.appendChild(el);
    return el;
  }

  function el(tag, attrs, text, parent) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    if (text !== undefined && text !== null) e.textContent = String(text);
    if (parent) parent.appendChild(e);
    return e;
  }

  function clock(ns) {
    const d = new Date(Number(ns) / 1e6);
    return d.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit" });
  }

  function dateTime(ns) {
    const d = new Date(Number(ns) / 1e6);
    return d.toLocaleDateString([], { month: "short", day: "numeric" }) + " " + clock(ns);
  }

  async function getJSON(url, options) {
    const r = await fetch(url, Object.assign({ credentials: "same-origin", cache: "no-store" }, options || {}));
    if (r.status === 401) { window.location.href = "/login?next=" + encodeURIComponent(location.pathname); throw new Error("not logged in"); }
    let body = null;
    try { body = await r.json(); } catch (e) { body = null; }
    if (!r.ok) throw new Error((body && body.error) || (r.status + " " + r.statusText));
    return body;
  }

  function polyPoints(points, fn) {
    return points.map((p) => fn(p[0], p[1]).join(",")).join(" ");
  }

  return { svg, el, clock, dateTime, getJSON, polyPoints, POSTURE_COLOURS };
})();
