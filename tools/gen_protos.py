"""Regenerate the committed protobuf modules: ``python -m lelsonar.tools.gen_protos [OUT_DIR]``.

The generated ``*_pb2.py``/``*_pb2.pyi`` files are committed next to the
``.proto`` files; a test regenerates them into a temp dir and diffs.
"""

from __future__ import annotations

import sys
from pathlib import Path

SCHEMAS = Path(__file__).resolve().parents[1] / "schemas"


def proto_files() -> list[Path]:
    return sorted((SCHEMAS / "lelsonar" / "v1").glob("*.proto"))


def generate(out_dir: Path) -> None:
    """Run the protoc bundled with grpcio-tools (a test extra) into ``out_dir``."""
    from grpc_tools import protoc  # dev dependency, imported only here

    out_dir.mkdir(parents=True, exist_ok=True)
    args = ["protoc", f"-I{SCHEMAS}", f"--python_out={out_dir}", f"--pyi_out={out_dir}"]
    args += [str(p.relative_to(SCHEMAS)) for p in proto_files()]
    if protoc.main(args) != 0:
        raise SystemExit(f"protoc failed: {' '.join(args)}")


if __name__ == "__main__":
    generate(Path(sys.argv[1]) if len(sys.argv) > 1 else SCHEMAS)
