"""`lelsonar batch`: many recordings, each processed exactly as its own command would, whatever the engine."""

from __future__ import annotations

import json
import os
import signal
import sys
from pathlib import Path

import pytest

from lelsonar.cli.executor import ExecutorConfig, Outcome, run_each, worker_loads
from lelsonar.cli.main import COMMAND_MODULES, main
from lelsonar.log import recording

from .conftest import simulated_messages

#: (file name, preset, seed): two scenes, so a mix-up between files would show.
ARCHIVE = (("a-paper1.mcap", "paper-test1", 1), ("b-paper2.mcap", "paper-test2", 2))


def _write_archive(folder: Path) -> list[Path]:
    folder.mkdir(parents=True)
    paths = []
    for name, preset_name, seed in ARCHIVE:
        path = folder / name
        with recording.McapRecorder(path) as rec:
            for msg in simulated_messages(preset_name, seed, scanner_id=name[0], scan_id=seed):
                rec.write(msg)
        paths.append(path)
    # Not an MCAP file at all: reported and counted, never in the way of the others.
    (folder / "c-corrupt.mcap").write_bytes(b"\x89MCAP0\r\n" + os.urandom(256))
    return paths


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> list[Path]:
    return _write_archive(tmp_path_factory.mktemp("batch") / "archive")


def _reconstruct_alone(path: Path, capsys) -> str:
    capsys.readouterr()
    rc = main(["reconstruct", "--source", str(path), "--json"])
    out = capsys.readouterr().out
    assert rc == 0 and out.strip(), f"reconstruct --source {path} gave {rc}"
    return out


def _index(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "index.jsonl").read_text().splitlines()]


def _batch(archive: list[Path], out: Path, *flags: str) -> int:
    return main(["batch", "reconstruct", str(archive[0].parent / "*.mcap"), "--out", str(out), *flags])


@pytest.mark.slow
def test_batch_reconstruct_is_reconstruct_per_file_and_resumes(archive, tmp_path, capsys):
    out = tmp_path / "pool"
    assert _batch(archive, out, "--workers", "2") == 1  # the corrupt file fails the batch, after the others
    err = capsys.readouterr().err
    assert "c-corrupt.mcap" in err and "Traceback" not in err

    lines = _index(out)
    assert [line["input"] for line in lines] == ["a-paper1.mcap", "b-paper2.mcap", "c-corrupt.mcap"]
    good, bad = lines[:2], lines[2]
    for path, line in zip(archive, good):
        assert line["rc"] == 0 and line["error"] is None
        produced = (out / line["output"]).read_text()
        finals = [json.loads(x) for x in produced.splitlines()]
        alone = [json.loads(x) for x in _reconstruct_alone(path, capsys).splitlines()]
        for d in alone:  # when and how fast this run computed it: not part of a result that must not vary
            del d["stamp_ns"], d["timings"]
        assert finals == alone  # every estimate, plane, σ and verdict, in the command's order
        assert produced == "".join(json.dumps(d, separators=(",", ":"), sort_keys=True) + "\n" for d in alone)
        assert line["scans"] == len(finals) == 1
        assert finals[0]["surfaces"]  # every surface of the sweep, as the command alone gives them
        assert line["statuses"] == {finals[0]["status"]: 1}
        assert sum(line["verdicts"].values()) == len(finals[0]["planes"])
    assert bad["rc"] == 2 and bad["output_hash"] is None and "c-corrupt.mcap" in bad["error"]
    assert not (out / "c-corrupt.jsonl").exists()

    # Resumed: the finished files are not redone (their outputs untouched), the failed one is tried again.
    outputs = [out / "a-paper1.jsonl", out / "b-paper2.jsonl"]
    stamps = {p: p.stat().st_mtime_ns for p in outputs}
    index_bytes = (out / "index.jsonl").read_bytes()
    capsys.readouterr()
    assert _batch(archive, out, "--workers", "2") == 1
    assert "done before" in capsys.readouterr().err
    assert {p: p.stat().st_mtime_ns for p in outputs} == stamps
    assert (out / "index.jsonl").read_bytes() == index_bytes

    # A changed input is redone.
    os.utime(archive[0], ns=(archive[0].stat().st_atime_ns, archive[0].stat().st_mtime_ns + 1))
    assert _batch(archive, out, "--workers", "2") == 1
    assert (out / "a-paper1.jsonl").stat().st_mtime_ns != stamps[out / "a-paper1.jsonl"]
    assert (out / "b-paper2.jsonl").stat().st_mtime_ns == stamps[out / "b-paper2.jsonl"]

    # The same bytes with one worker in this process: nothing depends on the workers.
    inline = tmp_path / "inline"
    assert _batch(archive, inline, "--workers", "1") == 1
    assert (inline / "index.jsonl").read_bytes() == (out / "index.jsonl").read_bytes()
    for line in good:
        assert (inline / line["output"]).read_bytes() == (out / line["output"]).read_bytes()


