"""``voxelwatch``: the umbrella command.

Each subcommand lives in its own small function that parses nothing but its
own arguments and hands plain values to the library.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from common.shell import add_logging_arguments, configure_logging

DESCRIPTION = """\
voxelwatch: multi-camera 3D sensing of people at home.

Camera hosts segment their own video and publish compressed foreground masks
over zenoh; one fusion server carves them into voxels, tracks people, judges
posture, dwelling and falls, and publishes tracks and events.
"""

EPILOG = """\
examples:
  voxelwatch demo                             the synthetic house as a distributed system on this machine
  voxelwatch synth --scenario demo --out out/demo     render a scenario with its ground truth
  voxelwatch replay --site out/demo/site.toml --input out/demo --out out/run
  voxelwatch eval --truth out/demo --run out/run       score a run against ground truth
  voxelwatch eval --suite                     the whole scenario library
  voxelwatch bench                            speed and size of every stage on this machine
  voxelwatch site check deploy/site.toml      validate a site file and its calibrations
  voxelwatch calibrate floor --site deploy/site.toml --clip cam1=board1.avi ...   camera poses from a board on the floor
  voxelwatch router --listen tcp/0.0.0.0:7447  a zenoh router for client-mode hosts
  voxelwatch certs --site deploy/site.toml    the site's authority and one TLS certificate per host
  voxelwatch router --site deploy/site.toml   the router with the site's TLS and access control
  voxelwatch notify --site deploy/site.toml  alarms to MQTT/Home Assistant, webhooks and e-mail
  voxelwatch camera --help                    the camera worker (same as voxelwatch-camera)
  voxelwatch fusion --help                    the fusion server (same as voxelwatch-fusion)
