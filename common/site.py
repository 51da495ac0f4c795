"""The site file: one TOML file that describes a home.

Paths inside the file are relative to the file. Every problem stops start-up
with one :class:`SiteError` naming the file, the field and the problem, e.g.
``site file /etc/vw/flat.toml: cameras[1].resolution: expected 2 items``.

Schema (all lengths in metres, world frame Z up, floor at Z = 0)::

    name = "synthetic-house"     # [A-Za-z0-9_-]+, used in the zenoh prefix
    residents = 1                # people who live here; more present = a visit
    utc_offset_hours = 0.0       # local time = UTC + offset (visit labels)

    [volume]
    min_m = [0.0, 0.0, 0.0]
    max_m = [8.0, 6.0, 2.5]
    open_edges = false           # people enter and leave across the volume's edges too
                                 # (default: only when the site has no doors)

    [carving]
    voxel_sizes_m = [0.4, 0.2, 0.1, 0.05]  # octree levels, coarse to fine, halving (0.005..2 m)
    min_cameras = 2              # seeing cameras that must find foreground
    min_ratio = 0.75             # and the fraction of seeing cameras that must
    mask_scale = 1.0             # workers downscale masks by this factor
    fusion = "vote"              # vote | graphcut: keep the voxels that pass the vote, or
                                 # label them by a graph cut with a Potts smoothness prior
    smoothing = 0.1              # the graph cut's Potts lambda (0..1): an isolated voxel goes, and a
                                 # one-voxel hole fills, when 6 lambda exceeds its margin (one camera
                                 # short of the vote or just enough: 1 / cameras seeing)
    free_space = true            # depth cameras carve the space in front of what they measure

    [events]
    long_lie_s = 30.0            # on the floor this long after a fall: long_lie (5..3600)
    inactivity_s = 1800.0        # still this long, outside bed: inactivity (30..86400)

    [identity]
    reid_window_s = 600.0        # a person who leaves and comes back within this keeps their track id
    rate_hz = 3.0                # colour descriptor requests per person per second per camera

    [[enrolled]]                 # a resident recognised by appearance (at most `residents` of them)
    name = "Ada"                 # unique, 1..64 characters; shown as `person` on tracks and events
    model = "residents/ada.json" # appearance model written by `voxelwatch enrol`

    [zenoh]
    prefix = ""                  # default voxelwatch/<name>
    mode = "peer"                # peer | client | router
    listen = []                  # e.g. ["tcp/127.0.0.1:7447"]
    connect = []
    multicast_scouting = false
    shared_memory = false
    config = ""                  # a zenoh JSON5 file applied first (zenoh's own settings)
    [zenoh.settings]             # zenoh's own settings applied last, by path or as tables
    "transport/link/tx/lease" = 10000

    [zenoh.tls]                  # TLS with mutual authentication (voxelwatch certs makes the files)
    ca = "certs/ca.pem"          # the site's certificate authority
    certs = "certs"              # folder with this host's <host>.pem and <host>-key.pem
                                 # (host: router, fusion, the camera id; --tls-cert/--tls-key override)
    readers = ["reader"]         # reader certificates (reader-<name>) allowed to read
    access_control = true        # the router lets each host do only its part (common/access.py)

    [view]                       # voxelwatch view: the live web page
    listen = "127.0.0.1:8080"    # host:port; localhost unless told otherwise
    token_file = "view.token"    # the access token (12+ characters), or token = "..."
    alarms = ["fall", "long_lie"]  # kinds shown as an alarm banner until acknowledged
    trail_s = 10.0               # seconds of each person's path drawn on the plan

    [notify]                     # voxelwatch notify: alerts where people already look
    kinds = ["fall", "long_lie", "camera_lost", "clock_skew"]  # default for every channel
    outbox = "notify-outbox.sqlite"  # kept until every channel has taken each event
    retry_max_s = 300.0          # back-off doubles up to this
    [notify.mqtt]                # a broker, e.g. the home-automation hub's
    host = "127.0.0.1"
    port = 1883
    username = ""
    password_file = ""           # or password = "..."
    tls_ca = ""                  # the broker's authority: connect with TLS
    topic_prefix = ""            # default voxelwatch/<name>
    discovery = true             # people and cameras as Home Assistant sensors, alarms as event entities
    discovery_prefix = "homeassistant"
    [[notify.webhooks]]          # JSON POST of each event, retried with back-off
    url = "https://example.org/hook"
    kinds = ["fall"]             # optional: this channel's own kinds
    headers = { Authorization = "Bearer ..." }
    timeout_s = 10.0             # per attempt; 2xx delivered, 408/429/5xx retried, other 4xx given up
    [notify.email]
    host = "smtp.example.org"
    port = 587
    security = "starttls"        # starttls | tls | none
    username = ""
    password_file = ""
    sender = "voxelwatch@example.org"
    to = ["nurse@example.org"]

    [[cameras]]
    id = "cam1"
    calibration = "calib/cam1.toml"
    format = "voxelwatch"        # opencv | opencv-fisheye | pets-tsai | voxelwatch
    units = "m"                  # m | cm | mm: the calibration's length unit
    up = "+z"                    # +z | -z: the calibration's up axis
    origin_m = [0.0, 0.0, 0.0]   # the calibration origin in the site's world
    yaw_deg = 0.0                # rotation of the calibration frame about Z
    resolution = [640, 480]      # optional when the calibration states its size
    modality = "colour"          # colour | thermal | infrared | depth
    fps = 15.0
    source = ""                  # default source for this camera's worker
    background = ""              # clip of the empty room to learn from first
    view_reference = ""          # PNG keeping the worker's reference view of the room (moved-camera check)

    [[hotspots]]
    name = "dinner table"
    kind = "table"
    polygon_m = [[3.0, 2.0], [4.6, 2.0], [4.6, 3.0], [3.0, 3.0]]

    [[doors]]
    name = "front door"
    polygon_m = [[0.0, 4.6], [0.5, 4.6], [0.5, 5.6], [0.0, 5.6]]

    [[occluders]]                # furniture and walls that hide people from cameras:
    name = "sofa back"           # a camera does not vote on what it sees only through them
    polygon_m = [[1.0, 0.0], [3.0, 0.0], [3.0, 0.25], [1.0, 0.25]]  # convex
    z_m = [0.0, 0.9]             # from this height to this one
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from common import keys
from common.settings import field_name, problem

if TYPE_CHECKING:
    from common.camera import Camera
    from common.appearance import Resident

NAME_PATTERN = r"^[A-Za-z0-9_-]+$"


class SiteError(ValueError):
    """A site file that cannot be used; the message names file, field and problem."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _polygon_ok(polygon: list[tuple[float, float]]) -> list[tuple[float, float]]:
    if len(polygon) < 3:
        raise ValueError(f"a polygon needs at least 3 points, got {len(polygon)}")
    if not all(math.isfinite(c) for p in polygon for c in p):
        raise ValueError("polygon coordinates must be finite")
    return polygon


