"""The floor plan of a site: the geometry every picture of the home is drawn from.

:func:`plan_of` turns a :class:`common.site.Site` into a :class:`Plan`: the
volume's floor outline, hot spots, doors and occluders (floor polygons,
world frame, metres) and every camera's position and field of view on the
floor. The live view sends it to the browser as JSON (:meth:`Plan.to_dict`),
:func:`plan_svg` draws a finished run on it as a static SVG (the demo's
``run/plan.svg``), and the installer's page uses :func:`image_outlines` to
draw the floor and the hot spots into a camera's image.

A camera's floor field of view (:func:`floor_fov`) is the set of floor
points inside the volume that project into its image, taken on a fine grid
and outlined: the same test whatever the lens (a ceiling fisheye that sees
more than a half-space has no image border to cast onto the floor), and
what the carving itself asks of a camera. Pure geometry: no I/O beyond what
:meth:`Site.load_cameras` reads, no clock.
"""

from __future__ import annotations

import html
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from common.camera import Camera
    from common.messages import Event
    from common.site import Site

GRID_CELLS = 320
"""Grid cells along the floor's longer side when finding a field of view (2.5 cm in an 8 m room)."""

Polygon = list[tuple[float, float]]


@dataclass(frozen=True)
class PlanCamera:
    """One camera on the plan: ``position_m`` (x, y, z) of its optical centre, world frame, metres;
    ``heading_deg`` the direction its optical axis points on the floor (0 = +x, counter-clockwise,
    None when it looks straight down); ``fov`` its field of view on the floor, clipped to the volume."""

    id: str
    modality: str
    position_m: tuple[float, float, float]
    heading_deg: float | None
    fov: Polygon


@dataclass(frozen=True)
class Area:
    """A named floor polygon (hot spot, door or occluder); ``kind`` for hot spots, ``z_m`` for occluders."""

    name: str
    polygon: Polygon
    kind: str = ""
    z_m: tuple[float, float] | None = None