"""


def build_parser() -> argparse.ArgumentParser:
    """The umbrella command's parser with every subcommand (each sets its ``handler``)."""
    parser = argparse.ArgumentParser(
        prog="voxelwatch", description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_logging_arguments(parser)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for register in _SUBCOMMANDS:
        register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # camera and fusion hand every remaining argument to their own parsers
    if argv and argv[0] in _PASSTHROUGH:
        return _PASSTHROUGH[argv[0]]()(argv[1:])
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    configure_logging(args.verbose, args.quiet)
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        return 130
    except ValueError as exc:  # configuration problems carry their own clear message
        print(f"voxelwatch {args.command}: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        from camera_worker.sources import SourceError

        if not isinstance(exc, (SourceError, OSError)):
            raise
        print(f"voxelwatch {args.command}: {exc}", file=sys.stderr)  # an input that cannot be read
        return 1


def _camera_main() -> Callable[[Sequence[str]], int]:
    from camera_worker.cli import main as camera_main

    return camera_main


def _fusion_main() -> Callable[[Sequence[str]], int]:
    from fusion_server.cli import main as fusion_main

    return fusion_main


_PASSTHROUGH: dict[str, Callable[[], Callable[[Sequence[str]], int]]] = {
    "camera": _camera_main,
    "fusion": _fusion_main,
}


def _register_passthrough(sub) -> None:
    sub.add_parser("camera", help="run one camera worker (voxelwatch-camera)", add_help=False)
    sub.add_parser("fusion", help="run the fusion server (voxelwatch-fusion)", add_help=False)


def _register_site(sub) -> None:
    p = sub.add_parser("site", help="check a site file, its calibrations and enrolled residents")
    p.add_argument("action", choices=["check"],
                   help="check: validate the file, load every calibration and every enrolled resident's model")
    p.add_argument("path", help="the site TOML file")
    p.add_argument("--clip", action="append", default=[], metavar="CAM=FILE",
                   help="a clip of people walking from camera CAM (video, image or mask folder; all clips recorded "
                        "together, 3 cameras or more): report how well each camera sees them where the others do")
    p.set_defaults(handler=_site_check)


def _site_check(args: argparse.Namespace) -> int:
    from common.site import load_site
    from fusion_server.settings import FusionSettings

    site = load_site(args.path)  # endpoints are checked here, as the processes check them
    cameras = site.load_cameras()
    residents = site.load_residents()
    FusionSettings(site=site, prefix=site.prefix)  # what the fusion server refuses at start (min_cameras ...)
    print(f"site {site.name}: prefix {site.prefix}, volume {list(site.volume.min_m)} .. {list(site.volume.max_m)} m")
    for cam_id, cam in cameras.items():
        x, y, z = cam.center
        print(f"  camera {cam_id}: {cam.model} {cam.width}x{cam.height}, centre ({x:.2f}, {y:.2f}, {z:.2f}) m")
    print(f"  {len(site.hotspots)} hot spots, {len(site.doors)} doors, {len(site.occluders)} occluders; "
          f"long lie after {site.events.long_lie_s:g} s, "
          f"inactivity after {site.events.inactivity_s:g} s")
    print(f"  identity: a person who leaves keeps their track id for {site.identity.reid_window_s:g} s; "
          f"colours asked {site.identity.rate_hz:g} times a second; {site.residents} residents, {len(residents)} enrolled")
    for spec, resident in zip(site.enrolled, residents):
        print(f"  enrolled {resident.name}: {_model_summary(resident.model)} ({site.resolve(spec.model)})")
    for line in _network_lines(site):
        print(f"  {line}")
    if args.clip:
        from calibrate.check import check_clips

        clips = dict(c.split("=", 1) for c in args.clip if "=" in c)
        if len(clips) != len(args.clip):
            raise ValueError("--clip takes CAM=FILE")
        for check in check_clips(site, clips):
            print(f"  {check.line()}")
    return 0


def _network_lines(site) -> list[str]:
    """What the site's [zenoh] section means for security, with warnings for plain transport."""
    from common.transport import plain_endpoints

    z = site.zenoh
    plain = plain_endpoints(z)
    if z.tls is None:
        return [f"zenoh: {z.mode} mode, {', '.join([*z.listen, *z.connect]) or 'no endpoints'}",
                "WARNING: zenoh runs over plain TCP: anyone on the network can read tracks and events and publish "
                "fake ones. Make certificates with 'voxelwatch certs' and add a [zenoh.tls] section "
                "(docs/guides/securing.md)."]
    acl = "the router lets each host do only its part" if z.tls.access_control else "no access control"
    lines = [f"zenoh: {z.mode} mode over TLS with mutual authentication (authority {site.resolve(z.tls.ca)}); {acl}; "
             f"readers {', '.join(z.tls.readers)}"]
    if plain:
        lines.append(f"WARNING: endpoints without TLS: {', '.join(plain)}: use tls/HOST:PORT")
    if z.mode == "peer":
        lines.append("WARNING: peer mode: only a router enforces the access control; use mode = \"client\" "
                     "and voxelwatch router --site on the fusion host")
    if not site.resolve(z.tls.ca).is_file():
        lines.append(f"WARNING: the authority {site.resolve(z.tls.ca)} is missing")
    return lines


def _model_summary(model) -> str:
    """Frames learnt per body band and the standing height of an appearance model, in words."""
    from common.appearance import BANDS

    bands = ", ".join(f"{band} {int(n)}" for band, n in zip(BANDS, model.frames))
    height = f"{model.height_m:.2f} m tall" if model.height_m == model.height_m else "height unknown"
    return f"frames learnt {bands}; {height}"


def _register_router(sub) -> None:
    p = sub.add_parser("router", help="run a zenoh router (for client-mode hosts)")
    p.add_argument("--site", type=Path, default=None,
                   help="the site TOML file: its [zenoh] settings, TLS and access control (default: plain TCP, no site)")
    p.add_argument("--listen", action="append", default=None,
                   help="endpoint to listen on (repeatable), default tcp/0.0.0.0:7447, or tls/0.0.0.0:7447 for a "
                        "site with [zenoh.tls]")
    p.add_argument("--tls-cert", type=Path, default=None, help="the router's certificate (default: router.pem in the site's certs folder)")
    p.add_argument("--tls-key", type=Path, default=None, help="the router's private key (default: router-key.pem beside it)")
    p.add_argument("--multicast-scouting", action="store_true", help="answer multicast scouting")
    p.set_defaults(handler=_router)


def _router(args: argparse.Namespace) -> int:
    import zenoh

    from common.shell import stop_on_signals
    from common.transport import short_error

    conf, listen, how = _router_config(args)
    with stop_on_signals() as stop:
        try:
            session = zenoh.open(conf)
        except Exception as exc:  # noqa: BLE001 - zenoh reports a busy port or a bad certificate as ZError
            print(f"voxelwatch router: cannot listen on {', '.join(listen)}: {short_error(exc)}", file=sys.stderr)
            return 1
        with session:
            print(f"voxelwatch router listening on {', '.join(listen)} ({how})", flush=True)
            stop.wait()
    return 0


def _router_config(args: argparse.Namespace):
    """``(the router's zenoh configuration, the endpoints it listens on, how it is secured, in words)``
    from the arguments and the site file; ValueError on any problem."""
    from common.certs import ROUTER
    from common.site import ZenohSettings, load_site
    from common.transport import site_config, zenoh_config

    if args.site is not None:
        site = load_site(args.site)
        if args.multicast_scouting:
            site = site.model_copy(update={"zenoh": site.zenoh.model_copy(update={"multicast_scouting": True})})
        secure = site.zenoh.tls is not None
        listen = args.listen or [f"{'tls' if secure else 'tcp'}/0.0.0.0:7447"]
        conf = site_config(site, host=ROUTER, mode="router", listen=listen, connect=[],
                           tls_cert=args.tls_cert, tls_key=args.tls_key)
        how = ("TLS, access control for " + ", ".join(site.camera_ids) if secure and site.zenoh.tls.access_control
               else "TLS, no access control" if secure else "plain TCP: no authentication, no access control")
    else:
        if args.tls_cert or args.tls_key:
            raise ValueError("--tls-cert/--tls-key need --site (its [zenoh.tls] section names the authority)")
        listen = args.listen or ["tcp/0.0.0.0:7447"]
        conf = zenoh_config(ZenohSettings(multicast_scouting=bool(args.multicast_scouting)), mode="router", listen=listen)
        how = "plain TCP: no authentication, no access control"
    return conf, listen, how


def _register_certs(sub) -> None:
    p = sub.add_parser("certs", help="make the site's certificate authority and one certificate per host (TLS)")
    p.add_argument("--site", type=Path, required=True, help="the site TOML file (its name, cameras and readers)")
    p.add_argument("--out", type=Path, default=None,
                   help="folder to write into (default: the site's [zenoh.tls] certs folder, else certs/ beside the site file)")
    p.add_argument("--reader", action="append", default=None, metavar="NAME",
                   help="a reader's certificate (repeatable; default: the site's [zenoh.tls] readers, or 'reader')")
    p.add_argument("--name", action="append", default=[], metavar="HOST=NAME[,NAME]",
                   help="extra DNS names or addresses for a host's certificate (host: router, fusion, a camera id, a "
                        "reader, or * for all), e.g. --name router=fusion.local --name cam1=192.168.1.21; the host "
                        "names of the site's endpoints go to the router and fusion certificates by themselves")
    p.add_argument("--days", type=int, default=3650, help="validity in days (default 3650)")
    p.add_argument("--force", action="store_true", help="replace an existing authority (every host then needs its new files)")
    p.add_argument("--reuse-ca", action="store_true",
                   help="keep the existing authority and sign certificates for the hosts that have none yet")
    p.set_defaults(handler=_certs)


def _certs(args: argparse.Namespace) -> int:
    from common.certs import FUSION, ROUTER, make_site_certs, where_to_copy
    from common.site import load_site

    site = load_site(args.site)
    tls = site.zenoh.tls
    out = args.out if args.out is not None else site.resolve(tls.certs or ".") if tls else site.base_dir / "certs"
    readers = args.reader if args.reader is not None else (tls.readers if tls else ["reader"])
    names: dict[str, list[str]] = {}
    for host in _endpoint_hosts([*site.zenoh.connect, *site.zenoh.listen]):
        for role in (ROUTER, FUSION):
            names.setdefault(role, []).append(host)
    for item in args.name:
        host, sep, text = item.partition("=")
        if not sep or not host or not text:
            raise ValueError(f"--name {item!r}: expected HOST=NAME[,NAME], e.g. router=fusion.local")
        names.setdefault(host.strip(), []).extend(n.strip() for n in text.split(",") if n.strip())
    made = make_site_certs(out, site=site.name, cameras=site.camera_ids, readers=readers, names=names,
                           force=args.force, reuse_ca=args.reuse_ca, days=args.days)
    print(f"site {site.name}: {'the existing authority' if made.ca_reused else 'new authority'} "
          f"{made.ca}; {len(made.hosts)} new host certificates in {made.folder} (keys mode 0600)")
    print(f"keep {made.ca_key.name} off the network (it makes certificates); copy to each host only its own files:")
    for line in where_to_copy(made):
        print(f"  {line}")
    unlisted = [r for r in readers if tls is not None and r not in tls.readers]
    if unlisted:
        print(f"the router lets only the site's readers read: add {', '.join(unlisted)} to [zenoh.tls] readers")
    if tls is None:
        print("then add to the site file:\n  [zenoh.tls]\n  ca = \"certs/ca.pem\"\n  certs = \"certs\"\n"
              "and make every endpoint tls/ (e.g. connect = [\"tls/fusion.local:7447\"])")
    return 0


def _endpoint_hosts(endpoints) -> list[str]:
    """Host names in zenoh endpoints (``tls/fusion.local:7447`` -> ``fusion.local``), wildcards left out."""
    hosts = []
    for endpoint in endpoints:
        _, _, address = endpoint.partition("/")
        host = address.split("#")[0].rsplit(":", 1)[0].strip("[]")
        if host and host not in ("0.0.0.0", "::", "localhost", "127.0.0.1") and host not in hosts:
            hosts.append(host)
    return hosts


def _register_synth(sub) -> None:
    p = sub.add_parser("synth", help="render a synthetic-house scenario or a random world: media, site file, ground truth")
    p.add_argument("--world", default="house", choices=["house", "random"],
                   help="house: the synthetic house (default); random: a randomised world drawn from --seed "
                        "(seeds 0-999 tune, 1000 and up evaluate)")
    p.add_argument("--scenario", default=None, help="scenario name (default: the demo scenario); --list shows them")
    p.add_argument("--out", type=Path, help="output folder")
    p.add_argument("--seed", type=int, default=0, help="random seed (every scenario is deterministic for a seed)")
    p.add_argument("--cameras", default=None, help="comma-separated camera ids (default all five)")
    p.add_argument("--frames", type=int, default=None, help="render only the first N frames")
    p.add_argument("--masks", action="store_true", help="also write the true silhouettes as PNG")
    p.add_argument("--codec", default="MJPG", choices=["MJPG", "FFV1"], help="video codec")
    p.add_argument("--workers", type=int, default=1, help="render cameras in this many processes")
    p.add_argument("--sensors", default="colour", choices=["colour", "mixed"],
                   help="with --world random: every camera colour (default), or a mixed rig: one depth and one "
                        "thermal camera among them (the same world otherwise)")
    p.add_argument("--list", action="store_true", help="list the scenarios and exit")
    p.set_defaults(handler=_synth)


def _synth(args: argparse.Namespace) -> int:
    import synth

    if args.list:
        for name in synth.list_scenarios():
            spec = synth.scenario_spec(name)
            print(f"{name:18s} {spec.duration_s / 60:5.1f} min  {len(spec.people)} people  {spec.description}")
        return 0
    if args.out is None:
        raise ValueError("--out is required (the folder to write into)")
    if args.world == "random":
        return _synth_world(args)
    if args.sensors != "colour":
        raise ValueError("--sensors is for --world random")
    name = args.scenario or synth.DEFAULT_SCENARIO
    cameras = args.cameras.split(",") if args.cameras else None
    out = synth.write_scenario(
        name, args.out, seed=args.seed, cameras=cameras, frames=args.frames, masks=args.masks,
        codec=args.codec, workers=args.workers,
    )
    print(f"scenario {name}: {out.n_frames} frames of {len(out.videos)} cameras in {out.out_dir}")
    print(f"  site {out.site}\n  truth {out.tracks}, {out.events}")
    return 0


def _synth_world(args: argparse.Namespace) -> int:
    from synth.world import random_world, write_world

    if args.scenario or args.cameras or args.masks:
        raise ValueError("--scenario, --cameras and --masks are for --world house; a random world is all its --seed")
    world = random_world(args.seed, sensors=args.sensors)
    out = write_world(world, args.out, frames=args.frames)
    s = world.summary()
    room = s["room"]
    print(f"{world.name} ({s['seed_set']} seed): {room['shape']} room {room['size_m'][0]:.1f} x {room['size_m'][1]:.1f} m, "
          f"{s['cameras']} cameras ({s['rig_label']}{', ceiling fisheye' if s['fisheye'] else ''}), "
          f"{s['people']} people ({', '.join(s['behaviours'])}"
          f"{'; every adult dressed alike' if s['dress'] == 'alike' else ''}), {out.n_frames} frames of {s['media']}")
    for cam, why in s.get("sensors", {}).get("why", {}).items():
        print(f"  {cam} {why}")
    print(f"  site {out.site}\n  truth {out.truth_dir}")
    return 0


def _register_replay(sub) -> None:
    p = sub.add_parser("replay", help="run the pipeline offline in one process and write tracks and events")
    p.add_argument("--site", type=Path, help="the site TOML file (default with --synthetic: the synthetic house)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--input", type=Path, help="folder with one sub-folder per camera: video.*, background.*, or masks/")
    src.add_argument("--synthetic", metavar="SCENARIO", help="render a synthetic-house scenario in this process")
    p.add_argument("--out", type=Path, required=True, help="output folder for tracks.csv and events.jsonl")
    p.add_argument("--cameras", default=None, help="comma-separated subset of the site's cameras")
    p.add_argument("--frames", type=int, default=None, help="stop after N frame sets")
    p.add_argument("--seed", type=int, default=0, help="seed of the tracker (and of the synthetic scenario)")
    p.add_argument("--cache-dir", type=Path, default=None, help="carving lookup-table cache")
    p.add_argument("--overlays", type=int, default=None, metavar="N",
                   help="every N frames, write each camera's frame with its mask overlaid to OUT/overlays/")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_replay)


def _replay(args: argparse.Namespace) -> int:
    from fusion_server.replay import replay

    site = _replay_site(args)
    cameras = args.cameras.split(",") if args.cameras else None
    summary = replay(
        site, args.out, input_dir=args.input, synthetic=args.synthetic, cameras=cameras, max_frames=args.frames,
        seed=args.seed, cache_dir=args.cache_dir, progress=None if args.quiet else _progress_bar(),
        overlay_every=args.overlays,
    )
    if not args.quiet:
        print(file=sys.stderr)
    print(
        f"replay: {summary.frames} frame sets of {len(summary.cameras)} cameras in {summary.elapsed_s:.1f} s "
        f"({summary.fps:.1f}/s), {summary.track_rows} track rows, {summary.events} events -> {args.out}"
    )
    return 0


def _replay_site(args: argparse.Namespace):
    from common.site import load_site

    if args.site is not None:
        return load_site(args.site)
    if args.synthetic is None:
        raise ValueError("--site is required with --input")
    from synth import default_site

    return default_site(args.out / "site")


def _progress_bar():
    import time

    start = time.perf_counter()

    def show(done: int, total: int | None, fused) -> None:
        if done % 15 and done != total:
            return
        rate = done / max(time.perf_counter() - start, 1e-9)
        width = 30
        bar = "#" * int(width * done / total) if total else ""
        of = f"/{total}" if total else ""
        print(f"\r[{bar:<{width}}] {done}{of} frames {rate:5.1f}/s  tracks {len(fused.tracks)}", end="", file=sys.stderr, flush=True)

    return show


def _register_enrol(sub) -> None:
    p = sub.add_parser("enrol", help="learn a resident's appearance from a clip of them alone, for the site file")
    p.add_argument("--site", type=Path, help="the site TOML file (default with --synthetic: the synthetic house)")
    p.add_argument("--name", required=True, help="the resident's name (1-64 characters), shown on their tracks and events")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--input", type=Path, help="folder with one sub-folder per camera, as voxelwatch replay reads")
    src.add_argument("--synthetic", metavar="SCENARIO", help="a synthetic-house scenario (its person 1)")
    p.add_argument("--out", type=Path, required=True, help="the enrolment file to write (JSON)")
    p.add_argument("--frames", type=int, default=None, help="use only the first N frame sets")
    p.add_argument("--seed", type=int, default=0, help="seed of the tracker (and of the synthetic scenario)")
    p.add_argument("--cache-dir", type=Path, default=None, help="carving lookup-table cache")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_enrol)


