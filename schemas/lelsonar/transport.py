"""Zenoh sessions for every lelsonar process, configured one way.

The embedded default never relies on Zenoh's own defaults (listen on every
interface, multicast scouting to 224.0.0.224): it is a peer with multicast
scouting off that connects to a router on loopback.  A robot runs one router
(``lelsonar router``); services and remote planners connect to it.  A Zenoh
JSON5 file can replace all of it (``--zenoh-config``).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import zenoh

from lelsonar.errors import ConfigError, LelsonarError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
MODES = ("peer", "client", "router")
_SCHEMES = ("tcp/", "udp/", "tls/", "quic/", "unixsock-stream/", "ws/")


class TransportError(LelsonarError):
    """A Zenoh session could not be opened or used."""


@dataclass(frozen=True)
class ZenohSettings:
    """How a process joins the Zenoh network.

    Parameters
    ----------
    mode : {"peer", "client", "router"}
    connect : tuple of str
        Endpoints to connect to, e.g. ``tcp/127.0.0.1:7447`` or ``unixsock-stream/<path>``.
    listen : tuple of str
        Endpoints to listen on.
    config_file : Path, optional
        A Zenoh JSON5 configuration; the fields above override what it says.
    multicast_scouting : bool
        Off by default: discovery by multicast leaks beyond the host.
    overlay : tuple of (str, str)
        (JSON5 path, JSON value) pairs inserted last, over everything else, e.g. the
        mutual-TLS and access-control overlay of :func:`lelsonar.secure.secure_settings`.
    """

    mode: str = "peer"
    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    listen: tuple[str, ...] = ()
    config_file: Path | None = None
    multicast_scouting: bool = False
    overlay: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"Zenoh mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for endpoint in self.connect + self.listen:
            if not endpoint.startswith(_SCHEMES):
                raise ConfigError(
                    f"Zenoh endpoint {endpoint!r} needs a scheme, e.g. tcp/127.0.0.1:7447 or unixsock-stream/PATH"
                )
        if self.mode == "client" and not self.connect:
            raise ConfigError("a Zenoh client needs at least one --connect endpoint (a router)")
        if self.config_file is not None and not Path(self.config_file).is_file():
            raise ConfigError(f"Zenoh config file {self.config_file} does not exist")

    def to_config(self) -> zenoh.Config:
        cfg = zenoh.Config.from_file(str(self.config_file)) if self.config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        for path, value in self.overlay:
            cfg.insert_json5(path, value)
        return cfg


@contextmanager
def open_session(settings: ZenohSettings) -> Iterator[zenoh.Session]:
    """Open a Zenoh session and always close it (callback threads are not daemons)."""
    try:
        session = zenoh.open(settings.to_config())
    except zenoh.ZError as exc:
        hint = ""
        if settings.mode == "client":
            hint = (f"; is a router listening on {', '.join(settings.connect)}? "
                    "Start one with `lelsonar router`, or pass --mode peer")
        if settings.overlay and settings.mode == "client":  # --secure
            hint = (f"; is `lelsonar router --secure DIR` listening on {', '.join(settings.connect)}, with the same "
                    "CA as this process's certificate, and does its certificate name the host you dial?")
        raise TransportError(f"cannot open a Zenoh {settings.mode} session: {exc}{hint}") from None
    try:
        yield session
    finally:
        session.close()


# --- command-line flags, shared by every command that talks Zenoh -------------------
def add_zenoh_arguments(parser: argparse.ArgumentParser, *, default_mode: str = "peer",
                        default_connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)) -> None:
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", choices=MODES, default=default_mode,
                   help=f"Zenoh session mode (default: {default_mode})")
    g.add_argument("--connect", "-e", action="append", metavar="ENDPOINT",
                   help=f"endpoint to connect to; repeatable (default: {', '.join(default_connect) or 'none'})")
    g.add_argument("--listen", "-l", action="append", metavar="ENDPOINT",
                   help="endpoint to listen on; repeatable (default: none)")
    g.add_argument("--zenoh-config", type=Path, metavar="FILE", help="a Zenoh JSON5 config file to start from")
    g.add_argument("--prefix", default=None, metavar="PREFIX",
                   help="key-expression prefix, e.g. robot7/lelsonar (default: lelsonar)")
    parser.set_defaults(_default_connect=tuple(default_connect))


def zenoh_settings_from_args(args: argparse.Namespace) -> ZenohSettings:
    connect = tuple(args.connect) if args.connect else tuple(args._default_connect)
    return ZenohSettings(mode=args.mode, connect=connect, listen=tuple(args.listen or ()),
                         config_file=args.zenoh_config)


def hermetic_settings(socket_path: Path | str, *, listen: bool) -> ZenohSettings:
    """A peer on one unix socket, for tests and single-host pipelines: one side listens, the others connect."""
    endpoint = f"unixsock-stream/{socket_path}"
    if listen:
        return ZenohSettings(mode="peer", connect=(), listen=(endpoint,))
    return ZenohSettings(mode="client", connect=(endpoint,))