@dataclass(frozen=True)
class Plan:
    """Everything a floor plan shows that comes from the site file, world frame, metres."""

    site: str
    min_xy: tuple[float, float]
    max_xy: tuple[float, float]
    hotspots: list[Area] = field(default_factory=list)
    doors: list[Area] = field(default_factory=list)
    occluders: list[Area] = field(default_factory=list)
    cameras: list[PlanCamera] = field(default_factory=list)

    @property
    def outline(self) -> Polygon:
        """The volume's floor rectangle, counter-clockwise from ``min_xy``."""
        (x0, y0), (x1, y1) = self.min_xy, self.max_xy
        return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (lists of ``[x, y]``, metres, rounded to the millimetre)."""

        def poly(p: Polygon) -> list[list[float]]:
            return [[round(x, 3), round(y, 3)] for x, y in p]

        def area(a: Area) -> dict[str, Any]:
            out: dict[str, Any] = {"name": a.name, "polygon": poly(a.polygon)}
            if a.kind:
                out["kind"] = a.kind
            if a.z_m is not None:
                out["z_m"] = list(a.z_m)
            return out

        return {
            "site": self.site,
            "min_xy": list(self.min_xy),
            "max_xy": list(self.max_xy),
            "outline": poly(self.outline),
            "hotspots": [area(a) for a in self.hotspots],
            "doors": [area(a) for a in self.doors],
            "occluders": [area(a) for a in self.occluders],
            "cameras": [{"id": c.id, "modality": c.modality, "position_m": [round(v, 3) for v in c.position_m],
                         "heading_deg": None if c.heading_deg is None else round(c.heading_deg, 1),
                         "fov": poly(c.fov)} for c in self.cameras],
        }


def plan_of(site: "Site", cameras: Mapping[str, "Camera"] | None = None) -> Plan:
    """The plan of ``site``; ``cameras`` (id -> Camera) default to the site's calibrations
    (:meth:`Site.load_cameras`, which raises a SiteError naming a calibration it cannot read)."""
    cams = dict(cameras) if cameras is not None else site.load_cameras()
    lo = (float(site.volume.min_m[0]), float(site.volume.min_m[1]))
    hi = (float(site.volume.max_m[0]), float(site.volume.max_m[1]))
    placed = []
    for spec in site.cameras:
        cam = cams.get(spec.id)
        if cam is None:
            continue
        fwd = cam.forward
        heading = None if math.hypot(fwd[0], fwd[1]) < 1e-6 else math.degrees(math.atan2(fwd[1], fwd[0]))
        placed.append(PlanCamera(id=spec.id, modality=spec.modality,
                                 position_m=tuple(float(v) for v in cam.center),  # type: ignore[arg-type]
                                 heading_deg=heading, fov=floor_fov(cam, lo, hi)))
    return Plan(
        site=site.name, min_xy=lo, max_xy=hi,
        hotspots=[Area(h.name, _poly(h.polygon_m), kind=h.kind) for h in site.hotspots],
        doors=[Area(d.name, _poly(d.polygon_m)) for d in site.doors],
        occluders=[Area(o.name, _poly(o.polygon_m), z_m=(float(o.z_m[0]), float(o.z_m[1]))) for o in site.occluders],
        cameras=placed,
    )


def floor_fov(camera: "Camera", min_xy: Sequence[float], max_xy: Sequence[float], *,
              cells: int = GRID_CELLS, floor_z_m: float = 0.0) -> Polygon:
    """The part of the floor rectangle ``min_xy .. max_xy`` (metres) that ``camera`` sees.

    The floor points whose projection :meth:`Camera.project` calls valid (in
    front of the camera, inside the image), found on a grid of ``cells``
    cells along the rectangle's longer side, outlined (the largest region) and
    simplified. Returns the polygon's vertices ``[(x, y), ...]`` (world frame,
    metres, counter-clockwise), within a cell of the true outline; empty when
    the camera sees none of the rectangle.
    """
    import cv2

    if cells < 8:
        raise ValueError(f"cells must be at least 8, got {cells}")
    x0, y0 = float(min_xy[0]), float(min_xy[1])
    x1, y1 = float(max_xy[0]), float(max_xy[1])
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"max_xy {list(max_xy)} must exceed min_xy {list(min_xy)}")
    cell = max(x1 - x0, y1 - y0) / cells
    nx, ny = max(2, round((x1 - x0) / cell)), max(2, round((y1 - y0) / cell))
    sx, sy = (x1 - x0) / nx, (y1 - y0) / ny
    gx, gy = np.meshgrid(x0 + (np.arange(nx) + 0.5) * sx, y0 + (np.arange(ny) + 0.5) * sy)  # (ny, nx)
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, floor_z_m)], axis=1)
    _, valid = camera.project(pts)
    if not valid.any():
        return []
    seen = np.zeros((ny + 2, nx + 2), np.uint8)  # unseen cells all round: every outline closes
    seen[1:-1, 1:-1] = valid.reshape(ny, nx)
    contours, _ = cv2.findContours(seen, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    outline = max(contours, key=cv2.contourArea)
    outline = cv2.approxPolyDP(outline, 1.5, True).reshape(-1, 2).astype(np.float64)
    # a contour runs through the centres of the outermost seen cells
    poly = [(float(x0 + (u - 0.5) * sx), float(y0 + (v - 0.5) * sy)) for u, v in outline]
    if len(poly) < 3 or abs(_signed_area(poly)) < 1e-12:
        return []
    return poly if _signed_area(poly) > 0 else poly[::-1]


def image_outlines(site: "Site", camera: "Camera", *, step_m: float = 0.1) -> dict[str, Any]:
    """What the installer's page draws over one camera's mask, in that camera's pixels
    (full-resolution capture, ``camera.width x camera.height``).

    ``floor``: the volume's floor rectangle; ``hotspots``/``doors``: each
    ``{"name", "lines"}``. Each outline is a list of polylines ``[[u, v], ...]``:
    edges are sampled every ``step_m`` metres on the floor, so that lens
    distortion bends them as in the image, and broken where points fall out
    of view.
    """
    lo = site.volume.min_m
    hi = site.volume.max_m
    rect = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]

    def lines(poly: Sequence[tuple[float, float]]) -> list[list[list[float]]]:
        return _image_polylines(camera, poly, step_m)

    return {
        "camera": camera.id, "width": camera.width, "height": camera.height,
        "floor": lines(rect),
        "hotspots": [{"name": h.name, "lines": lines(h.polygon_m)} for h in site.hotspots],
        "doors": [{"name": d.name, "lines": lines(d.polygon_m)} for d in site.doors],
    }


# --------------------------------------------------------------------------- the static SVG

POSTURE_COLOURS = {"standing": "#2b7bb9", "walking": "#2b7bb9", "sitting": "#e69f00", "bending": "#8e6bbf",
                   "lying": "#d62728", "unknown": "#888888"}
"""Colour of each posture on a path (the live page uses the same ones)."""
EVENT_STYLE = {"fall": ("#d62728", "X"), "long_lie": ("#8b0000", "L"), "sit_down": ("#e69f00", "S"),
               "stand_up": ("#2b7bb9", "U"), "enter": ("#2ca02c", ">"), "exit": ("#2ca02c", "<"),
               "dwell_start": ("#1f77b4", "D"), "dwell_end": ("#1f77b4", "d"), "visit": ("#9467bd", "V"),
               "inactivity": ("#7f7f7f", "I"), "alarm_ack": ("#444444", "A")}
"""Colour and one-letter mark of each event kind on the plan."""


def plan_svg(site: "Site | Plan", tracks_rows: Any, events: Iterable["Event | Mapping[str, Any]"] = (),
             truth: Any = None, *, px_per_m: float = 90.0, title: str = "") -> str:
    """A finished run drawn on the floor plan, as SVG text (no other file needed to view it).

    site: a Site (its calibrations are loaded for the cameras' fields of view) or a :class:`Plan`.
    tracks_rows: the run's tracks: a ``TrackTable`` (:mod:`evaluation.io`), or rows
        ``(frame, stamp_ns, id, x, y, z_top, posture[, person])`` or dicts with those keys.
    events: Events (or their dicts); those with a place are marked where they happened.
    truth: the true tracks in the same forms, drawn as dashed black paths.
    Each person's path is drawn in segments coloured by posture.
    """
    plan = site if isinstance(site, Plan) else plan_of(site)
    rows = _rows(tracks_rows)
    truth_rows = _rows(truth) if truth is not None else []
    evs = [_event_dict(e) for e in events]
    (x0, y0), (x1, y1) = plan.min_xy, plan.max_xy
    margin = 0.4
    legend_h = 60
    width = (x1 - x0 + 2 * margin) * px_per_m
    height = (y1 - y0 + 2 * margin) * px_per_m + legend_h

    def pt(x: float, y: float) -> str:
        return f"{(x - x0 + margin) * px_per_m:.1f},{(y1 - y + margin) * px_per_m:.1f}"  # y up on the floor

    def polygon(p: Sequence[tuple[float, float]], attrs: str) -> str:
        return f'<polygon points="{" ".join(pt(x, y) for x, y in p)}" {attrs}/>'

    def text(x: float, y: float, s: str, attrs: str = "") -> str:
        return f'<text x="{pt(x, y).split(",")[0]}" y="{pt(x, y).split(",")[1]}" {attrs}>{html.escape(s)}</text>'

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0f}" height="{height:.0f}" '
           f'viewBox="0 0 {width:.0f} {height:.0f}" font-family="sans-serif" font-size="11">',
           f"<title>{html.escape(title or f'voxelwatch plan: {plan.site}')}</title>",
           f'<rect width="{width:.0f}" height="{height:.0f}" fill="#ffffff"/>']
    out.append('<g class="fov">')
    for cam in plan.cameras:
        if cam.fov:
            out.append(polygon(cam.fov, 'fill="#f2c94c" fill-opacity="0.06" stroke="#c9a227" stroke-opacity="0.35" '
                                        'stroke-width="1" stroke-dasharray="4 3"'))
    out.append("</g>")
    out.append(polygon(plan.outline, 'fill="none" stroke="#222" stroke-width="3"'))
    for a in plan.occluders:
        out.append(polygon(a.polygon, 'class="occluder" fill="#999" fill-opacity="0.35" stroke="#666" stroke-width="1"'))
    for a in plan.hotspots:
        out.append(polygon(a.polygon, 'class="hotspot" fill="#1f77b4" fill-opacity="0.15" stroke="#1f77b4"'))
        cx, cy = np.mean(a.polygon, axis=0)
        out.append(text(cx, cy, a.name, 'text-anchor="middle" fill="#0b3d6b"'))
    for a in plan.doors:
        out.append(polygon(a.polygon, 'class="door" fill="#2ca02c" fill-opacity="0.35" stroke="#1a601a"'))
        cx, cy = np.mean(a.polygon, axis=0)
        out.append(text(cx, cy, a.name, 'text-anchor="middle" fill="#1a601a"'))
    for cam in plan.cameras:
        x, y, _ = cam.position_m
        out.append(f'<circle class="camera" cx="{pt(x, y).split(",")[0]}" cy="{pt(x, y).split(",")[1]}" r="6" '
                   f'fill="#333"/>')
        out.append(text(x, y - 0.25, cam.id, 'text-anchor="middle" fill="#333"'))
    by_track: dict[str, list[tuple]] = {}
    for r in truth_rows:
        by_track.setdefault(r[2], []).append(r)
    for tid, path in by_track.items():
        out.append(f'<polyline class="truth" points="{" ".join(pt(r[3], r[4]) for r in path)}" fill="none" '
                   f'stroke="#000" stroke-width="1" stroke-dasharray="5 4" stroke-opacity="0.7"/>')
    by_track = {}
    for r in rows:
        by_track.setdefault(r[2], []).append(r)
    for tid, path in by_track.items():
        out.append(f'<g class="path" data-track="{html.escape(str(tid))}">')
        for posture, seg in _runs(path):
            out.append(f'<polyline points="{" ".join(pt(r[3], r[4]) for r in seg)}" fill="none" '
                       f'stroke="{POSTURE_COLOURS.get(posture, "#888888")}" stroke-width="2.5" '
                       f'stroke-linejoin="round" data-posture="{html.escape(posture)}"/>')
        last = path[-1]
        label = last[7] or f"#{tid}"
        out.append(text(last[3] + 0.12, last[4] + 0.12, label, 'fill="#000" font-weight="bold"'))
        out.append("</g>")
    for e in evs:
        if e.get("track", -1) < 0 or (e.get("x") in (None, 0.0) and e.get("y") in (None, 0.0)):
            continue
        colour, mark = EVENT_STYLE.get(e["kind"], ("#000", "?"))
        px, py = pt(float(e["x"]), float(e["y"])).split(",")
        out.append(f'<g class="event" data-kind="{html.escape(e["kind"])}"><circle cx="{px}" cy="{py}" r="8" '
                   f'fill="#fff" stroke="{colour}" stroke-width="2"/><text x="{px}" y="{float(py) + 4:.1f}" '
                   f'text-anchor="middle" fill="{colour}" font-weight="bold">{html.escape(mark)}</text>'
                   f'<title>{html.escape(e["kind"])} (track {e.get("track")}, frame {e.get("frame")})</title></g>')
    # legend
    ly = (y1 - y0 + 2 * margin) * px_per_m + 18
    lx = 10.0
    for name, colour in (("standing", POSTURE_COLOURS["standing"]), ("sitting", POSTURE_COLOURS["sitting"]),
                         ("bending", POSTURE_COLOURS["bending"]), ("lying", POSTURE_COLOURS["lying"])):
        out.append(f'<line x1="{lx}" y1="{ly}" x2="{lx + 20}" y2="{ly}" stroke="{colour}" stroke-width="3"/>'
                   f'<text x="{lx + 24}" y="{ly + 4}">{name}</text>')
        lx += 90
    if truth_rows:
        out.append(f'<line x1="{lx}" y1="{ly}" x2="{lx + 20}" y2="{ly}" stroke="#000" stroke-dasharray="5 4"/>'
                   f'<text x="{lx + 24}" y="{ly + 4}">truth</text>')
    lx, ly = 10.0, ly + 24
    for kind in sorted({e["kind"] for e in evs if e["kind"] in EVENT_STYLE}):
        colour, mark = EVENT_STYLE[kind]
        out.append(f'<text x="{lx}" y="{ly}" fill="{colour}" font-weight="bold">{html.escape(mark)}</text>'
                   f'<text x="{lx + 12}" y="{ly}">{html.escape(kind)}</text>')
        lx += 100
    out.append("</svg>")
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------- helpers


def _poly(points: Iterable[Sequence[float]]) -> Polygon:
    return [(float(x), float(y)) for x, y in points]


def _signed_area(points: Sequence[tuple[float, float]]) -> float:
    n = len(points)
    return 0.5 * sum(points[i][0] * points[(i + 1) % n][1] - points[(i + 1) % n][0] * points[i][1] for i in range(n))


def _image_polylines(camera: "Camera", polygon: Sequence[tuple[float, float]], step_m: float) -> list[list[list[float]]]:
    pts = []
    n = len(polygon)
    for i in range(n):
        (ax, ay), (bx, by) = polygon[i], polygon[(i + 1) % n]
        k = max(1, int(math.ceil(math.hypot(bx - ax, by - ay) / step_m)))
        for j in range(k):
            f = j / k
            pts.append((ax + f * (bx - ax), ay + f * (by - ay), 0.0))
    pts.append(pts[0])
    uv, valid = camera.project(np.asarray(pts, dtype=np.float64))
    lines: list[list[list[float]]] = []
    cur: list[list[float]] = []
    for (u, v), ok in zip(uv, valid):
        if ok:
            cur.append([round(float(u), 1), round(float(v), 1)])
        elif cur:
            if len(cur) >= 2:
                lines.append(cur)
            cur = []
    if len(cur) >= 2:
        lines.append(cur)
    return lines


def _runs(path: Sequence[tuple], max_gap_frames: int = 30) -> list[tuple[str, list[tuple]]]:
    """A path cut into runs of one posture: ``(posture, rows)``, each run ending on the next run's
    first row so that the drawn path has no holes; a gap of more than ``max_gap_frames`` ends a run."""
    runs: list[tuple[str, list[tuple]]] = []
    for a, b in zip(path, path[1:]):
        if b[0] - a[0] > max_gap_frames:
            continue
        if runs and runs[-1][0] == a[6] and runs[-1][1][-1] is a:
            runs[-1][1].append(b)
        else:
            runs.append((a[6], [a, b]))
    return runs


def _rows(table: Any) -> list[tuple]:
    """``(frame, stamp_ns, id, x, y, z_top, posture, person)`` tuples, sorted by (id, frame)."""
    if table is None:
        return []
    if hasattr(table, "frame") and hasattr(table, "track_id"):
        person = table.person if table.person is not None else [""] * len(table)
        rows = [(int(f), int(s), str(i), float(x), float(y), float(z), str(p), str(n))
                for f, s, i, x, y, z, p, n in zip(table.frame, table.stamp_ns, table.track_id, table.x, table.y,
                                                    table.z_top, table.posture, person)]
    else:
        rows = []
        for r in table:
            if isinstance(r, Mapping):
                rows.append((int(r["frame"]), int(r.get("stamp_ns", 0)), str(r["id"]), float(r["x"]), float(r["y"]),
                             float(r.get("z_top", 0.0)), str(r.get("posture", "unknown")), str(r.get("person") or "")))
            else:
                f, s, i, x, y, z, p, *rest = r
                rows.append((int(f), int(s), str(i), float(x), float(y), float(z), str(p),
                             str(rest[0]) if rest and rest[0] else ""))
    rows.sort(key=lambda r: (r[2], r[0]))
    return rows


def _event_dict(e: Any) -> dict[str, Any]:
    if isinstance(e, Mapping):
        return dict(e)
    return e.to_dict()
