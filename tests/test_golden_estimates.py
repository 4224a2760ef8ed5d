"""Every estimate of the L-corner benches is the one of record: planes and verdicts against a golden file.

``tests/data/golden_estimates.json`` holds, per plane, the normal, offset, verdict, reasons and standard
errors that ``lelsonar bench estimators`` gave on the scene families (20 seeds) and the stress sweep
(8 seeds).  A change that moves code must leave every one of them as it was; a change that means to
change an estimate regenerates the file (``python tests/test_golden_estimates.py``) and says why.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

GOLDEN = Path(__file__).parent / "data" / "golden_estimates.json"
#: Kernels run without fastmath on one kind of machine: the same inputs give the same floats; this
#: only absorbs a different summation order in a library.
ATOL = 1e-9

FAMILY_KEYS = (
    "family",
    "seed",
    "method",
    "label",
    "observed",
    "normal",
    "offset",
    "quality",
    "quality_reasons",
    "normal_stderr_deg",
    "offset_stderr_cm",
    "crit",
)
STRESS_KEYS = (
    "family",
    "seed",
    "label",
    "quality",
    "reasons",
    "angle_deg",
    "offset_cm",
    "normal_stderr_deg",
    "offset_stderr_cm",
    "verdict",
    "ls_quality",
)


def bench_rows(tmp: Path) -> dict[str, list[dict]]:
    """Run both benches as a user would and keep the golden fields of every plane."""
    runs = {
        "families": ["--families", "all", "--seeds", "20", "--no-anchor", "--timing-repeats", "1"],
        "stress": ["--stress", "all", "--seeds", "8"],
    }
    keys = {"families": FAMILY_KEYS, "stress": STRESS_KEYS}
    out = {}
    for name, flags in runs.items():
        path = tmp / f"{name}.json"
        done = subprocess.run(
            [sys.executable, "-m", "lelsonar", "bench", "estimators", *flags, "--jobs", "2", "--json", str(path)],
            capture_output=True,
            text=True,
            timeout=900,
        )
        assert done.returncode in (0, 1), done.stderr[-2000:]  # 1: a target missed, which the tables report
        out[name] = [{k: row.get(k) for k in keys[name]} for row in json.loads(path.read_text())["rows"]]
    return out


def same(a, b) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return a is not None and b is not None and bool(np.isclose(a, b, rtol=0, atol=ATOL, equal_nan=True))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


@pytest.mark.slow
def test_every_plane_and_verdict_is_the_golden_one(tmp_path):
    golden = json.loads(GOLDEN.read_text())
    now = bench_rows(tmp_path)
    for name in ("families", "stress"):
        assert len(now[name]) == len(golden[name]), name
        differ = [(g, n) for g, n in zip(golden[name], now[name], strict=True) if not all(same(g[k], n[k]) for k in g)]
        assert not differ, f"{len(differ)} {name} planes changed; first: {differ[0]}"


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        rows = bench_rows(Path(tmp))
    commands = {
        "families": "lelsonar bench estimators --families all --seeds 20 --no-anchor",
        "stress": "lelsonar bench estimators --stress all --seeds 8",
    }
    with GOLDEN.open("w") as f:
        f.write(json.dumps({"commands": commands}, separators=(",", ": "))[:-1] + ",\n")
        for i, name in enumerate(("families", "stress")):
            f.write(f'"{name}": [\n' + ",\n".join(json.dumps(r, separators=(",", ":")) for r in rows[name]) + "\n]")
            f.write(",\n" if i == 0 else "\n}\n")
