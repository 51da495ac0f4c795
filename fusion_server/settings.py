"""The fusion server's settings (:class:`FusionSettings`), apart from the server's stages so that a
process reads and checks them, and says what it is about to do, before it loads the pipeline (numpy,
scipy, OpenCV and the models take more than a second to import)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import Field, field_validator, model_validator

from common import keys
from common.camera import Camera
from common.settings import Settings
from common.site import Site

if TYPE_CHECKING:
    import logging

    import zenoh

    from fusion_server.pipeline import FusionPipeline

__all__ = ["DEFAULT_STORE_NAME", "FusionSettings"]

DEFAULT_STORE_NAME = "voxelwatch-events.sqlite"
"""The event store's file name next to the site file when ``--store`` is not given."""


class FusionSettings(Settings):
    """Everything the fusion server needs; ``fusion_server.cli`` builds it from the command line.

    site: the loaded site. prefix: the zenoh key prefix. store_path: the
    SQLite event store (the live server needs one; the offline replay stores
    nothing). out_dir: where tracks.csv/events.jsonl go (None: no files).
    mode/listen/connect: zenoh overrides of the site (None: the site's).
    tls_cert/tls_key: this host's certificate and key (None: ``fusion.pem`` and
    ``fusion-key.pem`` in the site's ``[zenoh.tls] certs`` folder).
    cache_dir: carving lookup-table cache (None: the carver's default).
    min_cameras: fewest cameras a frame set needs (None: the
    site's carving vote). exit_after_idle_s: stop after this long without
    masks (None: never). free_timeline: let the frame-set timeline follow the
    cameras' stamps instead of the server's clock, for recordings played over
    zenoh faster than real time (a camera ahead of the others is still left
    out, but the cameras' clocks are trusted). inbox_per_camera and history_queue size the
    process's queues; the rest tune the node (see the module doc).
    """

    site: Site
    prefix: str
    store_path: Path | None = None
    out_dir: Path | None = None
    mode: Literal["peer", "client"] | None = None
    listen: tuple[str, ...] | None = None
    connect: tuple[str, ...] | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None
    cache_dir: Path | None = None
    min_cameras: int | None = Field(default=None, ge=1, strict=True)
    exit_after_idle_s: float | None = Field(default=None, gt=0.0, allow_inf_nan=False)
    seed: int = 0
    status_period_s: float = Field(default=1.0, gt=0.0, allow_inf_nan=False)
    hold_ttl_ms: int = Field(default=2000, ge=1, strict=True)
    hold_slack_px: int = Field(default=2, ge=0, strict=True)
    max_clock_skew_ms: float = Field(default=250.0, gt=0.0, allow_inf_nan=False)
    free_timeline: bool = False
    skew_window: int = Field(default=30, ge=1, strict=True)
    inbox_per_camera: int = Field(default=32, ge=1, strict=True)
    max_ready_sets: int = Field(default=4, ge=1, strict=True)
    sync_buffer: int = Field(default=8, ge=1, strict=True)
    stale_s: float = Field(default=2.0, gt=0.0, allow_inf_nan=False)
    log_every_s: float = Field(default=10.0, gt=0.0, allow_inf_nan=False)
    history_queue: int = Field(default=16, ge=1, strict=True)
    restore_within_s: float = Field(default=300.0, ge=0.0, allow_inf_nan=False)

    @field_validator("prefix")
    @classmethod
    def _prefix_ok(cls, prefix: str) -> str:
        keys.validate_prefix(prefix)
        return prefix

    @model_validator(mode="after")
    def _cameras_enough(self) -> "FusionSettings":
        n_cams = len(self.site.cameras)
        if self.min_cameras is not None and self.min_cameras > n_cams:
            raise ValueError(f"min_cameras must be an int in 1..{n_cams} (the site's cameras), got {self.min_cameras!r}")
        if self.min_cameras is None and self.site.carving.min_cameras > n_cams:
            raise ValueError(f"site file {self.site.source}: field carving.min_cameras: {self.site.carving.min_cameras} "
                             f"exceeds the site's {n_cams} cameras: nothing could ever be carved")
        return self

    def build_pipeline(self, cameras: dict[str, Camera] | None = None) -> "FusionPipeline":
        """The pipeline these settings describe (calibrations loaded unless given)."""
        from fusion_server.pipeline import FusionPipeline

        return FusionPipeline.from_site(self.site, cameras=cameras, cache_dir=self.cache_dir, seed=self.seed,
                                        min_cameras=self.min_cameras)

    def endpoints(self) -> tuple[str, ...]:
        """The routers or peers the server connects to: the command line's, else the site's."""
        return tuple(self.connect if self.connect is not None else self.site.zenoh.connect)

    def zenoh_config(self) -> "zenoh.Config":
        """The server's zenoh configuration (a client waits 1 s for its router per attempt); a bad
        endpoint or zenoh setting raises a ValueError naming it."""
        from common.certs import FUSION
        from common.transport import site_config

        return site_config(self.site, host=FUSION, mode=self.mode, listen=self.listen, connect=self.connect,
                           tls_cert=self.tls_cert, tls_key=self.tls_key, connect_timeout_ms=1000)

    def announce(self, log: "logging.Logger") -> dict[str, Camera]:
        """Check the zenoh settings and load the calibrations (a ValueError naming the problem), then log
        what the server does before it can be reached (building the carving tables takes seconds to a
        minute when they are not cached). Returns the calibrations."""
        self.zenoh_config()
        cameras = self.site.load_cameras()
        log.info("fusion: site %s, %d cameras: loading the carving tables, then zenoh (%s)", self.site.name,
                 len(cameras), ", ".join(self.endpoints()) or "no router: peer")
        return cameras
