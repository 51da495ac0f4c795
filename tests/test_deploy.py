"""The deployment material in deploy/: the example site and its calibrations,
the zenoh configuration files, the systemd units and the compose file.

The units and the compose file are checked against the real console scripts
and argument parsers, and the router unit's command is run for real: two
clients configured from deploy/zenoh/client.json5 talk through it on loopback.
"""

from __future__ import annotations

import importlib
import json
import re
import shlex
import shutil
import socket
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
import zenoh

from voxelwatch import cli as vw_cli
from common.site import load_site
from common.transport import MAX_ZENOH_MESSAGE_BYTES, zenoh_config
from fusion_server import cli as fusion_cli

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
SITE = DEPLOY / "site.toml"
UNITS = DEPLOY / "systemd"
ENV_FILE = UNITS / "voxelwatch.env"

# the zenoh settings ZENOH.md lists as checked with eclipse-zenoh on loopback
VERIFIED_ZENOH_KEYS = {
    "mode",
    "listen/endpoints",
    "connect/endpoints",
    "connect/timeout_ms",
    "scouting/multicast/enabled",
    "transport/shared_memory/enabled",
    "transport/link/rx/max_message_size",
}
ZENOH_FILES = {"peer": "peer", "client": "client", "router": "router"}


# ---------------------------------------------------------------- site file


@pytest.fixture(scope="module")
def site():
    return load_site(SITE)


@pytest.fixture(scope="module")
def cameras(site):
    return site.load_cameras()


def test_site_loads_with_five_cameras_hot_spots_and_a_door(site, cameras):
    assert site.camera_ids == ["cam1", "cam2", "cam3", "cam4", "cam5"]
    assert sorted(cam.model for cam in cameras.values()) == ["fisheye"] + ["pinhole"] * 4
    assert {h.name for h in site.hotspots} == {"sofa", "dinner table", "kitchen", "TV"}
    assert [d.name for d in site.doors] == ["front door"]
    assert site.prefix == f"voxelwatch/{site.name}"


def test_every_camera_sees_the_middle_of_the_room_at_one_metre(site, cameras):
    lo, hi = np.array(site.volume.min_m), np.array(site.volume.max_m)
    centre = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 1.0]
    for cam_id, cam in cameras.items():
        uv, valid = cam.project([centre])
        assert valid[0], f"{cam_id} does not see the room centre {centre} (projects to {uv[0]})"


def test_cameras_are_mounted_inside_the_room_below_the_ceiling(site, cameras):
    lo, hi = np.array(site.volume.min_m), np.array(site.volume.max_m)
    for cam_id, cam in cameras.items():
        x, y, z = cam.center
        assert lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1], f"{cam_id} centre {cam.center} outside the floor plan"
        assert 2.0 <= z <= 2.6, f"{cam_id} mounted at {z:.2f} m, expected near the ceiling"
        assert cam.forward[2] < -0.3, f"{cam_id} does not look downwards: axis {cam.forward}"


@pytest.mark.parametrize("height_m", [0.3, 1.0, 1.7])
def test_the_whole_floor_is_seen_by_more_cameras_than_the_carving_vote_needs(site, cameras, height_m):
    """A lying, a seated and a standing person anywhere in the room: the
    carving needs ``min_cameras``; one more leaves room for an occlusion."""
    lo, hi = site.volume.min_m, site.volume.max_m
    step = 0.2
    gx, gy = np.meshgrid(np.arange(lo[0] + step / 2, hi[0], step), np.arange(lo[1] + step / 2, hi[1], step))
    points = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, height_m)], axis=1)
    seen = sum(cam.project(points)[1].astype(int) for cam in cameras.values())
    worst = int(np.argmin(seen))
    assert seen.min() >= site.carving.min_cameras + 1, f"{points[worst]} is seen by only {seen[worst]} cameras"


