"""`lelsonar version`, `lelsonar schemas` and `lelsonar router`: the contract and the network."""

from __future__ import annotations

import argparse
import signal
import threading


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("version", help="print the package and wire-contract versions")
    p.set_defaults(run=run_version)

    p = sub.add_parser("schemas", help="print the wire contract: messages, fields, units and key expressions")
    p.add_argument("--prefix", default="lelsonar", help="key-expression prefix to show (default: lelsonar)")
    p.add_argument("--scanner", default="<scanner_id>", help="scanner id to show in the keys")
    p.set_defaults(run=run_schemas)

    p = sub.add_parser("router", help="run a Zenoh router that services and planners connect to as clients")
    p.add_argument(
        "--listen",
        "-l",
        action="append",
        metavar="ENDPOINT",
        help="endpoint to listen on; repeatable (default: tcp/127.0.0.1:7447)",
    )
    p.add_argument("--zenoh-config", metavar="FILE", help="a Zenoh JSON5 config file to start from")
    p.add_argument(
        "--secure",
        metavar="DIR",
        help="mutual TLS with DIR/router.pem and per-role access control, deny by default "
        "(DIR made by `lelsonar secure init`); tcp/ endpoints become tls/",
    )
    p.add_argument(
        "--prefix", default="lelsonar", help="key-expression prefix the access rules cover (default: lelsonar)"
    )
    p.set_defaults(run=run_router)


def run_version(args: argparse.Namespace) -> int:
    import lelsonar

    print(f"lelsonar {lelsonar.__version__} (wire contract lelsonar.v1, schema version {lelsonar.SCHEMA_VERSION})")
    return 0


def contract_tables(prefix: str = "lelsonar", scanner: str = "<scanner_id>"):
    """The key table and one field table per message, as rich Tables."""
    from rich.table import Table

    from lelsonar import codec
    from lelsonar.log import recording

    keys = Table(title="Zenoh key expressions", title_justify="left")
    for col in ("key expression", "payload (Zenoh encoding schema)", "MCAP topic"):
        keys.add_column(col, overflow="fold")
    base = f"{prefix}/{scanner}"
    keys.add_row(f"{base}/sample", "lelsonar.v1.Sample", recording.TOPICS[codec.Sample])
    keys.add_row(
        f"{base}/scan",
        "lelsonar.v1.ScanStart | ScanEnd",
        f"{recording.TOPICS[codec.ScanStart]}, {recording.TOPICS[codec.ScanEnd]}",
    )
    keys.add_row(f"{base}/planes", "lelsonar.v1.Reconstruction (get → latest)", recording.TOPICS[codec.Reconstruction])
    keys.add_row(f"{base}/alive/<service>", "liveliness token", "—")
    keys.add_row(
        f"{base}/log/<scan_id>?steps=A-B;start=1;end=1",
        "queryable (acquire): the recorded ScanStart | Sample | ScanEnd",
        "—",
    )
    tables = [keys]
    comments = field_comments()
    for cls in codec.MESSAGE_TYPES.values():
        t = Table(title=cls.DESCRIPTOR.full_name, title_justify="left")
        t.add_column("#", justify="right")
        t.add_column("field")
        t.add_column("type")
        t.add_column("unit / meaning", overflow="fold")
        for f in cls.DESCRIPTOR.fields:
            named = f.message_type or f.enum_type
            kind = named.full_name if named else _SCALAR_NAMES.get(f.type, str(f.type))
            t.add_row(
                str(f.number),
                f.name,
                ("repeated " if _is_repeated(f) else "") + str(kind),
                comments.get((cls.DESCRIPTOR.name, f.name), ""),
            )
        tables.append(t)
    return tables


def field_comments() -> dict[tuple[str, str], str]:
    """Trailing ``// comment`` of each field in the shipped .proto files, by (message, field)."""
    import re
    from importlib.resources import files

    comments: dict[tuple[str, str], str] = {}
    field_line = re.compile(r"^\s*(?:repeated\s+|optional\s+)?[\w.]+\s+(\w+)\s*=\s*\d+;\s*//\s*(.*)$")
    for proto in files("lelsonar.v1").iterdir():
        if not proto.name.endswith(".proto"):
            continue
        message = ""
        for line in proto.read_text().splitlines():
            if m := re.match(r"^message\s+(\w+)", line):
                message = m.group(1)
            elif m := field_line.match(line):
                comments[(message, m.group(1))] = m.group(2)
    return comments


def _is_repeated(field) -> bool:
    return bool(getattr(field, "is_repeated", False)) or getattr(field, "label", None) == 3


_SCALAR_NAMES = {
    1: "double",
    2: "float",
    3: "int64",
    4: "uint64",
    5: "int32",
    8: "bool",
    9: "string",
    12: "bytes",
    13: "uint32",
}


def run_schemas(args: argparse.Namespace) -> int:
    from lelsonar.keys import validate_prefix
    from lelsonar.view import present

    validate_prefix(args.prefix)
    console = present.console()
    for table in contract_tables(args.prefix, args.scanner):
        console.print(table)
    console.print("Units: SI (m, rad, s, K, V, Hz); timestamps are Unix-epoch ns. Details: schemas/README.md")
    return 0


def run_router(args: argparse.Namespace) -> int:
    from pathlib import Path

    from lelsonar.net.transport import ZenohSettings, open_session

    file = Path(args.zenoh_config) if args.zenoh_config else None
    # Typed flags override the file; the defaults apply only without a file (see lelsonar.net.transport).
    settings = ZenohSettings(
        mode="router",
        connect=None if file else (),
        listen=tuple(args.listen) if args.listen else (None if file else ("tcp/127.0.0.1:7447",)),
        config_file=file,
    )
    note = ""
    if args.secure:
        from lelsonar.net.secure import ROUTER, SecureDir, secure_settings

        settings = secure_settings(settings, args.secure, ROUTER, args.prefix)
        note = (
            " (mutual TLS; deny by default, allowing reconstruct, planner and "
            f"{', '.join('acquire-' + s for s in SecureDir(Path(args.secure)).scanners())})"
        )
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with open_session(settings):
        print(f"lelsonar router listening ({settings.describe()}){note}; Ctrl-C to stop", flush=True)
        stop.wait()
    return 0
