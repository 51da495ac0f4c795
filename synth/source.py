"""The synthetic house as a frame source: one camera of one scenario, frame by frame.

``SyntheticCamera(scenario, cam_id, seed)`` renders frame ``index`` as a pure
function of (scenario, seed, camera, index), so each camera worker renders
its own camera independently and any frame can be rendered on its own
(random access, no state carried between frames). ``modality`` makes it a
thermal (``(H, W) uint16`` centi-kelvin), range (``(H, W) uint16`` millimetres)
or near-infrared camera instead of a colour one
(:func:`synth.render.frame_for`); the room's air drifts as
:func:`synth.sensors.ambient_c` says.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from camera_worker.sources import Frame, FrameSource, SourceError, check_fps, recorded_stamp_ns
from common.camera import Camera
from synth.degrade import CameraMove
from synth.render import MODALITIES, CameraRenderer, frame_for
from synth.scenario import Scenario, ScenarioSpec
from synth.scenarios import DEFAULT_SCENARIO, get_scenario
from synth.scene import default_cameras
from synth.sensors import ambient_c

BACKGROUND_S = 3.0
_FRAME_STREAM, _BACKGROUND_STREAM = 0, 1


class SyntheticCamera:
    """Frames of one camera of a synthetic scenario.

    scenario: a library name, a :class:`ScenarioSpec` or a compiled :class:`Scenario`.
    cam_id: camera id (cam1..cam5 in the default site).
    seed: people's variations, lighting and noise (ignored for the people of an
        already compiled Scenario, which keeps its own).
    site: optional :class:`common.site.Site` or site file path whose calibration of
        ``cam_id`` is used instead of the default camera.
    camera: optional :class:`Camera` used as is (overrides ``site``), e.g. a scaled-down
        default camera for fast tests.
    noise_std: sensor noise, grey levels. shadows: draw cast shadows.
    modality: 'colour' (default), 'infrared', 'thermal' or 'depth'.
    moved: the camera knocked out of place mid-run (:class:`synth.degrade.CameraMove`):
        from its frame on, frames are rendered through the moved camera (the calibration
        anyone reads from the site stays the old one). The background clip is before it.
    """

    def __init__(
        self,
        scenario: str | ScenarioSpec | Scenario = DEFAULT_SCENARIO,
        cam_id: str = "cam1",
        seed: int = 0,
        site=None,
        *,
        camera: Camera | None = None,
        noise_std: float = 2.5,
        shadows: bool = True,
        background_s: float = BACKGROUND_S,
        modality: str = "colour",
        moved: CameraMove | None = None,
    ) -> None:
        if modality not in MODALITIES:
            raise ValueError(f"modality must be one of {', '.join(MODALITIES)}, got {modality!r}")
        self.modality = modality
        self.scenario = get_scenario(scenario, seed)
        self.seed = int(seed)
        if camera is None:
            camera = _site_camera(site, cam_id) if site is not None else _default_camera(cam_id)
        elif camera.id != cam_id:
            raise ValueError(f"camera id {camera.id!r} does not match cam_id {cam_id!r}")
        self.camera = camera
        self.cam_id = cam_id
        self.renderer = CameraRenderer(camera, self.scenario.room, seed=self.seed, noise_std=noise_std, shadows=shadows,
                                       colour=modality in ("colour", "infrared"))
        self.moved = moved
        self._moved_renderer: CameraRenderer | None = None
        self._renderer_args = dict(seed=self.seed, noise_std=noise_std, shadows=shadows,
                                   colour=modality in ("colour", "infrared"))
        self.n_background_frames = int(round(background_s * self.scenario.fps))

    @property
    def n_frames(self) -> int:
        return self.scenario.n_frames

    @property
    def fps(self) -> float:
        return self.scenario.fps

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    def stamp_ns(self, index: int) -> int:
        """Capture time of frame ``index``: ``start_ns + round(index * 1e9 / fps)``."""
        return self.scenario.stamp_ns(index)

    def frame(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index``: BGR (H, W, 3) uint8 (a thermal or depth camera: (H, W) uint16) and the
        true person mask (H, W) uint8 (255 = person)."""
        bgr, labels = self.frame_labels(index)
        return bgr, np.where(labels > 0, np.uint8(255), np.uint8(0))

    def frame_labels(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``index``: BGR (H, W, 3) uint8 and the visible person id per pixel (H, W) uint8 (0 = nobody)."""
        self._check(index, self.n_frames)
        sc = self.scenario
        renderer = self._renderer_at(int(index))
        if self.modality == "colour":
            return renderer.render(sc.bodies(index), sc.gain(index), (_FRAME_STREAM, int(index)))
        return frame_for(renderer, self.modality, sc.bodies(index), (_FRAME_STREAM, int(index)),
                         gain=sc.gain(index), ambient_c=ambient_c(self.seed, index / self.fps))

    def background_frame(self, index: int) -> np.ndarray:
        """Frame ``index`` (0..n_background_frames-1) of a clip of the empty room recorded just before
        the scenario (same lighting drift and noise statistics): BGR (H, W, 3) uint8."""
        self._check(index, self.n_background_frames)
        t = (index - self.n_background_frames) / self.fps
        if self.modality == "colour":
            return self.renderer.background(float(self.scenario.gain_at(t)), (_BACKGROUND_STREAM, int(index)))
        return frame_for(self.renderer, self.modality, [], (_BACKGROUND_STREAM, int(index)),
                         gain=float(self.scenario.gain_at(t)), ambient_c=ambient_c(self.seed, t))[0]

    def frames(self, start: int = 0, stop: int | None = None):
        """Iterate ``(index, stamp_ns, bgr, mask)`` over frames ``start..stop-1``."""
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        for i in range(start, stop):
            bgr, mask = self.frame(i)
            yield i, self.stamp_ns(i), bgr, mask

    def _renderer_at(self, index: int) -> CameraRenderer:
        """The renderer of frame ``index``: the moved camera's from the move on."""
        if self.moved is None or index < self.moved.first:
            return self.renderer
        if self._moved_renderer is None:
            self._moved_renderer = CameraRenderer(self.moved.apply(self.camera), self.scenario.room,
                                                  **self._renderer_args)
        return self._moved_renderer

    @staticmethod
    def _check(index, n: int) -> None:
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not (0 <= index < n):
            raise ValueError(f"frame index must be an int in 0..{n - 1}, got {index!r}")


def open_synthetic(rest: str, *, cam_id: str, seed: int = 0, start_ns: int | None = 0, background: bool = False,
                   n_frames: int | None = None, fps: float | None = None, modality: str = "colour",
                   utc_offset_hours: float = 0.0) -> SyntheticSource:
    """The ``synthetic[:scenario]`` source of a camera worker (entry point ``voxelwatch.sources``).

    ``start_ns=None``: stamped from the scenario's own start in the site's time zone.
    """
    scenario = rest or None
    if start_ns is None:
        start_ns = get_scenario(scenario or DEFAULT_SCENARIO, seed, utc_offset_hours=utc_offset_hours).start_ns
    return SyntheticSource(cam_id, scenario=scenario, seed=seed, start_ns=start_ns, background=background,
                           n_frames=n_frames, fps=fps, modality=modality)


def open_world(rest: str, *, cam_id: str, seed: int = 0, start_ns: int | None = 0, background: bool = False,
               n_frames: int | None = None, fps: float | None = None, modality: str = "colour",
               utc_offset_hours: float = 0.0) -> SyntheticSource:
    """The ``world:SEED`` source of a camera worker (entry point ``voxelwatch.sources``); ``seed`` is unused."""
    if not rest.isdigit():
        raise ValueError("a world source is 'world:SEED' with a non-negative integer seed")
    return SyntheticSource(cam_id, world=int(rest), start_ns=start_ns or 0, background=background,
                           n_frames=n_frames, fps=fps, modality=modality)


class SyntheticSource(FrameSource):
    """One camera of the synthetic house (``synth``) or of a randomised world
    (``world``: its seed) as a camera worker's frame source; recorded stamps, true masks.

    ``background=True`` yields the clip of the empty room recorded before the
    scenario (``background_frame(i)``), for learning. ``n_frames`` caps either.
    ``modality``: the camera's kind (``colour``, ``infrared``, ``thermal``, ``depth``);
    thermal and depth frames are ``(H, W) uint16``.
    """

    live = False

    def __init__(self, cam_id: str, *, scenario: str | None = None, seed: int = 0, start_ns: int = 0,
                 background: bool = False, n_frames: int | None = None, world: int | None = None,
                 fps: float | None = None, modality: str = "colour") -> None:
        self.cam_id = cam_id
        self.modality = modality
        self._fps_override = check_fps(fps)
        self.scenario = scenario
        self.seed = int(seed)
        self.world = None if world is None else int(world)
        self.start_ns = int(start_ns)
        self.background = bool(background)
        label = f"world:{world}" if world is not None else f"synthetic:{scenario}" if scenario else "synthetic"
        self.name = f"{label} camera {cam_id}" + (" (empty room)" if background else "")
        self._n_frames = n_frames
        self._camera = None
        self._index = 0

    def open(self) -> None:
        try:
            if self.world is not None:
                camera = _world_camera(self.world, self.cam_id, self.modality)
            elif self.scenario:
                camera = SyntheticCamera(self.scenario, self.cam_id, self.seed, modality=self.modality)
            else:
                camera = SyntheticCamera(cam_id=self.cam_id, seed=self.seed, modality=self.modality)
        except (KeyError, ValueError) as exc:
            raise SourceError(f"{self.name}: {exc}") from None
        self._camera = camera
        self.fps = self._fps_override or float(camera.fps)  # faster: the same frames, played sooner
        self._index = 0

    @property
    def n_frames(self) -> int:
        """Frames this source yields, capped by ``n_frames``: the scenario's length, or for the
        empty room the clip recorded before the scenario (3 s)."""
        if self._camera is None:
            raise SourceError(f"{self.name}: not open")
        total = int(self._camera.n_background_frames if self.background else self._camera.n_frames)
        return total if self._n_frames is None else min(total, self._n_frames)

    def seek(self, index: int) -> None:
        """Jump to frame ``index`` (rendering is random access: skipped frames cost nothing)."""
        self._index = max(0, int(index))

    def read(self) -> Frame | None:
        if self._camera is None:
            raise SourceError(f"{self.name}: read before open")
        if self._index >= self.n_frames:
            return None
        i = self._index
        stamp = recorded_stamp_ns(self.start_ns, i, self.fps)
        if self.background:
            frame = Frame(i, stamp, self._camera.background_frame(i))
        else:
            image, truth = self._camera.frame(i)
            frame = Frame(i, stamp, image, truth)
        self._index += 1
        return frame


def _world_camera(seed: int, cam_id: str, modality: str = "colour"):
    """The renderer of camera ``cam_id`` of the randomised world ``seed``, as its video worlds render
    (a thermal or depth camera as a mixed rig's frames are written)."""
    from synth.world import random_world

    world = random_world(seed)
    if cam_id not in world.cameras:
        raise ValueError(f"world {seed} has no camera {cam_id!r}; its cameras are {', '.join(world.cameras)}")
    return SyntheticCamera(world.scenario, cam_id, world.seed, camera=world.cameras[cam_id],
                           background_s=BACKGROUND_S, modality=modality)


def _default_camera(cam_id: str) -> Camera:
    cams = default_cameras()
    if cam_id not in cams:
        raise ValueError(f"no camera {cam_id!r} in the synthetic house; cameras are {sorted(cams)}")
    return cams[cam_id]


def _site_camera(site, cam_id: str) -> Camera:
    from common.site import load_site

    if isinstance(site, (str, Path)):
        site = load_site(site)
    return site.load_camera(cam_id)
