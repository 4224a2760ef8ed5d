"""`lelsonar version` and `lelsonar schemas`: what this build speaks."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("version", help="print the package and wire-contract versions")
    p.set_defaults(run=_version)


def _version(args: argparse.Namespace) -> int:
    import lelsonar

    print(f"lelsonar {lelsonar.__version__} (wire contract lelsonar.v1, schema version {lelsonar.SCHEMA_VERSION})")
    return 0