def test_hot_spots_and_door_lie_on_the_floor_plan(site):
    lo, hi = site.volume.min_m, site.volume.max_m
    for zone in [*site.hotspots, *site.doors]:
        poly = np.array(zone.polygon_m)
        assert (poly[:, 0] >= lo[0]).all() and (poly[:, 0] <= hi[0]).all(), zone.name
        assert (poly[:, 1] >= lo[1]).all() and (poly[:, 1] <= hi[1]).all(), zone.name


def test_site_zenoh_settings_are_client_mode_through_the_fusion_host_router(site):
    z = site.zenoh
    assert (z.mode, z.listen, z.multicast_scouting, z.shared_memory) == ("client", [], False, False)
    assert z.connect == ["tcp/fusion.local:7447"]
    conf = zenoh_config(z)  # zenoh accepts every value
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/fusion.local:7447"]


def test_site_check_command_prints_every_camera_centre(cameras, capsys):
    assert vw_cli.main(["site", "check", str(SITE)]) == 0
    out = capsys.readouterr().out
    for cam_id, cam in cameras.items():
        x, y, z = cam.center
        assert f"camera {cam_id}: {cam.model} 640x480, centre ({x:.2f}, {y:.2f}, {z:.2f}) m" in out


# ---------------------------------------------------------------- zenoh files


def _json5_of_our_files(text: str) -> dict:
    """The small JSON5 subset the deploy files use (// comments, bare keys,
    trailing commas) as JSON. Only for these files: strings hold no '//'."""
    no_comments = re.sub(r"//[^\n]*", "", text)
    quoted = re.sub(r"(^|[{,]\s*)([A-Za-z_][A-Za-z0-9_]*)\s*:", r'\1"\2":', no_comments, flags=re.M)
    return json.loads(re.sub(r",(\s*[}\]])", r"\1", quoted))


def _flatten(tree: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in tree.items():
        path = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, path + "/"))
        else:
            out[path] = value
    return out


@pytest.mark.parametrize("name", sorted(ZENOH_FILES))
def test_zenoh_file_is_accepted_and_sets_only_verified_keys(name):
    path = DEPLOY / "zenoh" / f"{name}.json5"
    text = path.read_text(encoding="utf-8")
    settings = _flatten(_json5_of_our_files(text))
    assert set(settings) <= VERIFIED_ZENOH_KEYS, f"{path.name}: unverified keys {set(settings) - VERIFIED_ZENOH_KEYS}"
    assert settings["mode"] == name
    assert settings["scouting/multicast/enabled"] is False
    assert settings["transport/shared_memory/enabled"] is False
    assert settings["transport/link/rx/max_message_size"] == MAX_ZENOH_MESSAGE_BYTES
    for conf in (zenoh.Config.from_json5(text), zenoh.Config.from_file(str(path))):
        for key, value in settings.items():
            assert json.loads(conf.get_json(key)) == value, f"{path.name}: zenoh read {key} differently"
    one_by_one = zenoh.Config()
    for key, value in settings.items():
        one_by_one.insert_json5(key, json.dumps(value))


def test_zenoh_files_follow_the_network_plan():
    read = {n: _flatten(_json5_of_our_files((DEPLOY / "zenoh" / f"{n}.json5").read_text())) for n in ZENOH_FILES}
    assert read["client"]["connect/endpoints"] == ["tcp/fusion.local:7447"]
    assert read["client"]["connect/timeout_ms"] == -1  # wait for the router, hosts boot in any order
    assert read["peer"]["listen/endpoints"] == ["tcp/0.0.0.0:7447"]  # every peer listens
    assert read["router"]["listen/endpoints"] == ["tcp/0.0.0.0:7447"]


# ---------------------------------------------------------------- systemd units


def _unit(path: Path) -> dict[str, list[str]]:
    """``Key -> [values]`` of a unit file (sections merged; keys may repeat)."""
    values: dict[str, list[str]] = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";", "[")):
            continue
        key, _, value = line.partition("=")
        values.setdefault(key.strip(), []).append(value.strip())
    return values


