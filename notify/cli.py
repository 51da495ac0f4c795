"""``voxelwatch notify``: its command line (:func:`register` adds it to the umbrella command)."""

from __future__ import annotations

import argparse
from pathlib import Path

from common.shell import add_zenoh_arguments


def register(sub) -> None:
    """Add the ``notify`` subcommand to the umbrella command's subparsers."""
    p = sub.add_parser("notify", help="deliver alarms to MQTT (Home Assistant), webhooks and e-mail, "
                                      "kept on disk until each is delivered")
    p.add_argument("--site", type=Path, required=True, help="the site TOML file (its [notify] section: channels, kinds)")
    p.add_argument("--outbox", type=Path, default=None,
                   help="the outbox file (default: [notify] outbox, relative to the site file)")
    p.add_argument("--reader", default=None, metavar="NAME",
                   help="the reader certificate to use with [zenoh.tls] (default: the site's first reader)")
    p.add_argument("--status-every", type=float, default=60.0, metavar="SECONDS",
                   help="log a status line per channel this often (default 60)")
    add_zenoh_arguments(p, host="<reader>", prefix=False)
    p.set_defaults(handler=_notify)


def _notify(args: argparse.Namespace) -> int:
    from notify.service import run_forever

    site, make_config, endpoints, channels, outbox = _configure(args)
    return run_forever(site, outbox_path=outbox, make_config=make_config, endpoints=endpoints, channels=channels,
                       status_every_s=args.status_every)


def _configure(args: argparse.Namespace):
    """``(site, a zenoh configuration factory, the endpoints it connects to, the channels, the outbox
    file)`` from the arguments and the site file; ValueError on any problem."""
    from common import keys
    from notify.service import build_channels
    from common.site import load_site
    from common.transport import site_config

    site = load_site(args.site)
    if not args.status_every > 0:
        raise ValueError(f"--status-every must be a positive number of seconds, got {args.status_every}")
    tls = site.zenoh.tls
    reader = args.reader or (tls.readers[0] if tls is not None else "reader")
    keys.validate_chunk(reader, "--reader")
    if tls is not None and reader not in tls.readers:
        raise ValueError(f"--reader {reader}: not one of the site's readers {tls.readers} ([zenoh.tls] readers)")

    def make_config():
        return site_config(site, host=reader, mode=args.mode, listen=args.listen, connect=args.connect,
                           tls_cert=args.tls_cert, tls_key=args.tls_key, connect_timeout_ms=1000)

    make_config()  # a bad endpoint or a missing certificate stops here, with its message
    channels = build_channels(site)
    outbox = args.outbox if args.outbox is not None else site.resolve(site.notify.outbox)
    endpoints = list(args.connect if args.connect is not None else site.zenoh.connect)
    return site, make_config, endpoints, channels, outbox
