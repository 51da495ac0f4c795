"""What the fusion server watches, kept so that a restart forgets no one.

A :class:`Snapshot` is the small state a restarted server needs to go on
where the last one stopped: the confirmed people (label, enrolled name,
place, posture, appearance model, and what the fall detector knows of them:
since when they are low and on the floor, whether their ``fall`` and
``long_lie`` were raised) and the hold boxes then in force. The live server
writes one to its event store every :data:`SNAPSHOT_EVERY_S` and reads it
at start (:meth:`~fusion_server.node.FusionNode.restore`): it sends the holds
at once, and the people are taken back by the first tracks confirmed where
they were (:meth:`~fusion_server.pipeline.FusionPipeline.restore`). A person
lying on the floor keeps their label, the time they went down, and their
``long_lie`` comes at its time, once.

The tracker's particles, the dwell and visit timers and the sit/stand state
are not kept: the people are found again from the masks, which the workers
keep (they hold their boxes while no server is live).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any

SNAPSHOT_EVERY_S = 1.0
"""How often the live server writes its snapshot (seconds of frame time)."""
FORMAT = 1
_FALL_FIELDS = ("low_since_ns", "floor_since_ns", "fall_emitted", "long_lie_emitted", "drop", "drop_series", "upright_ns")


@dataclass(frozen=True)
class Watched:
    """One confirmed person of a snapshot. ``fall``: the fall detector's state of them (the
    fields of :data:`_FALL_FIELDS`), None when they were not low. ``model``: their appearance
    model (:meth:`~common.appearance.AppearanceModel.to_dict`), None before it has one."""

    label: int
    x: float
    y: float
    posture: str | None = None
    name: str | None = None
    model: dict | None = None
    fall: dict | None = None


@dataclass(frozen=True)
class Snapshot:
    """The people a server watched at ``stamp_ns`` and the hold boxes it had sent, per camera."""

    stamp_ns: int
    people: tuple[Watched, ...] = ()
    holds: dict[str, list[tuple[int, int, int, int]]] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps({"format": FORMAT, "stamp_ns": self.stamp_ns, "people": [asdict(p) for p in self.people],
                           "holds": {cam: [list(b) for b in boxes] for cam, boxes in self.holds.items()}},
                          separators=(",", ":"))

    @classmethod
    def from_json(cls, text: str, *, where: str = "snapshot") -> "Snapshot":
        """The snapshot ``text`` holds; ValueError naming ``where`` and the problem."""
        try:
            d = json.loads(text)
            if not isinstance(d, dict) or d.get("format") != FORMAT:
                raise ValueError(f"format must be {FORMAT}, got {d.get('format') if isinstance(d, dict) else d!r}")
            people = tuple(_watched(p) for p in d["people"])
            holds = {str(cam): [_box(b) for b in boxes] for cam, boxes in d["holds"].items()}
            return cls(stamp_ns=int(d["stamp_ns"]), people=people, holds=holds)
        except KeyError as exc:
            raise ValueError(f"{where}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"{where}: {exc}") from None


def _watched(d: Any) -> Watched:
    p = Watched(label=int(d["label"]), x=float(d["x"]), y=float(d["y"]), posture=d.get("posture"),
                name=d.get("name"), model=d.get("model"), fall=d.get("fall"))
    if p.label <= 0 or not (math.isfinite(p.x) and math.isfinite(p.y)):
        raise ValueError(f"person {d!r}: a positive label and a finite place are needed")
    if p.fall is not None and not set(p.fall) <= set(_FALL_FIELDS):
        raise ValueError(f"person {p.label}: unknown fall fields {sorted(set(p.fall) - set(_FALL_FIELDS))}")
    return p


def _box(b: Any) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = (int(v) for v in b)
    return (x0, y0, x1, y1)