def _enrol(args: argparse.Namespace) -> int:
    import tempfile

    from common.site import load_site
    from fusion_server.enrolment import enrol

    with tempfile.TemporaryDirectory(prefix="voxelwatch-site-") as tmp:
        if args.site is not None:
            site = load_site(args.site)
        elif args.synthetic is None:
            raise ValueError("--site is required with --input")
        else:
            from synth import default_site

            site = default_site(Path(tmp))
        done = enrol(site, args.name, args.out, input_dir=args.input, synthetic=args.synthetic, seed=args.seed,
                     max_frames=args.frames, cache_dir=args.cache_dir, progress=None if args.quiet else _progress_bar())
    if not args.quiet:
        print(file=sys.stderr)
    print(f"enrolled {done.summary()} -> {args.out}")
    print(f"  name it in the site file: [[enrolled]] name = {json.dumps(done.name, ensure_ascii=False)}, "
          f"model = {json.dumps(str(args.out.resolve()), ensure_ascii=False)} (or a path relative to the site file)")
    return 0


def _register_eval(sub) -> None:
    p = sub.add_parser("eval", help="score runs against ground truth (one run, or the scenario suite)")
    p.add_argument("--truth", type=Path, help="ground-truth folder (truth/tracks.csv, truth/events.jsonl)")
    p.add_argument("--run", type=Path, help="run folder (tracks.csv, events.jsonl)")
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON here")
    p.add_argument("--plots", type=Path, default=None, help="draw the plan view and posture timeline into this folder")
    p.add_argument("--suite", action="store_true", help="replay and score the synthetic scenario library (or random worlds)")
    p.add_argument("--world", default="house", choices=["house", "random"],
                   help="with --suite: house scenarios (default) or random worlds (give --seeds)")
    p.add_argument("--seeds", default=None,
                   help="with --suite --world random: seeds, e.g. 1000-1049 or 3,7,20-22 (tuning 0-999, evaluation 1000 and up)")
    p.add_argument("--keep-media", action="store_true", help="with --world random: keep the worlds' masks and videos")
    p.add_argument("--sensors", default="colour", choices=["colour", "mixed"],
                   help="with --suite --world random: colour rigs (default) or mixed rigs (one depth and one thermal "
                        "camera in each world, the same worlds otherwise)")
    p.add_argument("--scenarios", default=None, help="with --suite: comma-separated scenario names (default all)")
    p.add_argument("--quick", action="store_true", help="with --suite: a few short scenarios, first 45 s of each")
    p.add_argument("--cameras", default="5", help="with --suite: comma-separated camera counts to run, e.g. 5,4,3,2")
    p.add_argument("--frames", type=int, default=None, help="with --suite: only the first N frames of each scenario")
    p.add_argument("--out", type=Path, default=Path("voxelwatch-suite"), help="with --suite: working folder")
    p.add_argument("--jobs", type=int, default=1, help="with --suite: scenarios replayed at once, one process each")
    p.add_argument("--mask-scale", type=float, default=None, help="with --suite: masks downscaled by this factor")
    p.add_argument("--enrolled", type=Path, default=None, metavar="FILE",
                   help="with --suite: enrol this file (voxelwatch enrol --synthetic walk, same --seed) and score "
                        "who carries its name")
    p.add_argument("--enrolled-person", type=int, default=1, metavar="ID",
                   help="with --enrolled: the house's person the file enrols (default 1)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", dest="settings",
                   help="with --suite: change a site setting for every replay (repeatable), "
                        "e.g. --set carving.fusion=graphcut")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(handler=_eval)