def is_convex(polygon) -> bool:
    """Whether a floor polygon (sequence of (x, y)) is convex with a non-zero area; collinear
    points are allowed, either winding."""
    pts = [(float(x), float(y)) for x, y in polygon]
    n = len(pts)
    if n < 3:
        return False
    scale = max(max(abs(pts[(i + 1) % n][k] - pts[i][k]) for k in (0, 1)) for i in range(n)) ** 2
    tol = 1e-12 * max(scale, 1e-300)
    area2 = sum(pts[i][0] * pts[(i + 1) % n][1] - pts[(i + 1) % n][0] * pts[i][1] for i in range(n))
    turns = []
    for i in range(n):
        (ax, ay), (bx, by), (cx, cy) = pts[i], pts[(i + 1) % n], pts[(i + 2) % n]
        turns.append((bx - ax) * (cy - by) - (by - ay) * (cx - bx))
    return abs(area2) > tol and (all(t >= -tol for t in turns) or all(t <= tol for t in turns))


def _convex_ok(polygon: list[tuple[float, float]]) -> list[tuple[float, float]]:
    if not is_convex(polygon):
        raise ValueError("the polygon must be convex with a non-zero area (split other shapes into convex parts)")
    return polygon


class Volume(_Model):
    """The monitored box, world frame, metres."""

    min_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_m: tuple[float, float, float] = (8.0, 6.0, 2.5)
    open_edges: bool | None = None
    """People can come and go across the volume's edges (it is part of a larger
    space); None: only where the site has no doors."""
    margin_m: float | None = Field(default=None, ge=0.0, le=3.0, allow_inf_nan=False)
    """How far beyond the volume's sides the cameras follow people without reporting them
    (carved and tracked, so that someone standing just outside is seen whole and placed
    outside, not cut by the volume's side into a body inside it); None: 0.6 m where the
    edges are open, 0 where walls bound the volume."""

    @model_validator(mode="after")
    def _ordered(self) -> "Volume":
        for axis, lo, hi in zip("xyz", self.min_m, self.max_m):
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"{axis} bounds must be finite")
            if hi <= lo:
                raise ValueError(f"max_m {axis}={hi} must exceed min_m {axis}={lo}")
        return self

    @property
    def size_m(self) -> tuple[float, float, float]:
        return tuple(hi - lo for lo, hi in zip(self.min_m, self.max_m))  # type: ignore[return-value]