def _env_file(text: str) -> dict[str, str]:
    env = {}
    for line in text.splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, _, value = line.partition("=")
            words = shlex.split(value)
            env[key.strip()] = " ".join(words)
    return env


def _exec_argv(exec_start: str, env: dict[str, str], instance: str) -> list[str]:
    """systemd's expansion: ``%i``, ``${VAR}`` as one word, ``$VAR`` split at whitespace."""
    words: list[str] = []
    for word in shlex.split(exec_start.replace("%i", instance)):
        whole = re.fullmatch(r"\$([A-Za-z_][A-Za-z0-9_]*)", word)
        if whole:
            words.extend(env.get(whole.group(1), "").split())
        else:
            words.append(re.sub(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}", lambda m: env[m.group(1)], word))
    return words


def _console_scripts() -> dict[str, str]:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]


def _parser(script: str):
    if script == "voxelwatch":  # the umbrella command with every subcommand
        import argparse

        parser = argparse.ArgumentParser(prog="voxelwatch")
        sub = parser.add_subparsers(dest="command")
        for register in vw_cli._SUBCOMMANDS:
            register(sub)
        return parser
    if script == "voxelwatch-fusion":
        return fusion_cli.build_parser()
    if script == "voxelwatch-camera":
        try:
            module = importlib.import_module("camera_worker.cli")
        except ModuleNotFoundError:
            pytest.skip("camera_worker.cli is not there: the camera unit's flags cannot be checked")
        return module.build_parser()
    raise AssertionError(f"no parser known for {script}")


def _parse(script: str, args: list[str]):
    parser = _parser(script)
    try:
        return parser.parse_args(args)
    except SystemExit:
        pytest.fail(f"{script} refuses the arguments {args}")


ENV = _env_file(ENV_FILE.read_text(encoding="utf-8"))
# the examples the env file's comments suggest
EXAMPLE_EXTRAS = {
    "VOXELWATCH_CAMERA_ARGS": "--source /dev/video2",
    "VOXELWATCH_FUSION_ARGS": "--out /var/lib/voxelwatch/files",
    "VOXELWATCH_NOTIFY_ARGS": "--reader kitchen-tablet",
    "VOXELWATCH_VIEW_ARGS": "--listen 0.0.0.0:8080",
}


def test_env_file_names_the_site_and_documents_the_extras():
    assert ENV["VOXELWATCH_SITE"] == "/etc/voxelwatch/site.toml"
    text = ENV_FILE.read_text()
    for key, example in EXAMPLE_EXTRAS.items():
        assert key in ENV and f'{key}="{example}"' in text


@pytest.mark.parametrize("unit", ["voxelwatch-camera@.service", "voxelwatch-fusion.service", "voxelwatch-router.service",
                                  "voxelwatch-notify.service", "voxelwatch-view.service"])
def test_unit_runs_as_a_dedicated_user_and_restarts(unit):
    values = _unit(UNITS / unit)
    assert values["User"] == ["voxelwatch"] and values["Group"] == ["voxelwatch"]
    assert values["Restart"] == ["always"]
    assert float(values["RestartSec"][0]) > 0
    assert "/etc/voxelwatch/voxelwatch.env" in values["EnvironmentFile"]
    assert values["WantedBy"] == ["multi-user.target"]
    script = Path(shlex.split(values["ExecStart"][0])[0]).name
    assert script in _console_scripts(), f"{unit}: {script} is not a console script of the project"


