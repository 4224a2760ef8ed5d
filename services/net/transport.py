"""Zenoh sessions for every lelsonar process, configured one way.

The embedded default never relies on Zenoh's own defaults (listen on every
interface, multicast scouting to 224.0.0.224): it is a peer with multicast
scouting off that connects to a router on loopback.  A robot runs one router
(``lelsonar router``); services and remote planners connect to it.  A Zenoh
JSON5 file can replace all of it (``--zenoh-config``).

Precedence, highest first:

1. flags the user typed (``--mode``, ``--connect``, ``--listen``);
2. the ``--zenoh-config`` file;
3. the command's defaults (e.g. ``--mode client --connect tcp/127.0.0.1:7447``),
   used only when there is no file.

Multicast scouting is off unless the file sets ``scouting/multicast``.  A
message larger than :data:`MAX_MESSAGE_BYTES` (twice the contract's decode
limit) is dropped by Zenoh while it is reassembled, before it reaches a
subscriber's queue, unless the file sets ``max_message_size``: Zenoh's own
default, 1 GiB a message, would let one put grow a process by as much.  In
:class:`ZenohSettings`, ``None`` means "not set": left to the file, or to the
embedded default when there is no file.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import zenoh

from lelsonar import codec
from lelsonar.errors import ConfigError, LelsonarError

_log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: Largest message a session reassembles (``transport/link/rx/max_message_size``): twice the decode limit,
#: so a payload just over the limit still arrives to be refused and counted, and nothing far larger is held.
MAX_MESSAGE_BYTES = 2 * codec.DEFAULT_LIMITS.max_payload_bytes
MODES = ("peer", "client", "router")
_SCHEMES = ("tcp/", "udp/", "tls/", "quic/", "unixsock-stream/", "ws/")


class TransportError(LelsonarError):
    """A Zenoh session could not be opened or used."""


def zenoh_reason(exc: Exception) -> str:
    """Zenoh's message without the Rust source location it ends with (`` at /…/orchestrator.rs:447.``)."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?$", "", str(exc).strip())