class Carving(_Model):
    """Octree levels and the vote."""

    voxel_sizes_m: list[Annotated[float, Field(ge=0.005, le=2.0, allow_inf_nan=False)]] = Field(
        default_factory=lambda: [0.4, 0.2, 0.1, 0.05])
    min_cameras: int = Field(default=2, ge=1)
    min_ratio: float = Field(default=0.75, gt=0.0, le=1.0)
    mask_scale: float = Field(default=1.0, ge=0.125, le=1.0)
    fusion: Literal["vote", "graphcut"] = "vote"
    smoothing: float = Field(default=0.1, ge=0.0, le=1.0)
    free_space: bool = Field(default=True, strict=True)

    @field_validator("voxel_sizes_m")
    @classmethod
    def _halving(cls, sizes: list[float]) -> list[float]:
        if not sizes:
            raise ValueError("needs at least one voxel size")
        for coarse, fine in zip(sizes, sizes[1:]):
            if not math.isclose(coarse, 2 * fine, rel_tol=1e-6):
                raise ValueError(f"each level must halve the previous one, got {coarse} then {fine}")
        return sizes


class EventSettings(_Model):
    """How long a situation lasts before it raises an alarm, seconds; each home
    sets its own (a care home may want a long lie reported sooner)."""

    long_lie_s: float = Field(default=30.0, ge=5.0, le=3600.0, allow_inf_nan=False)
    """Lying on the floor this long after a fall (or since lying down) is a
    ``long_lie``. Not below 5 s: the fall itself needs a second on the floor
    to be confirmed."""
    inactivity_s: float = Field(default=1800.0, ge=30.0, le=86400.0, allow_inf_nan=False)
    """Keeping still this long, outside bed, is ``inactivity``. Not below 30 s:
    stillness is judged over the last 30 s of positions."""
    decisions: Literal["frame", "viterbi"] = "frame"
    """How postures, and the sit, stand and fall events read from them, are
    decided: ``frame``, on each frame as it comes (a filter over the frames so
    far, and a minimum duration for any change); ``viterbi``, on the best
    sequence of postures over a short window of frames (standing, sitting,
    bending, lying, or out of view), ``viterbi_lag_s`` after the frame,
    never taken back."""
    viterbi_lag_s: float = Field(default=0.6, ge=0.0, le=1.0, allow_inf_nan=False)
    """With ``decisions = "viterbi"``: how long after a frame its posture is
    decided, seconds. Not above 1 s, so that a fall is still raised within
    1.5 s of the body reaching the floor."""


class IdentitySettings(_Model):
    """Who is who: how long a person who left keeps their track id, and how often
    the cameras describe each person's colours."""

    reid_window_s: float = Field(default=600.0, gt=0.0, le=7 * 86400.0, allow_inf_nan=False)
    """A person who leaves and comes back within this many seconds keeps their track id."""
    rate_hz: float = Field(default=3.0, gt=0.0, le=30.0, allow_inf_nan=False)
    """Colour descriptor requests per person per second, to every camera (about 110
    bytes per person per request on the wire)."""