@pytest.mark.parametrize("extras", [False, True], ids=["plain", "with-extras"])
def test_camera_unit_command_is_accepted_by_the_camera_parser(extras):
    values = _unit(UNITS / "voxelwatch-camera@.service")
    assert "-/etc/voxelwatch/camera-%i.env" in values["EnvironmentFile"]  # per-camera flags, optional
    assert values["SupplementaryGroups"] == ["video"]
    env = {**ENV, **(EXAMPLE_EXTRAS if extras else {})}
    argv = _exec_argv(values["ExecStart"][0], env, "cam3")
    assert Path(argv[0]).name == "voxelwatch-camera"
    args = _parse("voxelwatch-camera", argv[1:])
    assert str(args.site) == "/etc/voxelwatch/site.toml"
    assert args.camera == "cam3"
    # the moved-camera check's reference picture survives restarts, one per camera, in the unit's state
    assert values["StateDirectory"] == ["voxelwatch"] and args.view_reference == "/var/lib/voxelwatch/view-cam3.png"
    if extras:
        assert str(args.source) == "/dev/video2"


@pytest.mark.parametrize("extras", [False, True], ids=["plain", "with-extras"])
def test_fusion_unit_command_is_accepted_by_the_fusion_parser(extras):
    values = _unit(UNITS / "voxelwatch-fusion.service")
    env = {**ENV, **(EXAMPLE_EXTRAS if extras else {})}
    argv = _exec_argv(values["ExecStart"][0], env, "")
    assert Path(argv[0]).name == "voxelwatch-fusion"
    args = _parse("voxelwatch-fusion", argv[1:])
    assert str(args.site) == "/etc/voxelwatch/site.toml"
    # the store and the carving cache live where systemd makes them writable
    assert values["StateDirectory"] == ["voxelwatch"] and args.store.parent == Path("/var/lib/voxelwatch")
    assert values["CacheDirectory"] == ["voxelwatch"] and args.cache_dir == Path("/var/cache/voxelwatch")
    assert args.connect == ["tcp/127.0.0.1:7447"]  # the router on the same host
    assert "voxelwatch-router.service" in values["After"][0]
    if extras:
        assert args.out == Path("/var/lib/voxelwatch/files")


@pytest.mark.parametrize("extras", [False, True], ids=["plain", "with-extras"])
def test_notify_unit_command_is_accepted_by_the_notify_parser(extras):
    values = _unit(UNITS / "voxelwatch-notify.service")
    env = {**ENV, **(EXAMPLE_EXTRAS if extras else {})}
    argv = _exec_argv(values["ExecStart"][0], env, "")
    assert Path(argv[0]).name == "voxelwatch" and argv[1] == "notify"
    args = _parse("voxelwatch", argv[1:])
    assert str(args.site) == "/etc/voxelwatch/site.toml"
    # the outbox lives where systemd makes it writable
    assert values["StateDirectory"] == ["voxelwatch"] and args.outbox.parent == Path("/var/lib/voxelwatch")
    assert args.connect == ["tcp/127.0.0.1:7447"]  # the router on the same host
    assert "voxelwatch-router.service" in values["After"][0]
    if extras:
        assert args.reader == "kitchen-tablet"


@pytest.mark.parametrize("extras", [False, True], ids=["plain", "with-extras"])
def test_view_unit_command_is_accepted_by_the_view_parser(extras):
    values = _unit(UNITS / "voxelwatch-view.service")
    env = {**ENV, **(EXAMPLE_EXTRAS if extras else {})}
    argv = _exec_argv(values["ExecStart"][0], env, "")
    assert Path(argv[0]).name == "voxelwatch" and argv[1] == "view"
    args = _parse("voxelwatch", argv[1:])
    assert str(args.site) == "/etc/voxelwatch/site.toml"
    assert args.connect == ["tcp/127.0.0.1:7447"] and args.mode == "client"  # the router on the same host
    assert args.listen == ("0.0.0.0:8080" if extras else None)  # else the site's [view] listen
    assert "voxelwatch-router.service" in values["After"][0]