def _eval(args: argparse.Namespace) -> int:
    if args.suite and args.world == "random":
        from evaluation.world_suite import parse_seeds, run_world_suite

        if args.enrolled is not None:
            raise ValueError("--enrolled is for the house suite: a random world's people are its own")
        if args.seeds is None:
            raise ValueError("--world random needs --seeds, e.g. --seeds 0-19 to tune or --seeds 1000-1049 to report")
        run_world_suite(seeds=parse_seeds(args.seeds), out_dir=args.out, jobs=args.jobs, frames=args.frames,
                        json_path=args.json, keep_media=args.keep_media, settings=args.settings,
                        sensors=args.sensors)
        return 0
    if args.sensors != "colour":
        raise ValueError("--sensors is for --suite --world random")
    if args.suite:
        from evaluation.suite import run_suite

        return run_suite(
            out_dir=args.out, scenarios=args.scenarios.split(",") if args.scenarios else None, quick=args.quick,
            camera_counts=[int(c) for c in args.cameras.split(",")], max_frames=args.frames, seed=args.seed,
            json_path=args.json, jobs=args.jobs, mask_scale=args.mask_scale, enrolled=args.enrolled,
            enrolled_person=args.enrolled_person, settings=args.settings,
        )
    if args.truth is None or args.run is None:
        raise ValueError("give --truth and --run, or --suite")
    from evaluation import evaluate, format_table, write_json

    results = evaluate(args.truth, args.run)
    print(format_table(results))
    if args.json:
        write_json(results, args.json)
    if args.plots:
        from evaluation import plots

        args.plots.mkdir(parents=True, exist_ok=True)
        plots.plan_view(args.run, _site_near(args.truth), args.plots / "plan.png", truth_dir=args.truth)
        plots.timeline(args.run, args.truth, args.plots / "timeline.png")
        print(f"pictures in {args.plots}")
    return 0


