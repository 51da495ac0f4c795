"""Pictures of a run: plan view and posture timeline, as PNG (the per-camera mask overlays
are the fusion server's: :func:`fusion_server.outputs.mask_overlay`).

:func:`plan_view` and :func:`timeline` draw with matplotlib (the ``plots``
extra), imported only when called, on a private figure (no pyplot state), and
write images of exactly ``size_px`` pixels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common import messages
from evaluation import io
from evaluation.tracking import clear_mot

DPI = 100
EVENT_MARKERS: Mapping[str, tuple[str, str]] = {  # kind -> (matplotlib marker, colour)
    "fall": ("X", "#d62728"),
    "long_lie": ("P", "#8c1010"),
    "sit_down": ("v", "#1f77b4"),
    "stand_up": ("^", "#17becf"),
    "enter": (">", "#2ca02c"),
    "exit": ("<", "#98df8a"),
    "dwell_start": ("s", "#9467bd"),
    "dwell_end": ("D", "#c5b0d5"),
    "visit": ("*", "#ff7f0e"),
    "inactivity": ("h", "#8c564b"),
}
OTHER_MARKER = ("o", "#7f7f7f")
POSTURE_LEVELS: Mapping[str, int] = {"unknown": 0, "lying": 1, "sitting": 2, "bending": 3, "standing": 4}


@dataclass(frozen=True)
class SiteGeometry:
    """What the pictures need from a site: floor box and named polygons, world frame, metres."""

    min_xy_m: tuple[float, float] | None = None
    max_xy_m: tuple[float, float] | None = None
    hotspots: list[tuple[str, str, np.ndarray]] = field(default_factory=list)  # name, kind, (K, 2)
    doors: list[tuple[str, np.ndarray]] = field(default_factory=list)  # name, (K, 2)


def plan_view(
    run_dir: str | Path,
    site: Any,
    out_png: str | Path,
    truth_dir: str | Path | None = None,
    *,
    size_px: tuple[int, int] = (1000, 800),
    heat_cell_m: float = 0.1,
) -> Path:
    """Draw the plan view of a run and write it as a PNG of ``size_px`` (width, height) pixels.

    Shows the monitored volume's floor outline, hot spots (with names) and
    doors from ``site`` (a :class:`common.site.Site`, a dict of the same
    shape, or None), the floor occupancy heat (frames spent per
    ``heat_cell_m`` cell, log scale), the run's tracks coloured by id, the
    truth paths dashed when ``truth_dir`` is given, and the run's events with
    one symbol per kind.
    """
    if not heat_cell_m > 0:
        raise ValueError(f"heat_cell_m must be positive, got {heat_cell_m}")
    mpl = _matplotlib("plan_view")
    geom = site_geometry(site)
    run = io.read_run_tracks(run_dir)
    # camera-health events have no place on the floor
    events = [e for e in io.read_run_events(run_dir, required=False) if e.kind not in messages.CAMERA_EVENT_KINDS]
    truth = io.read_truth_tracks(truth_dir) if truth_dir is not None else None

    fig, canvas = _figure(mpl, size_px)
    ax = fig.add_subplot(1, 1, 1)
    (x0, y0), (x1, y1) = _bounds(geom, [t for t in (run, truth) if t is not None], events)

    if len(run):
        nx = max(1, int(np.ceil((x1 - x0) / heat_cell_m)))
        ny = max(1, int(np.ceil((y1 - y0) / heat_cell_m)))
        heat, _, _ = np.histogram2d(run.x, run.y, bins=[nx, ny], range=[[x0, x0 + nx * heat_cell_m], [y0, y0 + ny * heat_cell_m]])
        if heat.any():
            shown = np.ma.masked_equal(np.log1p(heat.T), 0.0)
            img = ax.imshow(shown, origin="lower", extent=(x0, x0 + nx * heat_cell_m, y0, y0 + ny * heat_cell_m),
                            cmap="YlOrRd", alpha=0.75, interpolation="nearest", zorder=1)
            bar = fig.colorbar(img, ax=ax, fraction=0.04, pad=0.02)
            bar.set_label("log(1 + frames per cell)")

    if geom.min_xy_m is not None and geom.max_xy_m is not None:
        (vx0, vy0), (vx1, vy1) = geom.min_xy_m, geom.max_xy_m
        ax.add_patch(mpl.patches.Rectangle((vx0, vy0), vx1 - vx0, vy1 - vy0, fill=False, edgecolor="black", linewidth=2, zorder=2))
    for name, kind, poly in geom.hotspots:
        ax.add_patch(mpl.patches.Polygon(poly, closed=True, facecolor="#1f77b4", alpha=0.18, edgecolor="#1f77b4", zorder=2))
        cx, cy = poly.mean(axis=0)
        ax.text(cx, cy, f"{name}\n({kind})" if kind else name, ha="center", va="center", fontsize=8, color="#0b3d6b", zorder=6)
    for name, poly in geom.doors:
        ax.add_patch(mpl.patches.Polygon(poly, closed=True, facecolor="#2ca02c", alpha=0.3, edgecolor="#1a601a", hatch="//", zorder=2))
        cx, cy = poly.mean(axis=0)
        ax.text(cx, cy, name, ha="center", va="center", fontsize=8, color="#1a601a", zorder=6)

    if truth is not None:
        first = True
        for tid in np.unique(truth.track_id):
            xs, ys = _path(truth, tid)
            ax.plot(xs, ys, linestyle="--", color="black", linewidth=0.8, alpha=0.7, zorder=3,
                    label="truth paths" if first else None)
            first = False
    colours = mpl.colormaps["tab20"]
    for k, tid in enumerate(np.unique(run.track_id)):
        xs, ys = _path(run, tid)
        colour = colours(k % 20)
        ax.plot(xs, ys, color=colour, linewidth=1.4, zorder=4)
        last = np.flatnonzero(~np.isnan(xs))
        if last.size:
            ax.annotate(str(tid), (xs[last[-1]], ys[last[-1]]), fontsize=7, color=colour, zorder=6)

    for kind in dict.fromkeys(e.kind for e in events):
        pts = np.array([(e.x, e.y) for e in events if e.kind == kind and e.x is not None])
        if pts.size:
            marker, colour = EVENT_MARKERS.get(kind, OTHER_MARKER)
            ax.scatter(pts[:, 0], pts[:, 1], marker=marker, s=90, color=colour, edgecolors="black", linewidths=0.6,
                       zorder=7, label=kind)

    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"plan view: {Path(run_dir).name}  ({len(np.unique(run.track_id))} tracks, {len(events)} events)")
    ax.grid(True, linewidth=0.3, alpha=0.5)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    return _save(fig, canvas, out_png)


def timeline(
    run_dir: str | Path,
    truth_dir: str | Path,
    out_png: str | Path,
    *,
    size_px: tuple[int, int] | None = None,
    radius_m: float = 0.5,
) -> Path:
    """Per truth person, posture over time against the run, with events; writes a PNG.

    One row per truth person: the truth posture as a black line, the posture
    of the run track matched to them (CLEAR-MOT, ``radius_m``) as dots
    coloured by run id, truth events as dashed vertical lines and the matched
    run tracks' events as symbols at the top. Time in seconds when the frame
    rate is known (``meta.json`` or stamps), else frames. ``size_px``
    defaults to (1200, 120 + 180 x rows).
    """
    mpl = _matplotlib("timeline")
    truth = io.read_truth_tracks(truth_dir)
    run = io.read_run_tracks(run_dir)
    truth_events = io.read_truth_events(truth_dir) or []
    run_events = io.read_run_events(run_dir, required=False)
    fps = io.read_truth_meta(truth_dir).fps or truth.fps_from_stamps() or run.fps_from_stamps()
    scale, unit = (1.0 / fps, "s") if fps else (1.0, "frame")

    people = [str(p) for p in np.unique(truth.track_id)]
    rows = max(1, len(people))
    size_px = size_px or (1200, 120 + 180 * rows)
    fig, canvas = _figure(mpl, size_px)
    matches = clear_mot(truth, run, radius_m=radius_m).pairs
    colours = mpl.colormaps["tab10"]
    run_ids = {str(r): k for k, r in enumerate(np.unique(run.track_id))}
    levels = sorted(POSTURE_LEVELS.items(), key=lambda kv: kv[1])

    all_frames = np.concatenate([truth.frame, run.frame])
    lo, hi = (int(all_frames.min()), int(all_frames.max())) if all_frames.size else (0, 1)
    if not people:
        ax = fig.add_subplot(1, 1, 1)
        ax.text(0.5, 0.5, "no people in the truth", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
    for row, person in enumerate(people):
        ax = fig.add_subplot(rows, 1, row + 1)
        sel = truth.track_id == person
        frames = truth.frame[sel]
        lv = np.array([POSTURE_LEVELS[p] for p in truth.posture[sel]], dtype=float)
        t_x, t_y = _broken(frames, lv)
        ax.step(t_x * scale, t_y, where="post", color="black", linewidth=2.0, label="truth")
        mine = truth.track_id[matches.truth_row] == person
        m_frames = matches.frame[mine]
        m_runs = run.track_id[matches.run_row[mine]]
        m_lv = np.array([POSTURE_LEVELS[p] for p in run.posture[matches.run_row[mine]]], dtype=float)
        for rid in dict.fromkeys(m_runs.tolist()):
            k = m_runs == rid
            ax.scatter(m_frames[k] * scale, m_lv[k] + 0.15, s=6, color=colours(run_ids[rid] % 10), label=f"run {rid}")
        for e in truth_events:
            if str(e.track) == person:
                marker, colour = EVENT_MARKERS.get(e.kind, OTHER_MARKER)
                ax.axvline(e.frame * scale, color=colour, linestyle="--", linewidth=1.0)
                ax.text(e.frame * scale, 4.55, e.kind, rotation=90, fontsize=7, va="bottom", ha="right", color=colour)
        linked = set(m_runs.tolist())
        for e in run_events:
            if e.track >= 0 and str(e.track) in linked:
                marker, colour = EVENT_MARKERS.get(e.kind, OTHER_MARKER)
                ax.scatter([e.frame * scale], [4.45], marker=marker, s=60, color=colour, edgecolors="black", linewidths=0.5, zorder=5)
        ax.set_yticks([v for _, v in levels], [name for name, _ in levels], fontsize=8)
        ax.set_ylim(-0.5, 5.2)
        ax.set_ylabel(person)
        ax.grid(True, axis="x", linewidth=0.3, alpha=0.5)
        ax.set_xlim((lo - 1) * scale, (hi + 1) * scale)  # one time axis for every row
        ax.legend(loc="lower right", fontsize=7, ncol=4, framealpha=0.8)
        if row == rows - 1:
            ax.set_xlabel(f"time ({unit})")
    fig.suptitle(f"posture timeline: {Path(run_dir).name} against {Path(truth_dir).name}")
    return _save(fig, canvas, out_png)


def site_geometry(site: Any) -> SiteGeometry:
    """The floor box, hot spots and doors of a :class:`common.site.Site`, a dict of that shape, or None."""
    if site is None:
        return SiteGeometry()
    volume = _get(site, "volume")
    lo = _get(volume, "min_m") if volume is not None else None
    hi = _get(volume, "max_m") if volume is not None else None
    min_xy = max_xy = None
    if lo is not None and hi is not None:
        lo, hi = _floats(lo, "volume.min_m"), _floats(hi, "volume.max_m")
        if len(lo) < 2 or len(hi) < 2 or hi[0] <= lo[0] or hi[1] <= lo[1]:
            raise ValueError(f"site volume: max_m {hi} must exceed min_m {lo} in x and y")
        min_xy, max_xy = (lo[0], lo[1]), (hi[0], hi[1])
    hotspots = []
    for k, spot in enumerate(_get(site, "hotspots") or []):
        name = str(_get(spot, "name") or f"hotspot {k}")
        hotspots.append((name, str(_get(spot, "kind") or ""), _polygon(_get(spot, "polygon_m"), f"hotspots[{k}].polygon_m")))
    doors = []
    for k, door in enumerate(_get(site, "doors") or []):
        name = str(_get(door, "name") or f"door {k}")
        doors.append((name, _polygon(_get(door, "polygon_m"), f"doors[{k}].polygon_m")))
    return SiteGeometry(min_xy_m=min_xy, max_xy_m=max_xy, hotspots=hotspots, doors=doors)


# ---------------------------------------------------------------- helpers


class _Mpl:
    """The matplotlib pieces the pictures use, imported on first use."""

    def __init__(self) -> None:
        import matplotlib
        import matplotlib.patches
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.colormaps = matplotlib.colormaps
        self.patches = matplotlib.patches
        self.Figure = Figure
        self.FigureCanvasAgg = FigureCanvasAgg


def _matplotlib(what: str) -> _Mpl:
    try:
        return _Mpl()
    except ImportError as exc:
        raise ImportError(
            f"{what} draws with matplotlib, which is not installed ({exc}); "
            "install the plots extra: pip install 'voxelwatch[plots]'"
        ) from None


def _figure(mpl: _Mpl, size_px: Sequence[int]):
    w, h = (int(v) for v in size_px)
    if w < 100 or h < 100:
        raise ValueError(f"size_px must be at least 100 x 100 pixels, got {tuple(size_px)}")
    fig = mpl.Figure(figsize=(w / DPI, h / DPI), dpi=DPI, layout="constrained")
    return fig, mpl.FigureCanvasAgg(fig)


def _save(fig, canvas, out_png: str | Path) -> Path:
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    canvas.draw()
    fig.savefig(out_png, dpi=DPI, format="png")  # no tight bbox: the PNG keeps size_px exactly
    return out_png


def _bounds(geom: SiteGeometry, tables: list[io.TrackTable], events: list[io.Event]) -> tuple[tuple[float, float], tuple[float, float]]:
    """Plot extent: the site's floor box, widened to show any position outside it (0.5 m margin)."""
    xs = [t.x for t in tables if len(t)] + [np.array([e.x for e in events if e.x is not None])]
    ys = [t.y for t in tables if len(t)] + [np.array([e.y for e in events if e.y is not None])]
    x = np.concatenate(xs) if xs else np.zeros(0)
    y = np.concatenate(ys) if ys else np.zeros(0)
    pts_lo = (float(x.min()) - 0.5, float(y.min()) - 0.5) if x.size else None
    pts_hi = (float(x.max()) + 0.5, float(y.max()) + 0.5) if x.size else None
    if geom.min_xy_m is not None:
        lo = (geom.min_xy_m[0] - 0.2, geom.min_xy_m[1] - 0.2)
        hi = (geom.max_xy_m[0] + 0.2, geom.max_xy_m[1] + 0.2)
        if pts_lo is not None:
            lo = (min(lo[0], pts_lo[0]), min(lo[1], pts_lo[1]))
            hi = (max(hi[0], pts_hi[0]), max(hi[1], pts_hi[1]))
        return lo, hi
    if pts_lo is not None:
        return pts_lo, pts_hi
    return (0.0, 0.0), (1.0, 1.0)