def test_units_pass_systemd_analyze_verify(tmp_path):
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed")
    bin_dir = Path(sys.executable).parent
    for unit in UNITS.glob("*.service"):
        text = unit.read_text().replace("/opt/voxelwatch/venv/bin", str(bin_dir))
        (tmp_path / unit.name).write_text(text)
    names = ["voxelwatch-router.service", "voxelwatch-fusion.service", "voxelwatch-camera@cam1.service",
             "voxelwatch-notify.service", "voxelwatch-view.service"]
    run = subprocess.run([analyze, "verify", "--man=no", *names], cwd=tmp_path, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_router_unit_command_routes_between_clients_configured_from_client_json5():
    """The router unit's command, listening on loopback instead of every
    interface, with two client sessions from client.json5 pointed at it."""
    values = _unit(UNITS / "voxelwatch-router.service")
    argv = _exec_argv(values["ExecStart"][0], {**ENV, "VOXELWATCH_SITE": str(SITE)}, "")
    assert Path(argv[0]).name == "voxelwatch" and argv[1] == "router"
    assert argv[argv.index("--site") + 1] == str(SITE)  # TLS and access control come from the site file
    listen_at = argv.index("--listen") + 1
    assert argv[listen_at] == "tcp/0.0.0.0:7447"
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    argv[listen_at] = endpoint
    command = [sys.executable, "-c", "import sys; from voxelwatch.cli import main; sys.exit(main())", *argv[1:]]
    router = subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first_line: list[str] = []
        reader = threading.Thread(target=lambda: first_line.append(router.stdout.readline()), daemon=True)
        reader.start()
        reader.join(timeout=60)
        said = router.stderr.read() if router.poll() is not None else ""
        assert first_line and "listening on" in first_line[0], f"router did not start: {said}"

        def client() -> zenoh.Config:
            conf = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "client.json5"))
            conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
            return conf

        got = threading.Event()
        received: list[str] = []

        def on_sample(sample) -> None:
            received.append(sample.payload.to_string())
            got.set()

        key = "voxelwatch/maple-court-flat-4/events/fall/7"
        with zenoh.open(client()) as reader_session, zenoh.open(client()) as writer_session:
            sub = reader_session.declare_subscriber("voxelwatch/maple-court-flat-4/events/**", on_sample)
            try:
                for _ in range(100):  # the subscription reaches the router shortly after declaration
                    writer_session.put(key, '{"kind": "fall"}')
                    if got.wait(0.1):
                        break
            finally:
                sub.undeclare()
        assert received and received[0] == '{"kind": "fall"}'
    finally:
        router.terminate()  # SIGTERM, what systemd sends on stop
        try:
            code = router.wait(timeout=30)
        except subprocess.TimeoutExpired:
            router.kill()
            raise
        router.stdout.close()
        router.stderr.close()
    assert code == 0


def test_two_peers_configured_from_peer_json5_talk_without_a_router():
    """peer.json5 on loopback: each peer listens on its own endpoint, the
    second connects to the first (as a camera host connects to the fusion host)."""
    first, second = f"tcp/127.0.0.1:{_free_port()}", f"tcp/127.0.0.1:{_free_port()}"

    def peer(listen: str, connect: list[str]) -> zenoh.Config:
        conf = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "peer.json5"))
        conf.insert_json5("listen/endpoints", json.dumps([listen]))
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        return conf

    got = threading.Event()
    with zenoh.open(peer(first, [])) as fusion_side, zenoh.open(peer(second, [first])) as camera_side:
        sub = fusion_side.declare_subscriber("voxelwatch/maple-court-flat-4/cam/cam1/mask", lambda s: got.set())
        try:
            for _ in range(100):
                camera_side.put("voxelwatch/maple-court-flat-4/cam/cam1/mask", b"mask")
                if got.wait(0.1):
                    break
        finally:
            sub.undeclare()
    assert got.is_set()


