"""``voxelwatch view``: the command line and the process around :class:`view.server.View`.

:func:`register` adds the subcommand to ``voxelwatch``; :func:`run_view`
opens the zenoh session (retrying while the router is away, like every
voxelwatch process), serves the page until SIGINT/SIGTERM and always closes
the session. Without a token (``[view] token`` or ``token_file`` in the site
file, or ``--token-file``) it refuses to start.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import TextIO

from common.shell import add_zenoh_arguments

log = logging.getLogger("voxelwatch.view")


def register(sub) -> None:
    p = sub.add_parser("view", help="the live web page: plan, people, alarms, events, timeline, cameras",
                       description="Serve the live view of a home: the floor plan with people and their "
                                   "postures, an alarm banner until acknowledged, the event history, a "
                                   "timeline of the day, camera health, and an installer's page per camera. "
                                   "The page asks for the site's [view] token once.")
    p.add_argument("--site", required=True, type=Path, help="the site TOML file")
    p.add_argument("--listen", default=None, metavar="HOST:PORT",
                   help="where the page is served (default: the site's [view] listen, 127.0.0.1:8080)")
    p.add_argument("--token-file", type=Path, default=None,
                   help="a file holding the access token (default: the site's [view] token or token_file)")
    add_zenoh_arguments(p, host="<first reader>", listen=False)
    p.set_defaults(handler=_view)


def _view(args: argparse.Namespace) -> int:
    site, host, port, token = _configure(args)
    return run_view(site, host=host, port=port, token=token, prefix=args.prefix, mode=args.mode,
                    connect=args.connect, tls_cert=args.tls_cert, tls_key=args.tls_key)


def _configure(args: argparse.Namespace):
    """``(site, host, port, token)`` from the arguments and the site file; ValueError on any problem."""
    from common.site import load_site

    site = load_site(args.site)
    listen = args.listen or site.view.listen
    host, port = _host_port(listen)
    token = _token(site, args.token_file)
    return site, host, port, token


def run_view(site, *, host: str, port: int, token: str, prefix: str | None = None, mode: str | None = None,
             connect: list[str] | None = None, tls_cert: Path | None = None, tls_key: Path | None = None,
             stream: TextIO = sys.stdout) -> int:
    """Serve the view of ``site`` on ``host:port`` until SIGINT/SIGTERM; the exit code."""
    from common.shell import serve

    make_config, endpoints = _zenoh_config(site, prefix=prefix, mode=mode, connect=connect, tls_cert=tls_cert,
                                           tls_key=tls_key)

    def work(session, stop: threading.Event) -> int:
        return asyncio.run(_serve(session, site, host=host, port=port, token=token, prefix=prefix,
                                  stop=stop, stream=stream))

    return serve(make_config, who="view", endpoints=endpoints, log=log, work=work)


def _zenoh_config(site, *, prefix: str | None = None, mode: str | None = None, connect: list[str] | None = None,
                  tls_cert: Path | None = None, tls_key: Path | None = None):
    """``(a factory of the view's zenoh configuration, the endpoints it connects to)``, the
    configuration made once: a bad prefix, endpoint or certificate is a ValueError here, before
    any retrying."""
    from common import keys
    from common.transport import site_config

    if prefix is not None:
        try:
            keys.validate_prefix(prefix)
        except ValueError as exc:
            raise ValueError(f"--prefix: {exc}") from None
    tls = site.zenoh.tls
    reader = tls.readers[0] if tls is not None and tls.readers else "reader"
    endpoints = list(connect if connect is not None else site.zenoh.connect)

    def make_config():
        return site_config(site, host=reader, mode=mode, connect=connect, tls_cert=tls_cert, tls_key=tls_key,
                           connect_timeout_ms=1000)

    make_config()
    return make_config, endpoints


async def _serve(session, site, *, host: str, port: int, token: str, prefix: str | None, stop: threading.Event,
                 stream: TextIO) -> int:
    from aiohttp import web

    from view.server import View, make_app

    view = View(session, site, token=token, prefix=prefix)
    # handler_cancellation: a page that goes away ends its stream at once (not at the next write)
    runner = web.AppRunner(make_app(view), handle_signals=False, access_log=None, shutdown_timeout=2.0,
                           handler_cancellation=True)
    await runner.setup()
    try:
        try:
            await web.TCPSite(runner, host, port).start()
        except OSError as exc:
            raise ValueError(f"cannot serve on {host}:{port}: {exc.strerror or exc}") from None
        where = f"[{host}]" if ":" in host else host
        print(f"voxelwatch view: http://{where}:{port}/ (site {site.name}, prefix {view.prefix}; "
              f"the page asks for the view token)", file=stream, flush=True)
        loop = asyncio.get_running_loop()
        done = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, done.set)
        threading.Thread(target=_relay, args=(stop, loop, done), daemon=True).start()
        await done.wait()
    finally:
        await runner.cleanup()
    return 0


def _relay(stop: threading.Event, loop: asyncio.AbstractEventLoop, done: asyncio.Event) -> None:
    """``stop`` (a signal before the loop ran, a lost session) ends the loop's wait."""
    stop.wait()
    try:
        loop.call_soon_threadsafe(done.set)
    except RuntimeError:  # the loop has already ended
        pass


def _host_port(listen: str) -> tuple[str, int]:
    host, sep, port = listen.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--listen: expected HOST:PORT, e.g. 127.0.0.1:8080, got {listen!r}")
    return host.strip("[]"), int(port)


def _token(site, token_file: Path | None) -> str:
    from common.site import SiteError

    if token_file is not None:
        try:
            token = token_file.read_text(encoding="utf-8").strip()
        except OSError as exc:
            raise ValueError(f"--token-file {token_file}: cannot read: {exc.strerror or exc}") from None
        where = f"--token-file {token_file}"
    else:
        token = site.secret(site.view.token, site.view.token_file, "view.token_file")
        where = f"site file {site.source}: [view] token"
    if not token:
        raise SiteError(f"no access token for the view: set [view] token or token_file in the site file "
                        f"{site.source}, or give --token-file")
    if len(token) < 12:
        raise ValueError(f"{where}: the token must be at least 12 characters")
    return token