MAX_NAME_CHARS = 64


class EnrolledSpec(_Model):
    """A resident recognised by appearance: a name and the appearance model
    (``voxelwatch enrol``'s JSON file, relative to the site file)."""

    name: str
    model: str = Field(min_length=1)

    @field_validator("name")
    @classmethod
    def _name_ok(cls, name: str) -> str:
        return check_person_name(name)


def check_person_name(name: str) -> str:
    """``name`` when it can name an enrolled person (1..64 characters, not only spaces);
    ValueError otherwise."""
    if not name.strip():
        raise ValueError("a name must not be empty")
    if len(name) > MAX_NAME_CHARS:
        raise ValueError(f"a name must be at most {MAX_NAME_CHARS} characters, got {len(name)}")
    return name


class TlsSettings(_Model):
    """TLS with mutual authentication: every host shows a certificate of the site's authority."""

    ca: str = Field(min_length=1)
    certs: str = ""
    readers: list[str] = Field(default_factory=lambda: ["reader"])
    access_control: bool = True

    @field_validator("readers")
    @classmethod
    def _readers_ok(cls, readers: list[str]) -> list[str]:
        for name in readers:
            keys.validate_chunk(name, "reader name")
        if len(set(readers)) != len(readers):
            raise ValueError(f"reader names must be unique, got {readers}")
        return readers


class ZenohSettings(_Model):
    """How this process joins the zenoh network."""

    prefix: str = ""
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=list)
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    shared_memory: bool = False
    config: str = ""
    """A zenoh JSON5 configuration file (relative to the site file), applied before everything else."""
    settings: dict[str, Any] = Field(default_factory=dict)
    """zenoh's own settings, ``"path/to/key" = value`` or nested tables, applied after everything else."""
    tls: TlsSettings | None = None

    @field_validator("prefix")
    @classmethod
    def _prefix_ok(cls, prefix: str) -> str:
        if prefix:
            for chunk in prefix.split("/"):
                keys.validate_chunk(chunk, "zenoh prefix")
        return prefix

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints_ok(cls, endpoints: list[str], info) -> list[str]:
        from common.transport import check_endpoint  # the transport's own rule, checked at load

        for endpoint in endpoints:
            check_endpoint(endpoint, listen=info.field_name == "listen")
        return endpoints


ALARM_KINDS = ("fall", "long_lie", "camera_lost", "clock_skew")
"""Event kinds that raise an alarm in the live view and that notifications deliver by default."""


def _kinds_ok(kinds: list[str]) -> list[str]:
    from common.messages import EVENT_KINDS

    unknown = sorted(set(kinds) - set(EVENT_KINDS))
    if unknown:
        raise ValueError(f"unknown event kinds {unknown}; kinds are {list(EVENT_KINDS)}")
    return list(dict.fromkeys(kinds))


class ViewSettings(_Model):
    """``voxelwatch view``: the live web page for the people who watch."""

    listen: str = "127.0.0.1:8080"
    """host:port the page is served on; localhost unless told otherwise."""
    token: str = ""
    """The access token (at least 12 characters), or ``token_file``: a file holding it."""
    token_file: str = ""
    alarms: list[str] = Field(default_factory=lambda: ["fall", "long_lie"])
    """Event kinds shown as an alarm banner, with sound, until acknowledged."""
    trail_s: float = Field(default=10.0, ge=0.0, le=600.0, allow_inf_nan=False)
    """How much of each person's recent path the plan draws, seconds."""

    _kinds = field_validator("alarms")(classmethod(lambda cls, k: _kinds_ok(k)))

    @field_validator("listen")
    @classmethod
    def _listen_ok(cls, listen: str) -> str:
        host, sep, port = listen.rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"expected host:port, e.g. 127.0.0.1:8080, got {listen!r}")
        return listen

    @model_validator(mode="after")
    def _one_token(self) -> "ViewSettings":
        if self.token and self.token_file:
            raise ValueError("give token or token_file, not both")
        if self.token and len(self.token) < 12:
            raise ValueError("token must be at least 12 characters")
        return self