def _clip(path: Path, n_frames: int) -> None:
    """A 640x480 MJPG clip: an empty textured room, then a dark block walking across."""
    import cv2

    rng = np.random.default_rng(3)
    room = cv2.GaussianBlur((rng.random((480, 640, 3)) * 60 + 80).astype(np.uint8), (0, 0), 5)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15.0, (640, 480))
    for i in range(n_frames):
        frame = room.copy()
        if i >= n_frames // 3:
            x = 200 + 3 * (i - n_frames // 3)
            cv2.rectangle(frame, (x, 150), (x + 60, 400), (20, 30, 200), -1)
        writer.write(frame)
    writer.release()


def _logs(folder: Path) -> str:
    return "\n".join(f"--- {log.name}\n{log.read_text()}" for log in sorted(folder.glob("*.log")))


def _script(name: str) -> list[str]:
    mains = {"voxelwatch": "voxelwatch.cli", "voxelwatch-fusion": "fusion_server.cli", "voxelwatch-camera": "camera_worker.cli"}
    return [sys.executable, "-c", f"import sys; from {mains[name]} import main; sys.exit(main())"]


@pytest.mark.slow
def test_units_run_together_router_fusion_and_two_cameras(tmp_path):
    """The three units' commands on loopback (paths and endpoints swapped for
    the test's): two workers replay a clip, the fusion server fuses, stores the
    camera_lost events when they stop and answers a history query through the
    router with JSON, one reply per event with zenoh's default consolidation,
    as the README's z_get example expects."""
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    clip = tmp_path / "clip.avi"
    _clip(clip, 45)
    env = {**ENV, "VOXELWATCH_SITE": str(SITE)}

    def argv_of(unit: str, instance: str = "") -> list[str]:
        argv = _exec_argv(_unit(UNITS / unit)["ExecStart"][0], env, instance)
        swaps = {"tcp/0.0.0.0:7447": endpoint, "tcp/127.0.0.1:7447": endpoint,
                 "/var/lib/voxelwatch/events.sqlite": str(tmp_path / "events.sqlite"),
                 "/var/cache/voxelwatch": str(tmp_path / "cache")}
        return _script(Path(argv[0]).name) + [swaps.get(a, a) for a in argv[1:]]

    logs = {}

    def start(name: str, argv: list[str]) -> subprocess.Popen:
        logs[name] = open(tmp_path / f"{name}.log", "w")
        return subprocess.Popen(argv, cwd=REPO, stdout=logs[name], stderr=subprocess.STDOUT, text=True)

    procs = {"router": start("router", argv_of("voxelwatch-router.service"))}
    try:
        procs["fusion"] = start("fusion", argv_of("voxelwatch-fusion.service") + ["--out", str(tmp_path / "out")])
        conf = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "client.json5"))
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        selector = "voxelwatch/maple-court-flat-4/history/events/**?since=2000-01-01T00:00:00Z;kind=camera_stopped"
        lost: set[str] = set()
        with zenoh.open(conf) as session:
            # the fusion server is ready once its liveliness token is up (its first start computes carving tables)
            for _ in range(600):
                if list(session.liveliness().get("voxelwatch/maple-court-flat-4/alive/fusion", timeout=1.0)):
                    break
                assert procs["fusion"].poll() is None, _logs(tmp_path)
                time.sleep(0.5)
            else:
                pytest.fail(f"the fusion server never came up\n{_logs(tmp_path)}")
            start_ns = str(time.time_ns())
            for cam in ("cam1", "cam2"):
                extra = ["--source", str(clip), "--start-ns", start_ns, "--connect", endpoint]
                procs[cam] = start(cam, argv_of("voxelwatch-camera@.service", cam) + extra)
            for cam in ("cam1", "cam2"):
                assert procs[cam].wait(timeout=120) == 0, _logs(tmp_path)
            for _ in range(60):  # the liveliness of a stopped worker lapses shortly after it exits
                lost = set()
                for reply in session.get(selector, timeout=5.0):
                    event = json.loads(reply.ok.payload.to_string())
                    assert event["kind"] == "camera_stopped"
                    lost.add(event["details"]["camera"])
                if lost >= {"cam1", "cam2"}:
                    break
                time.sleep(0.5)
        assert lost >= {"cam1", "cam2"}, _logs(tmp_path)
        procs["fusion"].terminate()
        assert procs["fusion"].wait(timeout=60) == 0, _logs(tmp_path)
        rows = (tmp_path / "out" / "tracks.csv").read_text().splitlines()
        assert rows[0] == "frame,stamp_ns,id,x,y,z_top,posture,person"
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
        for log in logs.values():
            log.close()


