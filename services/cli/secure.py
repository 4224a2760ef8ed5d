"""``lelsonar secure``: certificates and Zenoh configurations for mutual TLS and per-role access control."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lelsonar.keys import DEFAULT_PREFIX
from lelsonar.net.secure import (
    DEFAULT_DAYS,
    DEFAULT_HOSTS,
    SecureDir,
    add_scanner,
    init,
    role_config,
    rotate,
    validate_role,
)

_CLI_DESCRIPTION = """\
Mutual TLS with one certificate per role, and Zenoh access control on the router
(deny by default, keyed by the certificate's common name). Three commands make a
deployment secure:

  lelsonar secure init pki --scanner scanner1 --host robot7.local
  lelsonar router --secure pki --listen tls/0.0.0.0:7447
  lelsonar acquire --secure pki --connect tls/robot7.local:7447   (reconstruct, planner, mapper likewise)

Roles: router, reconstruct, planner, mapper, acquire-<scanner id>. Private keys are 0600
and never overwritten but by `lelsonar secure rotate`. Keep ca.key off the robots.
"""


def add_secure_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--secure",
        type=Path,
        metavar="DIR",
        help="join over mutual TLS with this role's certificate from DIR (made by "
        "`lelsonar secure init`); the router enforces the access rules",
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "secure",
        help="certificates and Zenoh configs for mutual TLS and per-role access control",
        description=_CLI_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ss = p.add_subparsers(dest="secure_command", required=True, metavar="ACTION")
    q = ss.add_parser("init", help="create a CA and the certificates of every role")
    q.add_argument("dir", type=Path)
    q.add_argument("--scanner", action="append", required=True, metavar="ID", help="a scanner id; repeatable")
    q.add_argument(
        "--host",
        action="append",
        metavar="NAME_OR_IP",
        help=f"a name or address clients dial the router by; repeatable "
        f"({', '.join(DEFAULT_HOSTS)} are always included)",
    )
    q.add_argument(
        "--days", type=int, default=DEFAULT_DAYS, help=f"validity of the role certificates (default: {DEFAULT_DAYS})"
    )
    q.set_defaults(run=_run_init)
    q = ss.add_parser("add-scanner", help="issue the certificate of another scanner (restart the router after)")
    q.add_argument("dir", type=Path)
    q.add_argument("scanner_id", metavar="ID")
    q.add_argument("--days", type=int, default=DEFAULT_DAYS)
    q.set_defaults(run=_run_add_scanner)
    q = ss.add_parser("rotate", help="replace a role's key and certificate (same CA, same common name)")
    q.add_argument("dir", type=Path)
    q.add_argument("role", help="router, reconstruct, planner, mapper or acquire-<scanner id>")
    q.add_argument(
        "--host",
        action="append",
        metavar="NAME_OR_IP",
        help="router: the names it is dialled by (default: those of the old certificate)",
    )
    q.add_argument("--days", type=int, default=DEFAULT_DAYS)
    q.set_defaults(run=_run_rotate)
    q = ss.add_parser("config", help="print the Zenoh JSON5 config of a role")
    q.add_argument("dir", type=Path)
    q.add_argument("--role", required=True, help="router, reconstruct, planner, mapper or acquire-<scanner id>")
    q.add_argument(
        "--connect", "-e", action="append", metavar="ENDPOINT", help="router endpoint (default: tls/127.0.0.1:7447)"
    )
    q.add_argument(
        "--listen",
        "-l",
        action="append",
        metavar="ENDPOINT",
        help="router role: endpoint to listen on (default: tls/127.0.0.1:7447)",
    )
    q.add_argument("--prefix", default=DEFAULT_PREFIX, help="key-expression prefix (default: lelsonar)")
    q.set_defaults(run=_run_config)


def _run_init(args: argparse.Namespace) -> int:
    created = init(args.dir, args.scanner, hosts=tuple(args.host or ()), days=args.days)
    for path in created:
        print(f"created {path}")
    print(
        f"start the router with: lelsonar router --secure {args.dir} --listen tls/0.0.0.0:7447\n"
        f"keep {SecureDir(args.dir).ca_key} off the robots; copy each role only its own .pem/.key and ca.pem"
    )
    return 0


def _run_add_scanner(args: argparse.Namespace) -> int:
    for path in add_scanner(args.dir, args.scanner_id, days=args.days):
        print(f"created {path}")
    print("restart `lelsonar router --secure` so that its access rules include this scanner")
    return 0


def _run_rotate(args: argparse.Namespace) -> int:
    for path in rotate(args.dir, args.role, hosts=args.host, days=args.days):
        print(f"replaced {path}")
    print(f"copy them to the machine that runs {args.role} and restart it; the access rules are unchanged")
    return 0


def _run_config(args: argparse.Namespace) -> int:
    print(
        json.dumps(
            role_config(
                args.dir,
                validate_role(args.role),
                prefix=args.prefix,
                connect=args.connect or (),
                listen=args.listen or (),
            ),
            indent=2,
        )
    )
    return 0