@pytest.mark.slow
def test_batch_on_a_local_ray_head_gives_the_same_bytes(archive, tmp_path):
    """One Ray test: a local head costs several seconds to start."""
    ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]')")
    if ray.is_initialized():
        ray.shutdown()
    pool, on_ray = tmp_path / "pool", tmp_path / "ray"
    assert _batch(archive, pool, "--workers", "1") == 1
    try:
        rc = _batch(archive, on_ray, "--ray")
    except Exception as exc:  # noqa: BLE001 - a host where Ray cannot start is a skip, with its reason
        pytest.skip(f"a local Ray head cannot start here: {type(exc).__name__}: {exc}")
    assert rc == 1
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # Ray's own handlers do not outlive the batch
    assert (on_ray / "index.jsonl").read_bytes() == (pool / "index.jsonl").read_bytes()
    for line in _index(pool)[:2]:
        assert (on_ray / line["output"]).read_bytes() == (pool / line["output"]).read_bytes()


def test_batch_info_writes_info_json_per_file(archive, tmp_path, capsys):
    out = tmp_path / "info"
    timings = tmp_path / "timings.json"
    assert (
        main(["batch", "info", *map(str, archive), "--out", str(out), "--workers", "1", "--timings", str(timings)]) == 0
    )
    t = json.loads(timings.read_text())
    assert t["engine"] == "inline" and [w["items"] for w in t["per_worker"]] == [len(archive)]
    assert t["per_worker"][0]["worker"].endswith(f":{os.getpid()}")  # in this process
    assert 0 < t["per_worker"][0]["busy"] <= t["wall_s"]
    assert t["cpu_all_s"] >= t["cpu_this_process_s"] > 0
    for path in archive:
        capsys.readouterr()
        assert main(["info", "--json", str(path.resolve())]) == 0
        assert (out / path.name.replace(".mcap", ".json")).read_text() == capsys.readouterr().out
    assert [line["scans"] for line in _index(out)] == [1, 1]


def test_batch_errors_are_one_line(tmp_path, capsys, monkeypatch):
    assert main(["batch", "reconstruct", str(tmp_path / "nothing-*.mcap"), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and err.startswith("lelsonar batch: ")  # the command, not the job
    some = tmp_path / "x.mcap"
    some.write_bytes(b"")
    if "lelsonar.cli.map" not in COMMAND_MODULES:  # batch runs `map` where the command exists
        assert main(["batch", "map", str(some), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert "lelsonar map" in err and err.strip().count("\n") == 0
    monkeypatch.setitem(sys.modules, "ray", None)  # as if the extra were not installed
    assert main(["batch", "info", str(some), "--out", str(tmp_path / "o"), "--ray"]) == 2
    err = capsys.readouterr().err
    assert "pip install -e '.[ray]'" in err and err.strip().count("\n") == 0


def _square_or_fail(x: int) -> int:
    if x == 3:
        raise ValueError("three is not welcome")
    if x == 5:
        os._exit(9)  # a worker that dies, as a crash in native code would
    return x * x


def test_executor_reports_a_failure_and_a_dead_worker_and_runs_the_rest():
    items = [(i,) for i in range(8)]
    got = dict(run_each(_square_or_fail, items, ExecutorConfig(workers=2)))
    assert sorted(got) == list(range(8))
    assert {i: o.value for i, o in got.items() if o.ok} == {i: i * i for i in range(8) if i not in (3, 5)}
    assert got[3].error == "ValueError: three is not welcome"
    assert "died" in got[5].error
    # Each item that ran says in which worker process: never this one.
    ran = [o for i, o in got.items() if i != 5]
    assert all(o.worker and not o.worker.endswith(f":{os.getpid()}") for o in ran)
    assert all(o.seconds >= 0 and o.cpu >= 0 and o.process_cpu >= o.cpu for o in ran)


def test_worker_loads_sum_each_workers_items():
    since = 1000.0
    outcomes = [
        Outcome(value=1, worker="h:1", started=1001.0, seconds=2.0, cpu=1.5, process_cpu=3.0),
        Outcome(value=2, worker="h:2", started=1000.5, seconds=1.0, cpu=0.5, process_cpu=0.6),
        Outcome(error="E: x", worker="h:1", started=1003.0, seconds=0.5, cpu=0.5, process_cpu=3.5),
        Outcome(error="the worker process died"),  # no worker to charge it to
    ]
    one, two = worker_loads(outcomes, since)
    assert (one.worker, one.items, one.busy, one.cpu, one.process_cpu) == ("h:1", 2, 2.5, 2.0, 3.5)
    assert (one.first_start, one.last_end) == (1.0, 3.5)
    assert (two.worker, two.items, two.first_start, two.last_end) == ("h:2", 1, 0.5, 1.5)