class MqttSettings(_Model):
    """An MQTT broker (a home-automation hub's): events, retained state per person, and
    Home Assistant discovery."""

    host: str = Field(min_length=1)
    port: int = Field(default=1883, gt=0, lt=65536)
    username: str = ""
    password: str = ""
    password_file: str = ""
    tls_ca: str = ""
    """The broker's certificate authority: connect with TLS (port usually 8883)."""
    topic_prefix: str = ""
    """Topics ``<topic_prefix>/events/<kind>``, ``<topic_prefix>/person/<id>/state``;
    default ``voxelwatch/<site>``."""
    discovery: bool = True
    """Announce each person and camera to Home Assistant (``<discovery_prefix>/sensor/...``)."""
    discovery_prefix: str = "homeassistant"
    kinds: list[str] | None = None
    """Event kinds published; default ``[notify] kinds``."""

    _kinds = field_validator("kinds")(classmethod(lambda cls, k: k if k is None else _kinds_ok(k)))


class WebhookSettings(_Model):
    """An HTTP endpoint that receives each event as a JSON POST."""

    url: str = Field(pattern=r"^https?://[^\s]+$")
    kinds: list[str] | None = None
    headers: dict[str, str] = Field(default_factory=dict)
    """Extra headers, e.g. an authorisation token."""
    timeout_s: float = Field(default=10.0, gt=0.0, le=120.0)

    _kinds = field_validator("kinds")(classmethod(lambda cls, k: k if k is None else _kinds_ok(k)))


class EmailSettings(_Model):
    """E-mail through an SMTP server."""

    host: str = Field(min_length=1)
    port: int = Field(default=587, gt=0, lt=65536)
    security: Literal["starttls", "tls", "none"] = "starttls"
    username: str = ""
    password: str = ""
    password_file: str = ""
    sender: str = Field(pattern=r"^[^@\s]+@[^@\s]+$")
    to: list[str] = Field(min_length=1)
    kinds: list[str] | None = None

    _kinds = field_validator("kinds")(classmethod(lambda cls, k: k if k is None else _kinds_ok(k)))

    @field_validator("to")
    @classmethod
    def _addresses_ok(cls, to: list[str]) -> list[str]:
        bad = [a for a in to if "@" not in a or any(c.isspace() for c in a)]
        if bad:
            raise ValueError(f"not e-mail addresses: {bad}")
        return to


class NotifySettings(_Model):
    """``voxelwatch notify``: alerts delivered where the people who watch already look."""

    kinds: list[str] = Field(default_factory=lambda: list(ALARM_KINDS))
    """Event kinds delivered by every channel that does not choose its own."""
    outbox: str = "notify-outbox.sqlite"
    """The outbox on disk (relative to the site file): every event is kept until each
    channel has taken it, across restarts."""
    retry_max_s: float = Field(default=300.0, ge=1.0, le=86400.0)
    """Back-off between delivery attempts doubles up to this, seconds."""
    mqtt: MqttSettings | None = None
    webhooks: list[WebhookSettings] = Field(default_factory=list)
    email: EmailSettings | None = None

    _kinds = field_validator("kinds")(classmethod(lambda cls, k: _kinds_ok(k)))


class CameraSpec(_Model):
    """One camera of the home."""

    id: str = Field(pattern=NAME_PATTERN)
    calibration: str
    format: Literal["opencv", "opencv-fisheye", "pets-tsai", "voxelwatch"] = "voxelwatch"
    units: Literal["m", "cm", "mm"] = "m"
    up: Literal["+z", "-z"] = "+z"
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0
    resolution: tuple[int, int] | None = None
    modality: Literal["colour", "thermal", "infrared", "depth"] = "colour"
    fps: float = Field(default=15.0, ge=0.5, le=240.0, allow_inf_nan=False)
    """Frames a second. Not below 0.5: the frame sets' lattice and the tracker need a frame at
    least every 2 s (a rate near 0 made the fusion server's frame period overflow at start)."""
    source: str = ""
    background: str = ""
    view_reference: str = ""

    @field_validator("resolution")
    @classmethod
    def _resolution_ok(cls, res: tuple[int, int] | None) -> tuple[int, int] | None:
        if res is not None and not all(16 <= v <= 8192 for v in res):
            raise ValueError(f"width and height must lie in 16..8192, got {list(res)}")
        return res


