"""Enrolment: a resident's appearance model learnt from a clip of them alone.

The clip is replayed through the site's own pipeline, recognising nobody;
the identity keeper then holds a model (colour histograms by body band and
the standing height, :class:`~common.appearance.AppearanceModel`) for
every person it saw. The enrolment is the model of the person seen the most,
by the frames their torso was learnt from, and only when

* that person was learnt from at least ``min_torso_frames`` frames, and
* nobody else was learnt from ``max_second_share`` of that or more (the clip
  must show the resident alone: with two people about, which one is the
  resident is a guess).

The file (:func:`enrolment_dict`) is the model's ``to_dict()`` with the
name; it holds histograms and numbers only, never an image. The site file
names it under ``[[enrolled]]``.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from common import appearance
from common.site import Site, check_person_name
from common.appearance import AppearanceModel

MIN_TORSO_FRAMES = 30
"""Fewest frames the enrolled person's torso must be learnt from (10 s of a person in view
at the default 3 descriptor requests a second)."""
MAX_SECOND_SHARE = 0.5
"""A second person learnt from this share of the first's torso frames or more refuses the clip."""

_TORSO = appearance.BANDS.index("torso")


class EnrolmentError(ValueError):
    """A clip that cannot enrol anyone; the message says why and what to do."""


@dataclass(frozen=True)
class Enrolment:
    """What an enrolment learnt: the chosen person's label and model, how many people
    were seen and over how many frame sets."""

    name: str
    label: int
    model: AppearanceModel
    people_seen: int
    frames: int

    def summary(self) -> str:
        bands = ", ".join(f"{band} {int(n)}" for band, n in zip(appearance.BANDS, self.model.frames))
        height = f"{self.model.height_m:.2f} m tall" if math.isfinite(self.model.height_m) else "height unknown"
        return (f"{self.name}: {self.frames} frame sets, {self.people_seen} people seen; "
                f"frames learnt {bands}; {height}")


def choose_model(models: Mapping[int, AppearanceModel], *, min_torso_frames: int = MIN_TORSO_FRAMES,
                 max_second_share: float = MAX_SECOND_SHARE) -> tuple[int, AppearanceModel]:
    """The label and model of the person learnt the most (torso frames), or
    :class:`EnrolmentError` when nobody was learnt well enough or a second person was
    learnt nearly as much. ``models``: label -> model of everyone the keeper saw."""
    ranked = sorted(models.items(), key=lambda item: (-item[1].frames[_TORSO], item[0]))
    if not ranked or ranked[0][1].frames[_TORSO] < min_torso_frames:
        best = int(ranked[0][1].frames[_TORSO]) if ranked else 0
        raise EnrolmentError(
            f"nobody was learnt well enough: the person seen the most has {best} torso frames, "
            f"{min_torso_frames} are needed; use a longer clip of the resident standing or walking "
            "where the cameras see them")
    label, model = ranked[0]
    if len(ranked) > 1:
        second_label, second = ranked[1]
        if second.frames[_TORSO] >= max_second_share * model.frames[_TORSO]:
            raise EnrolmentError(
                f"the clip shows more than one person: a second person was learnt from "
                f"{int(second.frames[_TORSO])} torso frames against {int(model.frames[_TORSO])} for the person "
                "seen the most; enrol from a clip of the resident alone")
    return label, model


def enrolment_dict(name: str, model: AppearanceModel) -> dict:
    """The enrolment file's content: ``{"name": ..., **model.to_dict()}``."""
    return {"name": name, **model.to_dict()}


def enrol(
    site: Site,
    name: str,
    out_path: str | Path,
    *,
    input_dir: str | Path | None = None,
    synthetic: str | None = None,
    seed: int = 0,
    max_frames: int | None = None,
    cache_dir: str | Path | None = None,
    progress: Callable | None = None,
) -> Enrolment:
    """Replay a clip (``input_dir`` or ``synthetic``, as :func:`fusion_server.replay.replay`
    takes them) through the site's pipeline recognising nobody, choose the resident's
    model (:func:`choose_model`) and write it to ``out_path`` as JSON. Nothing is
    written when the clip is refused (:class:`EnrolmentError`)."""
    from fusion_server.pipeline import FusionPipeline
    from fusion_server.replay import replay

    try:
        name = check_person_name(name)
    except ValueError as exc:
        raise EnrolmentError(f"--name: {exc}") from None
    cameras = site.load_cameras()
    pipeline = FusionPipeline.from_site(site, cameras=cameras, cache_dir=cache_dir, seed=seed, residents=())
    with tempfile.TemporaryDirectory(prefix="voxelwatch-enrol-") as work:
        summary = replay(site, work, input_dir=input_dir, synthetic=synthetic, max_frames=max_frames, seed=seed,
                         cache_dir=cache_dir, progress=progress, pipeline=pipeline)
    models = pipeline.identity.models()
    label, model = choose_model(models)
    _write_json(Path(out_path), enrolment_dict(name, model))
    return Enrolment(name=name, label=label, model=model, people_seen=len(models), frames=summary.frames)


def _write_json(path: Path, obj: dict) -> None:
    """Write ``obj`` to ``path`` whole or not at all (a temporary file renamed over it)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                json.dump(obj, fh, indent=1, allow_nan=False)
                fh.write("\n")
            os.chmod(tmp, 0o644)  # read by the fusion server's own user
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        raise EnrolmentError(f"enrolment file {path}: cannot write: {exc.strerror or exc}") from None