@dataclass(frozen=True)
class ZenohSettings:
    """How a process joins the Zenoh network.

    Parameters
    ----------
    mode : {"peer", "client", "router"} or None
    connect : tuple of str, or None
        Endpoints to connect to, e.g. ``tcp/127.0.0.1:7447`` or ``unixsock-stream/<path>``.
    listen : tuple of str, or None
        Endpoints to listen on.
    config_file : Path, optional
        A Zenoh JSON5 configuration; the fields above that are not None override what it says.
    multicast_scouting : bool or None
        None: off, unless the config file sets it (discovery by multicast leaks beyond the host).
    overlay : tuple of (str, str)
        (JSON5 path, JSON value) pairs inserted last, over everything else, e.g. the
        mutual-TLS and access-control overlay of :func:`lelsonar.net.secure.secure_settings`.

    Without a config file, a field left None takes the embedded default: a peer
    connecting to ``tcp/127.0.0.1:7447``, listening nowhere.
    """

    mode: str | None = "peer"
    connect: tuple[str, ...] | None = (DEFAULT_ENDPOINT,)
    listen: tuple[str, ...] | None = ()
    config_file: Path | None = None
    multicast_scouting: bool | None = None
    overlay: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        if self.mode is not None and self.mode not in MODES:
            raise ConfigError(f"Zenoh mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        for endpoint in (self.connect or ()) + (self.listen or ()):
            if not endpoint.startswith(_SCHEMES):
                raise ConfigError(
                    f"Zenoh endpoint {endpoint!r} needs a scheme, e.g. tcp/127.0.0.1:7447 or unixsock-stream/PATH"
                )
        if self.mode == "client" and self.connect is not None and not self.connect:
            raise ConfigError("a Zenoh client needs at least one --connect endpoint (a router)")
        if self.config_file is not None and not Path(self.config_file).is_file():
            raise ConfigError(f"Zenoh config file {self.config_file} does not exist")

    def to_config(self) -> zenoh.Config:
        """The session configuration: the file (or embedded defaults), then the fields that are set."""
        if self.config_file:
            try:
                cfg = zenoh.Config.from_file(str(self.config_file))
            except zenoh.ZError as exc:
                raise ConfigError(f"Zenoh config file {self.config_file} is not valid: {exc}") from None
            defaults: dict = {}
        else:
            cfg = zenoh.Config()
            defaults = {"mode": "peer", "connect": (DEFAULT_ENDPOINT,), "listen": ()}
        mode = self.mode if self.mode is not None else defaults.get("mode")
        connect = self.connect if self.connect is not None else defaults.get("connect")
        listen = self.listen if self.listen is not None else defaults.get("listen")
        if mode is not None:
            cfg.insert_json5("mode", json.dumps(mode))
        if connect is not None:
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen is not None:
            cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if self.multicast_scouting is not None:
            cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        elif not (self.config_file and _file_mentions(Path(self.config_file), "multicast")):
            cfg.insert_json5("scouting/multicast/enabled", "false")
        if not (self.config_file and _file_mentions(Path(self.config_file), "max_message_size")):
            cfg.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
        for path, value in self.overlay:
            cfg.insert_json5(path, value)
        return cfg

    def describe(self) -> str:
        """``mode, endpoints`` as the session will use them (file and flags resolved)."""
        cfg = self.to_config()

        def get(key: str):
            try:
                return json.loads(cfg.get_json(key))
            except (zenoh.ZError, ValueError, TypeError):
                return None

        ends = [*(get("connect/endpoints") or []), *(get("listen/endpoints") or [])]
        flat = [e for x in ends for e in (x if isinstance(x, list) else [x])]
        return f"{get('mode') or '?'}, {', '.join(map(str, flat)) or 'local only'}"


def _file_mentions(path: Path, word: str) -> bool:
    """Whether a JSON5 config file mentions ``word`` (a key: comments ignored)."""
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    text = re.sub(r"(?m)//.*$", "", text)
    return re.search(rf"\b{re.escape(word)}\b", text) is not None


@contextmanager
def open_session(settings: ZenohSettings) -> Iterator[zenoh.Session]:
    """Open a Zenoh session and always close it (callback threads are not daemons)."""
    try:
        session = zenoh.open(settings.to_config())
    except zenoh.ZError as exc:
        hint = ""
        dialled = ", ".join(settings.connect) if settings.connect else "the config file's connect endpoints"
        if settings.mode == "client":
            hint = f"; is a router listening on {dialled}? Start one with `lelsonar router`, or pass --mode peer"
        if settings.overlay and settings.mode == "client":  # --secure
            hint = (
                f"; is `lelsonar router --secure DIR` listening on {dialled}, with the same "
                "CA as this process's certificate, and does its certificate name the host you dial?"
            )
        raise TransportError(f"cannot open a Zenoh {settings.mode} session: {zenoh_reason(exc)}{hint}") from None
    try:
        yield session
    finally:
        try:
            session.close()
        except zenoh.ZError as exc:
            # After a partition the close handshake can time out; everything local is already
            # finished (the recording, the ports), so report it and let the process exit cleanly.
            _log.warning("closing the Zenoh session failed (is the network down?): %s", exc)


# --- command-line flags, shared by every command that talks Zenoh -------------------
def add_zenoh_arguments(
    parser: argparse.ArgumentParser,
    *,
    default_mode: str = "peer",
    default_connect: tuple[str, ...] = (DEFAULT_ENDPOINT,),
) -> None:
    g = parser.add_argument_group(
        "zenoh",
        "Precedence: flags you type, then the --zenoh-config file, then the defaults below (used only without a file).",
    )
    # default=None: a flag the user did not type must not override the config file.
    g.add_argument("--mode", choices=MODES, default=None, help=f"Zenoh session mode (default: {default_mode})")
    g.add_argument(
        "--connect",
        "-e",
        action="append",
        metavar="ENDPOINT",
        default=None,
        help=f"endpoint to connect to; repeatable (default: {', '.join(default_connect) or 'none'})",
    )
    g.add_argument(
        "--listen",
        "-l",
        action="append",
        metavar="ENDPOINT",
        default=None,
        help="endpoint to listen on; repeatable (default: none)",
    )
    g.add_argument(
        "--zenoh-config",
        type=Path,
        metavar="FILE",
        help="a Zenoh JSON5 config file; only the flags you type override it",
    )
    g.add_argument(
        "--prefix",
        default=None,
        metavar="PREFIX",
        help="key-expression prefix, e.g. robot7/lelsonar (default: lelsonar)",
    )
    parser.set_defaults(_default_connect=tuple(default_connect), _default_mode=default_mode)


def zenoh_settings_from_args(args: argparse.Namespace) -> ZenohSettings:
    """Settings from the flags: typed flags always apply; defaults only when there is no config file."""
    file = getattr(args, "zenoh_config", None)
    mode = args.mode if args.mode is not None else (None if file else args._default_mode)
    connect = tuple(args.connect) if args.connect else (None if file else tuple(args._default_connect))
    listen = tuple(args.listen) if args.listen else (None if file else ())
    return ZenohSettings(mode=mode, connect=connect, listen=listen, config_file=file)


def hermetic_settings(socket_path: Path | str, *, listen: bool) -> ZenohSettings:
    """A peer on one unix socket, for tests and single-host pipelines: one side listens, the others connect."""
    endpoint = f"unixsock-stream/{socket_path}"
    if listen:
        return ZenohSettings(mode="peer", connect=(), listen=(endpoint,))
    return ZenohSettings(mode="client", connect=(endpoint,))