class HotSpotSpec(_Model):
    """A named floor area where dwelling means something (sofa, table, TV)."""

    name: str = Field(min_length=1)
    kind: str = ""
    polygon_m: list[tuple[float, float]]

    _poly = field_validator("polygon_m")(classmethod(lambda cls, p: _polygon_ok(p)))


class DoorSpec(_Model):
    """A floor zone through which people enter and leave."""

    name: str = Field(min_length=1)
    polygon_m: list[tuple[float, float]]

    _poly = field_validator("polygon_m")(classmethod(lambda cls, p: _polygon_ok(p)))


class OccluderSpec(_Model):
    """Furniture or a wall that hides people from the cameras behind it: a convex floor
    polygon between two heights."""

    name: str = Field(min_length=1)
    polygon_m: list[tuple[float, float]]
    z_m: tuple[float, float]

    _poly = field_validator("polygon_m")(classmethod(lambda cls, p: _convex_ok(_polygon_ok(p))))

    @field_validator("z_m")
    @classmethod
    def _heights_ok(cls, z: tuple[float, float]) -> tuple[float, float]:
        if not all(math.isfinite(v) for v in z) or not 0.0 <= z[0] < z[1]:
            raise ValueError(f"expected [bottom, top] with 0 <= bottom < top, got {list(z)}")
        return z


CARVING_TABLE_BYTES_PER_VOXEL = 6
"""A camera's carving table holds a pixel index (4 bytes) and a radius (2 bytes) per voxel of each level."""
MAX_CARVING_TABLE_BYTES = 2 * 2**30
"""The largest carving tables a site may ask for, all cameras and levels (the synthetic house's are 33 MB,
tuning world 12's 138 MB, a 12 x 36 m common room's at 5 cm with seven cameras about 0.4 GB)."""


