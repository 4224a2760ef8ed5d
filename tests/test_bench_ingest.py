"""`lelsonar bench ingest`'s in-process parts: the profile of a replay and the ingest stage beside its floor."""

from __future__ import annotations

import io

from rich.console import Console

from lelsonar.tools.bench_ingest_replay import ingest_stage_vs_floor, profile_replay, record_scans


def test_profile_of_a_replay_times_the_finals_on_a_scan_it_kept(tmp_path):
    # The service forgets each scan once it is final: the per-method timing must not need one (it crashed
    # with StopIteration when it did).
    path = tmp_path / "replay.mcap"
    samples = record_scans(path, "paper-test1", 1)
    out = io.StringIO()
    profile_replay(path, samples, Console(file=out, width=200))
    text = out.getvalue()
    assert f"cProfile of one replay: {samples} samples, 1 finals" in text
    rows = [line for line in text.splitlines() if "│ main " in line or "│ compare " in line]
    assert len(rows) == 2 and "corner" in rows[0] and "ls" in rows[1]  # ReconstructConfig(): corner, compare ls


def test_the_ingest_stage_and_its_floor_run_on_the_same_payloads():
    floor, stage = ingest_stage_vs_floor("paper-test1", runs=1, n=20)  # raises if the stage refused any payload
    assert floor > 0 and stage > 0


def test_the_decoding_paths_run_on_the_same_payloads_and_place_the_same_scans():
    """The row's two ingest stages (with the fast path, and every payload parsed) accept every payload (it raises
    otherwise) and assemble the same arrays, bit for bit; the plain parse runs beside them."""
    from lelsonar.reconstruct.stream.ingest import Ingest
    from lelsonar.tools.bench_ingest_replay import decoding_paths, ingest_stage_payloads

    times = decoding_paths("paper-test1", runs=1, n=20)
    assert set(times) == {"parse", "fast", "parsed"} and all(t > 0 for t in times.values())
    payloads = ingest_stage_payloads("paper-test1", 20)
    scans = []
    for fast in (True, False):
        ingest = Ingest(fast_path=fast, max_closed=0)
        for name, b in payloads[: len(payloads) // 2]:  # the first scan, still open
            ingest.accept(name, b)
        (scan,) = ingest.scans.values()
        scans.append(scan)
    for name in ("distance", "sensor_energy", "echo_amplitude", "gamma", "ratio", "time_ns", "received"):
        assert getattr(scans[0], name).tobytes() == getattr(scans[1], name).tobytes(), name