def _path(table: io.TrackTable, tid: str) -> tuple[np.ndarray, np.ndarray]:
    """x, y of one id in frame order, NaN between frames that are not consecutive (a break in the line)."""
    sel = table.track_id == tid
    frames, x, y = table.frame[sel], table.x[sel], table.y[sel]
    _, xs = _broken(frames, x)
    _, ys = _broken(frames, y)
    return xs, ys


def _broken(frames: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Insert a NaN after every gap in ``frames`` so lines do not bridge absences."""
    if frames.size < 2:
        return frames.astype(float), values.astype(float)
    gaps = np.flatnonzero(np.diff(frames) > 1) + 1
    f = np.insert(frames.astype(float), gaps, np.nan)
    v = np.insert(values.astype(float), gaps, np.nan)
    return f, v


def _get(obj: Any, name: str) -> Any:
    if obj is None:
        return None
    if isinstance(obj, Mapping):
        return obj.get(name)
    return getattr(obj, name, None)


def _floats(value: Any, what: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"site {what}: expected numbers, got {value!r}") from None
    if not all(np.isfinite(out)):
        raise ValueError(f"site {what}: must be finite, got {value!r}")
    return out


def _polygon(value: Any, what: str) -> np.ndarray:
    try:
        poly = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"site {what}: expected a list of [x, y] points, got {value!r}") from None
    if poly.ndim != 2 or poly.shape[1] != 2 or poly.shape[0] < 3 or not np.isfinite(poly).all():
        raise ValueError(f"site {what}: expected at least 3 finite [x, y] points, got {value!r}")
    return poly