class Site(_Model):
    """A home: volume, cameras, hot spots, doors, event timing and network settings."""

    name: str = Field(pattern=NAME_PATTERN)
    residents: int = Field(default=1, ge=0)
    utc_offset_hours: float = Field(default=0.0, ge=-14.0, le=14.0)
    volume: Volume = Field(default_factory=Volume)
    carving: Carving = Field(default_factory=Carving)
    events: EventSettings = Field(default_factory=EventSettings)
    identity: IdentitySettings = Field(default_factory=IdentitySettings)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    cameras: list[CameraSpec] = Field(min_length=1)
    hotspots: list[HotSpotSpec] = Field(default_factory=list)
    doors: list[DoorSpec] = Field(default_factory=list)
    occluders: list[OccluderSpec] = Field(default_factory=list)
    enrolled: list[EnrolledSpec] = Field(default_factory=list)
    view: ViewSettings = Field(default_factory=ViewSettings)
    notify: NotifySettings = Field(default_factory=NotifySettings)
    base_dir: Path = Field(default=Path("."), exclude=True)
    source: str = Field(default="<site>", exclude=True)
    """Where the site came from (its file), for messages."""

    @field_validator("cameras")
    @classmethod
    def _unique_ids(cls, cameras: list[CameraSpec]) -> list[CameraSpec]:
        ids = [c.id for c in cameras]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise ValueError(f"camera ids must be unique, repeated: {dupes}")
        return cameras

    @model_validator(mode="after")
    def _tables_fit(self) -> "Site":
        """The fusion server's carving tables (6 bytes per camera and voxel of every octree level) must
        fit :data:`MAX_CARVING_TABLE_BYTES`: a finest voxel too small for the volume would otherwise pass
        the file and leave the server building tables until its memory runs out."""
        size = self.volume.size_m
        voxels = sum(math.prod(math.ceil(extent / s - 1e-9) for extent in size) for s in self.carving.voxel_sizes_m)
        need = voxels * CARVING_TABLE_BYTES_PER_VOXEL * len(self.cameras)
        if need > MAX_CARVING_TABLE_BYTES:
            finest = self.carving.voxel_sizes_m[-1]
            raise ValueError(
                f"carving.voxel_sizes_m: a finest voxel of {finest:g} m over a volume of "
                f"{' x '.join(f'{e:g}' for e in size)} m makes {voxels:,} voxels, carving tables of about "
                f"{need / 2**30:.1f} GiB for {len(self.cameras)} cameras, more than the "
                f"{MAX_CARVING_TABLE_BYTES / 2**30:g} GiB allowed: make the finest voxel larger or the volume smaller")
        return self

    @field_validator("enrolled")
    @classmethod
    def _enrolled_ok(cls, enrolled: list[EnrolledSpec], info: ValidationInfo) -> list[EnrolledSpec]:
        names = [e.name for e in enrolled]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"enrolled names must be unique, repeated: {dupes}")
        residents = info.data.get("residents")
        if residents is not None and len(enrolled) > residents:
            raise ValueError(f"{len(enrolled)} people enrolled but residents = {residents}: "
                             "enrol at most as many people as live here")
        return enrolled

    @property
    def prefix(self) -> str:
        return self.zenoh.prefix or keys.default_prefix(self.name)

    @property
    def camera_ids(self) -> list[str]:
        return [c.id for c in self.cameras]

    def camera(self, cam_id: str) -> CameraSpec:
        for spec in self.cameras:
            if spec.id == cam_id:
                return spec
        raise SiteError(f"site {self.name}: no camera {cam_id!r}; cameras are {self.camera_ids}")

    def resolve(self, path: str) -> Path:
        """A path from the file, made absolute against the file's folder."""
        p = Path(path).expanduser()
        return p if p.is_absolute() else (self.base_dir / p).resolve()

    def calibration_path(self, cam_id: str) -> Path:
        return self.resolve(self.camera(cam_id).calibration)

    def load_camera(self, cam_id: str) -> "Camera":
        """The camera model of one camera, in the site's world frame."""
        from common.calibration import WorldTransform, load_calibration

        spec = self.camera(cam_id)
        transform = WorldTransform(units=spec.units, up=spec.up, origin_m=spec.origin_m, yaw_deg=spec.yaw_deg)
        return load_calibration(
            self.calibration_path(cam_id), spec.format, cam_id, transform, image_size=spec.resolution
        )

    def load_cameras(self) -> dict[str, "Camera"]:
        return {cam_id: self.load_camera(cam_id) for cam_id in self.camera_ids}

    def secret(self, value: str, file: str, field: str) -> str:
        """A secret given in the file (``value``) or in a file of its own (``file``, relative to
        the site file; surrounding whitespace dropped); "" when neither is set. A secret file that
        cannot be read, or is empty, is a :class:`SiteError` naming the field."""
        if not file:
            return value
        path = self.resolve(file)
        text = _read_text(path, f"site file {self.source}: field {field}: file {path}",
                          folder="is a folder, expected a file").strip()
        if not text:
            raise SiteError(f"site file {self.source}: field {field}: file {path} is empty")
        return text

    def load_residents(self) -> list["Resident"]:
        """The enrolled residents with their appearance models, in file order (they
        take track ids 1, 2, ...). A model file that is missing, unreadable or not an
        appearance model is a :class:`SiteError` naming the file and the problem."""
        from common.appearance import AppearanceModel, Resident

        residents = []
        for i, spec in enumerate(self.enrolled):
            path = self.resolve(spec.model)
            where = f"site file {self.source}: field enrolled[{i}].model: model file {path}"
            text = _read_text(path, where, missing="not found (make it with voxelwatch enrol)",
                              folder="is a folder, expected a JSON file")
            try:
                raw = json.loads(text)
            except json.JSONDecodeError as exc:
                raise SiteError(f"{where}: not valid JSON: {exc.msg} at line {exc.lineno}") from None
            if not isinstance(raw, dict):
                raise SiteError(f"{where}: expected a JSON object, got {type(raw).__name__}")
            try:
                model = AppearanceModel.from_dict(raw, where=where)
            except ValueError as exc:
                raise SiteError(str(exc)) from None
            residents.append(Resident(name=spec.name, model=model))
        return residents