# ---------------------------------------------------------------- compose and image


def _compose_services() -> dict[str, dict]:
    """Each service's exec-form command and device mappings (the file keeps both on simple lines)."""
    services: dict[str, dict] = {}
    current = None
    in_services = False
    in_devices = False
    for line in (DEPLOY / "compose.yaml").read_text().splitlines():
        if line.startswith("services:"):
            in_services = True
            continue
        if in_services and re.match(r"^\S", line):
            in_services = False
        if not in_services:
            continue
        head = re.match(r"^  ([A-Za-z0-9_-]+):\s*$", line)
        if head:
            current = services.setdefault(head.group(1), {"command": None, "devices": []})
            in_devices = False
            continue
        command = re.match(r"^    command: (\[.*\])\s*$", line)
        if command:
            current["command"] = json.loads(command.group(1))
        in_devices = line.startswith("    devices:") or (in_devices and line.startswith("      - "))
        if in_devices and line.startswith("      - "):
            current["devices"].append(line.split("- ", 1)[1].strip())
    return services


def test_compose_has_the_router_the_fusion_server_and_one_worker_per_camera(site):
    services = _compose_services()
    assert set(services) == {"router", "fusion", "notify", "view", *site.camera_ids}
    hosts = []
    for cam_id in site.camera_ids:
        devices = services[cam_id]["devices"]
        assert len(devices) == 1 and devices[0].endswith(":/dev/video0"), devices
        hosts.append(devices[0].split(":")[0])
        # the site names /dev/video0 as every camera's source: the container's view
        assert site.camera(cam_id).source == "/dev/video0"
    assert len(set(hosts)) == len(hosts), f"two workers share a camera: {hosts}"


def test_compose_commands_are_accepted_by_the_real_parsers(site):
    services = _compose_services()
    scripts = _console_scripts()
    for name, service in services.items():
        argv = service["command"]
        assert argv and argv[0] in scripts, f"{name}: {argv}"
        if argv[:2] == ["voxelwatch", "view"]:
            args = _parse("voxelwatch", argv[1:])
            assert str(args.site) == "/etc/voxelwatch/site.toml" and args.connect == ["tcp/router:7447"]
            assert args.listen == "0.0.0.0:8080"  # inside its container; published on the host's loopback only
            continue
        if argv[:2] == ["voxelwatch", "router"]:
            assert argv[1:] == ["router", "--site", "/etc/voxelwatch/site.toml", "--listen", "tcp/0.0.0.0:7447"]
            continue
        if argv[:2] == ["voxelwatch", "notify"]:
            args = _parse("voxelwatch", argv[1:])
            assert str(args.site) == "/etc/voxelwatch/site.toml" and args.connect == ["tcp/router:7447"]
            assert args.outbox.parent == Path("/var/lib/voxelwatch")  # in the notify-state volume
            continue
        args = _parse(argv[0], argv[1:])
        assert str(args.site) == "/etc/voxelwatch/site.toml"
        assert args.connect == ["tcp/router:7447"]
        if argv[0] == "voxelwatch-camera":
            assert args.camera == name


def test_containerfile_copies_every_package_and_existing_paths():
    text = (DEPLOY / "Containerfile").read_text()
    sources = [word for line in text.splitlines() if line.startswith("COPY ") for word in line.split()[1:-1]]
    packages = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    for pattern in packages:
        assert pattern.rstrip("*") in sources, f"the image lacks the package {pattern}"
    for source in sources:
        if source != "README.md":  # written with the documentation; pyproject needs it to build
            assert (REPO / source).exists(), f"Containerfile copies {source}, which does not exist"
    assert "pip install ." in text and "USER voxelwatch" in text