def _site_near(folder: Path):
    from common.site import load_site

    path = folder / "site.toml"
    return load_site(path) if path.is_file() else None


def _register_demo(sub) -> None:
    p = sub.add_parser("demo", help="the synthetic house as a distributed system on this machine (the default job)")
    p.add_argument("--scenario", default=None, help="scenario name (default: the demo scenario); voxelwatch synth --list shows them")
    p.add_argument("--world", choices=["random"], default=None,
                   help="instead of the house, the randomised world of --seed (its room, rig and people)")
    p.add_argument("--out", type=Path, default=Path("voxelwatch-demo"), help="output folder (default ./voxelwatch-demo)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the scenario or the world")
    p.add_argument("--frames", type=int, default=None, help="run only the first N frames")
    p.add_argument("--port", type=int, default=None, help="loopback port of the demo's zenoh router (default: a free one)")
    p.add_argument("--sensors", default="colour", choices=["colour", "mixed"],
                   help="with --world random: 'mixed' makes one camera a depth camera and one a thermal camera")
    p.add_argument("--secure", action="store_true",
                   help="TLS with mutual authentication and the site's access control (certificates made in OUT/certs)")
    p.add_argument("--view", nargs="?", const="127.0.0.1:8080", default=None, metavar="HOST:PORT",
                   help="also serve the live view (default 127.0.0.1:8080); its token goes to OUT/view.token")
    p.add_argument("--cache-dir", type=Path, default=None, metavar="DIR",
                   help="where the fusion server keeps its carving tables (default OUT/cache: computed on the first "
                        "run, read on the next)")
    p.add_argument("--cameras", default=None, metavar="IDS",
                   help="the house with only these of its cameras, comma-separated (e.g. cam1,cam3,cam5: a "
                        "lighter demo for a small machine; default all five)")
    p.add_argument("--speed", type=float, default=1.0, metavar="X",
                   help="play the recording at X times real time (default 1; e.g. 0.5 on a machine too small to "
                        "render and segment every camera in real time: people move slower, falls may not read as falls)")
    p.set_defaults(handler=_demo)