def _read_text(path: Path, where: str, *, missing: str = "not found", folder: str | None = None) -> str:
    """The UTF-8 text of ``path``; a SiteError starting with ``where`` when it cannot be read."""
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SiteError(f"{where}: {missing}") from None
    except OSError as exc:
        if isinstance(exc, IsADirectoryError) and folder is not None:
            raise SiteError(f"{where}: {folder}") from None
        raise SiteError(f"{where}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise SiteError(f"{where}: not UTF-8 text") from None


def load_site(path: str | Path) -> Site:
    """Read and validate a site file; raise :class:`SiteError` on any problem."""
    path = Path(path)
    text = _read_text(path, f"site file {path}")
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SiteError(f"site file {path}: not valid TOML: {exc}") from None
    return site_from_dict(raw, base_dir=path.resolve().parent, source=str(path))


def site_from_dict(raw: dict[str, Any], *, base_dir: Path, source: str = "<site>") -> Site:
    """Validate a site given as a dict (the parsed TOML)."""
    try:
        return Site.model_validate({**raw, "base_dir": base_dir, "source": source})
    except ValidationError as exc:
        err = exc.errors()[0]
        field = field_name(err["loc"])
        more = f" (and {exc.error_count() - 1} more problems)" if exc.error_count() > 1 else ""
        raise SiteError(f"site file {source}: field {field}: {problem(err)}{more}") from None


def with_settings(site: Site, settings: Sequence[str]) -> Site:
    """``site`` with ``SECTION.KEY=VALUE`` settings changed (VALUE read as a TOML value, else as
    text), validated like the file: :class:`SiteError` naming the setting otherwise. For comparing
    options on the same sites (``voxelwatch eval --suite --set carving.fusion=graphcut``)."""
    data = site.model_dump(mode="json", exclude={"base_dir", "source"})
    for item in settings:
        name, sep, text = str(item).partition("=")
        section, dot, key = name.strip().partition(".")
        if not sep or not dot or not section or not key:
            raise SiteError(f"setting {item!r}: expected SECTION.KEY=VALUE, e.g. carving.fusion=graphcut")
        if not isinstance(data.get(section), dict):
            tables = ", ".join(k for k, v in data.items() if isinstance(v, dict))
            raise SiteError(f"setting {item!r}: no section [{section}] (sections: {tables})")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        data[section][key.strip()] = value
    return site_from_dict(data, base_dir=site.base_dir, source=f"{site.source} with {', '.join(settings)}")


def site_to_toml(site: Site) -> str:
    """The site as TOML text that :func:`load_site` reads back unchanged."""
    data = site.model_dump(mode="json", exclude={"base_dir"})
    lines: list[str] = []
    for key, value in data.items():
        if value == []:
            continue  # an empty list of tables: left out, so that tables can be added below by hand
        if not isinstance(value, (dict, list)) or (isinstance(value, list) and not _is_table_list(value)):
            lines.append(f"{key} = {_toml_value(value)}")
    for key, value in data.items():
        if isinstance(value, dict):
            lines.append(f"\n[{key}]")
            lines.extend(f"{k} = {_toml_value(v)}" for k, v in value.items() if v is not None)
        elif isinstance(value, list) and _is_table_list(value):
            for item in value:
                lines.append(f"\n[[{key}]]")
                lines.extend(f"{k} = {_toml_value(v)}" for k, v in item.items() if v is not None)
    return "\n".join(lines) + "\n"


def write_site(site: Site, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(site_to_toml(site), encoding="utf-8")
    return path


def _is_table_list(value: list) -> bool:
    return bool(value) and all(isinstance(v, dict) for v in value)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return f'"{escaped}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):  # an inline table ([zenoh] settings and tls)
        return "{" + ", ".join(f"{_toml_value(str(k))} = {_toml_value(v)}" for k, v in value.items() if v is not None) + "}"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")
