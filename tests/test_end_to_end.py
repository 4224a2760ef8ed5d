"""Separate processes over hermetic Zenoh: acquire → reconstruct → planner, and replay equivalence."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading

import pytest
import zenoh

from lelsonar.net.transport import ZenohSettings, open_session
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
from lelsonar.view import present

from .conftest import assert_matches_the_scene

LELSONAR = [sys.executable, "-m", "lelsonar"]
ENV = {**os.environ, "COLUMNS": "120"}


def start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(LELSONAR + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)


def without_clock(estimate: dict) -> dict:
    return {k: v for k, v in estimate.items() if k not in ("stamp_ns", "timings")}


@pytest.mark.slow
def test_planner_receives_the_final_estimate_and_replay_gives_the_same(tmp_path):
    endpoint = f"unixsock-stream/{tmp_path}/z.sock"
    link = ["--mode", "client", "--connect", endpoint]
    procs = []
    try:
        router = start(["router", "--listen", endpoint])
        procs.append(router)
        assert "listening" in router.stdout.readline()  # the router is up: clients can connect
        with open_session(ZenohSettings(mode="client", connect=(endpoint,))) as watcher:
            seen: set[str] = set()
            both = threading.Event()

            def on_token(sample: zenoh.Sample) -> None:
                seen.add(str(sample.key_expr).rsplit("/", 1)[-1])
                if {"reconstruct", "planner"} <= seen:
                    both.set()

            watcher.liveliness().declare_subscriber("lelsonar/**", on_token, history=True)
            recon = start(["reconstruct", "--json", "--until-scans", "1", *link])
            planner = start(["planner", "--json", "--until-final", "1", "--timeout", "120", *link])
            procs += [recon, planner]
            assert both.wait(60), f"services did not come up: {seen}"
            acquire = start(["acquire", "--device", "sim", "--out", str(tmp_path), "--serve-log-for", "0", *link])
            procs.append(acquire)
            assert acquire.wait(120) == 0, acquire.stderr.read()
            planner_out, planner_err = planner.communicate(timeout=120)
            recon_out, recon_err = recon.communicate(timeout=120)
        assert planner.returncode == 0, planner_err
        assert recon.returncode == 0, recon_err
    finally:
        for p in procs:
            p.kill()
    planner_finals = [
        json.loads(line)
        for line in planner_out.splitlines()
        if line.startswith("{") and json.loads(line)["status"] == "final"
    ]
    live = [json.loads(line) for line in recon_out.splitlines() if line.startswith("{")]
    assert len(planner_finals) == 1 and len(live) == 1
    assert planner_finals[0] == live[0]
    assert live[0]["samples_used"] == 184 and {p["label"] for p in live[0]["planes"]} == {"a", "b"}
    assert len(live[0]["surfaces"]) == 2  # the scene's two walls, as every surface of the sweep
    # What the planner got is the scene the simulated scanner looked at, within the noise model's bounds.
    estimate = present.from_json(live[0])
    assert_matches_the_scene(estimate, DEFAULT_METHOD, "paper-test1")  # acquire's default preset

    replay = subprocess.run(
        LELSONAR + ["reconstruct", "--source", str(tmp_path / "scan.mcap"), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        env=ENV,
    )
    assert replay.returncode == 0, replay.stderr
    (replayed,) = [json.loads(line) for line in replay.stdout.splitlines() if line.startswith("{")]
    assert without_clock(replayed) == without_clock(live[0])