def _demo(args: argparse.Namespace) -> int:
    from voxelwatch.demo import SPEEDS, UnknownCameras, run_demo

    if args.world and args.scenario:
        print("voxelwatch demo: give --scenario or --world, not both", file=sys.stderr)
        return 2
    if args.sensors != "colour" and not args.world:
        print("voxelwatch demo: --sensors is for --world random", file=sys.stderr)
        return 2
    if not SPEEDS[0] <= args.speed <= SPEEDS[1]:
        print(f"voxelwatch demo: --speed must lie in {SPEEDS[0]:g}..{SPEEDS[1]:g}, got {args.speed:g}", file=sys.stderr)
        return 2
    if args.cameras and args.world:
        print("voxelwatch demo: --cameras is for the house, not --world", file=sys.stderr)
        return 2
    cameras = [c.strip() for c in args.cameras.split(",") if c.strip()] if args.cameras else None
    try:
        return run_demo(scenario=args.scenario, world=args.world, out_dir=args.out, seed=args.seed, frames=args.frames,
                        port=args.port, secure=args.secure, sensors=args.sensors, view=args.view,
                        cache_dir=args.cache_dir, cameras=cameras, speed=args.speed)
    except UnknownCameras as exc:
        print(f"voxelwatch demo: --cameras: {exc}", file=sys.stderr)
        return 2


