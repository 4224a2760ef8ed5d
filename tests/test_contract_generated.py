"""The committed protobuf modules are what the .proto files generate today."""

from __future__ import annotations

import filecmp

from lelsonar.tools import gen_protos


def test_generated_code_is_up_to_date(tmp_path):
    gen_protos.generate(tmp_path)
    committed = gen_protos.SCHEMAS / "lelsonar" / "v1"
    protos = gen_protos.proto_files()
    assert protos, "no .proto files found"
    for proto in protos:
        for suffix in ("_pb2.py", "_pb2.pyi"):
            name = proto.stem + suffix
            fresh = tmp_path / "lelsonar" / "v1" / name
            assert fresh.exists(), f"protoc did not produce {name}"
            assert filecmp.cmp(fresh, committed / name, shallow=False), (
                f"{name} is stale: run `python -m lelsonar.tools.gen_protos` and commit the result"
            )


def test_cli_prints_the_contract(capsys):
    from lelsonar.cli.main import main

    assert main(["schemas", "--prefix", "robot7/lelsonar"]) == 0
    out = capsys.readouterr().out
    for needle in (
        "robot7/lelsonar/<scanner_id>/sample",
        "lelsonar.v1.Sample",
        "gamma_measured",
        "rad",
        "lelsonar.v1.Reconstruction",
        "/alive/",
    ):
        assert needle in out
    assert main(["version"]) == 0
    assert "schema version 1" in capsys.readouterr().out
