"""The one process shell of every voxelwatch process (camera worker, fusion server, live view,
notifier, router): its zenoh and logging flags, its logging, stopping on SIGINT/SIGTERM, and
the zenoh session opened (retried while the router is away) and watched.

Every process takes the same zenoh flags with the same choices
(:func:`add_zenoh_arguments`), logs in the same format (:func:`configure_logging`)
and runs its work inside :func:`serve`::

    args = parser.parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    ...
    return serve(make_config, who="camera cam1", endpoints=connect, log=log,
                 work=lambda session, stop: run(session, settings, stop=stop))

:func:`serve` returns the process's exit code: the work's own, 0 when a signal came before
zenoh could be reached, 1 when the session cannot be opened (a port that cannot be listened
on, a certificate zenoh refuses).
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = [
    "LOG_FORMAT",
    "MODES",
    "Stopped",
    "add_logging_arguments",
    "add_zenoh_arguments",
    "configure_logging",
    "serve",
    "stop_on_signals",
    "stop_if_asked",
    "stopped_raises",
]

MODES = ("peer", "client")
"""Zenoh modes a voxelwatch process may run in (a router is its own command, ``voxelwatch router``)."""

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, host: str, listen: bool = True,
                        prefix: bool = True) -> argparse._ArgumentGroup:
    """The zenoh flags, each overriding the site's ``[zenoh]`` section: ``--prefix``, ``--mode``,
    ``--listen`` (with ``listen``), ``--connect``, ``--tls-cert`` and ``--tls-key``. ``host`` says
    whose certificate is the default (``fusion``, ``<camera id>``, the first reader)."""
    g = parser.add_argument_group("zenoh (default: the site's [zenoh] section)")
    if prefix:
        g.add_argument("--prefix", default=None, help="zenoh key prefix (default from the site: voxelwatch/<site name>)")
    g.add_argument("--mode", choices=MODES, default=None, help="zenoh mode, overrides the site")
    if listen:
        g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                       help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7448 (repeatable), overrides the site")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="zenoh endpoint to connect to, e.g. tcp/10.0.0.2:7447 (repeatable), overrides the site")
    g.add_argument("--tls-cert", type=Path, default=None, metavar="PEM",
                   help=f"this host's certificate (default: {host}.pem in the site's [zenoh.tls] certs folder)")
    g.add_argument("--tls-key", type=Path, default=None, metavar="PEM",
                   help=f"this host's private key (default: {host}-key.pem beside it)")
    return g


def add_logging_arguments(parser: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """``-v/--verbose`` (debug messages) and ``-q/--quiet`` (warnings and errors only), in a
    ``logging`` group the caller may add to."""
    g = parser.add_argument_group("logging")
    g.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    g.add_argument("-q", "--quiet", action="store_true", help="log warnings and errors only")
    return g


def configure_logging(verbose: bool = False, quiet: bool = False) -> None:
    """Log to standard error in the processes' one format: debug with ``verbose``, warnings with
    ``quiet``, else information."""
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format=LOG_FORMAT)


class Stopped(BaseException):
    """SIGINT or SIGTERM while a process was still getting ready (:func:`stopped_raises`)."""

    @property
    def signame(self) -> str:
        """The signal's name (``SIGTERM``), or ``a signal`` when unknown."""
        try:
            return signal.Signals(self.args[0]).name
        except (IndexError, ValueError):
            return "a signal"


_ASKED_BY: list[int] = []
"""The signals :func:`stopped_raises`'s handler took: a stop was asked while the process got ready."""
_ASKED_DEPTH: list[str] = []   # the start-ups (stopped_raises blocks) in progress


def stop_if_asked() -> None:
    """Raise :class:`Stopped` when a signal came while the process got ready, for the end of
    each start-up step: the exception raised at the signal can be swallowed by code it lands in
    (third-party modules import with bare ``except:`` clauses), the request cannot."""
    if _ASKED_BY:
        raise Stopped(_ASKED_BY[-1])


@contextmanager
def stopped_raises(*, who: str, log: logging.Logger | None) -> Iterator[None]:
    """While the block runs, SIGINT and SIGTERM log one line and raise :class:`Stopped` (at the next
    Python instruction): for a process's start-up (loading its modules, building its tables), which
    has no loop to look at a stop event. :func:`serve` inside the block takes the signals over while
    it runs. The previous handlers come back after the block; off the main thread it does nothing.
    ``log=None``: no line from the handler (a process whose logging is not set up yet says it where
    it catches :class:`Stopped`)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum: int, _frame: object) -> None:
        _ASKED_BY.append(signum)
        if log is not None:
            log.info("%s: %s received while starting, stopping", who, signal.Signals(signum).name)
        raise Stopped(signum)

    if not _ASKED_DEPTH:   # a new start-up: what an earlier one was asked is done with
        _ASKED_BY.clear()
    _ASKED_DEPTH.append(who)
    previous = {sig: signal.signal(sig, _raise) for sig in _SIGNALS}
    try:
        yield
    except Stopped:
        raise
    except Exception as exc:
        # a compiled module's initialisation turns the exception raised in it into its own
        # ("ImportError: initialization failed", caused by Stopped): still the stop that was asked
        if _ASKED_BY and _stopped_in(exc):
            raise Stopped(_ASKED_BY[-1]) from exc
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _ASKED_DEPTH.pop()


def _stopped_in(exc: BaseException) -> bool:
    """Whether :class:`Stopped` is among the causes or contexts of ``exc``."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, Stopped):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


@contextmanager
def stop_on_signals(stop: threading.Event | None = None, *, who: str | None = None,
                    log: logging.Logger | None = None) -> Iterator[threading.Event]:
    """An event that SIGINT and SIGTERM set while the block runs (the previous handlers come back
    after it). Off the main thread, where Python takes no signal handlers, the event is only the
    caller's to set."""
    stop = stop if stop is not None else threading.Event()
    if _ASKED_DEPTH and _ASKED_BY:   # asked while getting ready (see stop_if_asked)
        stop.set()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def _on_signal(signum: int, _frame: object) -> None:
        if log is not None and not stop.is_set():
            log.info("%s: %s received, stopping", who or "process", signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, _on_signal) for sig in _SIGNALS}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def serve(make_config: Callable[[], Any], *, who: str, endpoints: list[str], log: logging.Logger,
          work: Callable[[Any, threading.Event], int], stop: threading.Event | None = None) -> int:
    """Open the zenoh session (:func:`common.transport.open_session`: retried with back-off while
    a router in ``endpoints`` is away), watch its links, run ``work(session, stop)`` and close the
    session. SIGINT and SIGTERM set ``stop``. Returns ``work``'s exit code; 0 when stopped before
    zenoh could be reached; 1 when the session cannot be opened (logged, naming ``who``)."""
    from common.transport import TransportError, open_session, watch_links

    with stop_on_signals(stop, who=who, log=log) as stop:
        try:
            session = open_session(make_config, stop, who=who, endpoints=endpoints, log=log)
        except TransportError as exc:
            log.error("%s: cannot open the zenoh session: %s", who, exc)
            return 1
        if session is None:
            log.info("%s: stopped before zenoh could be reached", who)
            return 0
        try:
            watch_links(session, stop, who=who, endpoints=endpoints, log=log)
            return work(session, stop)
        finally:
            stop.set()
            session.close()