def _register_bench(sub) -> None:
    p = sub.add_parser("bench", help="measure every stage's speed and size on this machine")
    p.add_argument("--sections", default=None,
                   help="comma-separated subset of: codec, worker, render, carving, tracking, pipeline, looks, latency; "
                   "and soak (never by default: the demo system for --soak-minutes with processes killed and restarted)")
    p.add_argument("--soak-minutes", type=float, default=30.0, help="soak: how long (default 30)")
    p.add_argument("--soak-speed", type=float, default=4.0, help="soak: times real time (default 4)")
    p.add_argument("--soak-kill-every", type=float, default=180.0, metavar="SECONDS",
                   help="soak: kill and restart a camera worker this often (default 180); the fusion server once, half-way")
    p.add_argument("--soak-out", type=Path, default=Path("voxelwatch-soak"), help="soak: output folder (default ./voxelwatch-soak)")
    p.add_argument("--quick", action="store_true", help="fewer frames and configurations (a minute or two)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures as JSON here")
    p.set_defaults(handler=_bench)


def _bench(args: argparse.Namespace) -> int:
    from evaluation.benchmark import SECTIONS, run_bench

    sections = [s.strip() for s in args.sections.split(",")] if args.sections else list(SECTIONS)
    unknown = sorted(set(sections) - set(SECTIONS) - {"soak"})
    if unknown:
        raise ValueError(f"unknown bench sections {unknown}; sections are {[*SECTIONS, 'soak']}")
    soak = None
    if "soak" in sections:
        from voxelwatch.soak import run_soak

        sections.remove("soak")
        soak = run_soak(minutes=args.soak_minutes, speed=args.soak_speed, kill_every_s=args.soak_kill_every,
                        out_dir=args.soak_out)
    figures = run_bench(sections=sections, quick=args.quick, json_path=None if soak else args.json) if sections else {}
    if soak is not None and args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({**figures, "soak": soak}, indent=2, default=str) + "\n")
    return 0


from notify.cli import register as _register_notify  # noqa: E402 - its own package, argparse only
from view.cli import register as _register_view  # noqa: E402 - its own package, argparse only
from calibrate.command import register as _register_calibrate  # noqa: E402 - its own package, argparse only

_SUBCOMMANDS: list[Callable] = [
    _register_demo,
    _register_view,
    _register_bench,
    _register_synth, _register_replay, _register_enrol, _register_eval, _register_site, _register_router, _register_certs,
    _register_notify,
    _register_calibrate,
    _register_passthrough,
]
