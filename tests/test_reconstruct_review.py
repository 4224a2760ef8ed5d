"""`lelsonar review`: a recording reconstructed offline into an .rrd with the layout embedded."""

from __future__ import annotations

import subprocess

from rerun.chunk import RrdReader

from lelsonar.cli.main import main
from lelsonar.log import recording
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD

from .conftest import simulated_messages
from .test_contract_mcap import RERUN


def test_review_writes_an_rrd_with_the_scan_the_estimates_and_the_blueprint(tmp_path):
    mcap, rrd = tmp_path / "scan.mcap", tmp_path / "scan.rrd"
    with recording.McapRecorder(mcap) as rec:
        for m in simulated_messages("paper-test1", seed=4, scanner_id="rig", scan_id=9):
            rec.write(m)
    assert main(["review", str(mcap), "-o", str(rrd), "--truth-preset", "paper-test1"]) == 0
    assert subprocess.run([RERUN, "rrd", "verify", str(rrd)], capture_output=True, timeout=120).returncode == 0

    columns: dict[str, set[str]] = {}
    texts: list[str] = []
    for chunk in RrdReader(rrd).store().stream().to_chunks():
        batch = chunk.to_record_batch()
        columns.setdefault(chunk.entity_path, set()).update(batch.schema.names)
        if "TextLog:text" in batch.schema.names:
            texts += [t for row in batch.column("TextLog:text").to_pylist() if row for t in row]

    def has(path_part: str, archetype: str) -> bool:
        return any(
            path_part in path and any(c.startswith(archetype + ":") for c in cols) for path, cols in columns.items()
        )

    assert has("/world/rig/array", "Transform3D")  # the array pose
    assert has("/world/rig/scans/scan_9/raw", "Points3D")  # raw points (eq. 9)
    assert has("/corrected/a", "Points3D") and has("/corrected/b", "Points3D")
    assert has("/planes/ls/a", "Mesh3D") and has(f"/planes/{DEFAULT_METHOD}/b", "Mesh3D")
    assert has("/truth/a", "Mesh3D")
    assert has("/normal", "Arrows3D") and has("/edge", "LineStrips3D")
    assert has("/plots/energy/rig", "Scalars") and has("/plots/ratio/rig", "Scalars")
    assert has("/plots/waveforms/rig", "LineStrips2D")
    assert has("/plots/errors/", "BarChart")
    assert has("/log/rig", "TextLog")
    # Where every sample went, one line in the scan's log.
    assert "accounting (final): published 184, live 184, recovered 0, duplicates 0, rejected 0, missing 0" in texts
    assert RrdReader(rrd).blueprints(), "the default blueprint is not embedded"
