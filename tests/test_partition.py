"""Network partitions between network namespaces the test creates (veth pair, link down mid-scan, up).

`acquire` runs in one namespace, `reconstruct` (and a watcher that tells the test when the scan
is under way) in the other; both listen, and `acquire` connects to them (and reconnects after
the cut), so both are connected before the scan starts.  The link goes down mid-scan for 3 s or 15 s —
longer than Zenoh's 10 s lease, so the session itself is lost and re-established.  Every command runs with its
default flags (what the README promises).  The live final must equal the replay of the
acquirer's MCAP with 0 steps missing, and `acquire` must exit 0 without a traceback.
Needs root and `ip netns` (skipped with the reason otherwise); `tc netem` is not needed.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import pytest

IP_A, IP_B = "10.77.0.1", "10.77.0.2"
PORT = 7447
ENV = {**os.environ, "COLUMNS": "120", "PYTHONUNBUFFERED": "1"}
WATCHER = f"""
import sys, zenoh
cfg = zenoh.Config()
cfg.insert_json5("mode", '"peer"')
cfg.insert_json5("listen/endpoints", '["tcp/{IP_B}:{PORT + 1}"]')
cfg.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(cfg) as s:
    sub = s.declare_subscriber("lelsonar/*/sample", lambda sample: print("sample", flush=True))
    print("ready", flush=True)
    sys.stdin.read()  # until the test closes our stdin
"""


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)


def _why_no_netns() -> str | None:
    if sys.platform != "linux":
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    probe = f"lsprobe{secrets.token_hex(3)}"
    done = _ip("netns", "add", probe)
    if done.returncode != 0:
        return f"`ip netns add` failed: {done.stderr.strip()}"
    _ip("netns", "del", probe)
    return None


@contextmanager
def veth_pair():
    """Two fresh namespaces joined by a veth pair: (ns_a, ns_b, device in a)."""
    tag = secrets.token_hex(3)
    ns_a, ns_b, dev_a, dev_b = f"lsa{tag}", f"lsb{tag}", f"va{tag}", f"vb{tag}"
    try:
        for cmd in (
            ["netns", "add", ns_a],
            ["netns", "add", ns_b],
            ["link", "add", dev_a, "type", "veth", "peer", "name", dev_b],
            ["link", "set", dev_a, "netns", ns_a],
            ["link", "set", dev_b, "netns", ns_b],
            ["-n", ns_a, "addr", "add", f"{IP_A}/24", "dev", dev_a],
            ["-n", ns_b, "addr", "add", f"{IP_B}/24", "dev", dev_b],
            ["-n", ns_a, "link", "set", dev_a, "up"],
            ["-n", ns_b, "link", "set", dev_b, "up"],
            ["-n", ns_a, "link", "set", "lo", "up"],
            ["-n", ns_b, "link", "set", "lo", "up"],
        ):
            done = _ip(*cmd)
            assert done.returncode == 0, f"ip {' '.join(cmd)}: {done.stderr}"
        yield ns_a, ns_b, dev_a
    finally:
        for ns in (ns_a, ns_b):  # deleting a namespace deletes its end of the veth pair
            _ip("netns", "del", ns)


def _in(ns: str, *argv: str, **kw) -> subprocess.Popen:
    return subprocess.Popen(["ip", "netns", "exec", ns, *argv], text=True, env=ENV, **kw)


def _lelsonar(ns: str, *argv: str, **kw) -> subprocess.Popen:
    return _in(ns, sys.executable, "-m", "lelsonar", *argv, **kw)


def _drain(stream, lines: list[str], on_line=None) -> threading.Thread:
    def run() -> None:
        for line in stream:
            lines.append(line)
            if on_line is not None:
                on_line(line)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def _estimate(line: str) -> dict:
    d = json.loads(line)
    return {k: v for k, v in d.items() if k not in ("stamp_ns", "timings", "accounting")}


def partition_mid_scan(tmp_path: Path, down_s: float) -> None:
    reason = _why_no_netns()
    if reason:
        pytest.skip(f"no network namespaces here: {reason}")
    (tmp_path / "acq.json5").write_text(
        f'{{ mode: "peer", listen: {{ endpoints: [] }}, '
        f'connect: {{ endpoints: ["tcp/{IP_B}:{PORT}", "tcp/{IP_B}:{PORT + 1}"] }} }}'
    )
    (tmp_path / "recon.json5").write_text(
        f'{{ mode: "peer", listen: {{ endpoints: ["tcp/{IP_B}:{PORT}"] }}, connect: {{ endpoints: [] }} }}'
    )
    procs: list[subprocess.Popen] = []
    with veth_pair() as (ns_a, ns_b, dev_a):
        try:
            recon = _lelsonar(
                ns_b,
                "reconstruct",
                "--json",
                "--until-scans",
                "1",
                "--zenoh-config",
                str(tmp_path / "recon.json5"),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
            watcher = _in(
                ns_b,
                sys.executable,
                "-c",
                WATCHER,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
            )
            procs += [recon, watcher]
            seen = [0]
            mid_scan, watching, listening = threading.Event(), threading.Event(), threading.Event()

            def count(line: str) -> None:
                if line.startswith("ready"):
                    watching.set()
                    return
                seen[0] += 1
                if seen[0] >= 40:
                    mid_scan.set()

            _drain(watcher.stdout, [], count)
            recon_err: list[str] = []
            recon_lines: list[str] = []
            # Both of reconstruct's pipes are drained by threads (communicate() would close them under one).
            recon_drains = [
                _drain(recon.stderr, recon_err, lambda line: "listening on" in line and listening.set()),
                _drain(recon.stdout, recon_lines),
            ]
            assert watching.wait(60) and listening.wait(60), f"not up: {''.join(recon_err)[-2000:]}"
            acquire = _lelsonar(
                ns_a,
                "acquire",
                "--device",
                "emulated",
                "--out",
                str(tmp_path),
                "--zenoh-config",
                str(tmp_path / "acq.json5"),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
            procs.append(acquire)
            assert mid_scan.wait(60), f"the scan never got under way; reconstruct said: {''.join(recon_err)[-2000:]}"
            assert _ip("-n", ns_a, "link", "set", dev_a, "down").returncode == 0
            # The fault itself is timed: the link stays down for down_s seconds, mid-scan.
            threading.Event().wait(down_s)
            assert _ip("-n", ns_a, "link", "set", dev_a, "up").returncode == 0
            recon.wait(timeout=down_s + 90)
            for t in recon_drains:
                t.join(timeout=30)
            recon_out = "".join(recon_lines)
            assert recon.returncode == 0, "".join(recon_err)[-3000:]
            acquire.send_signal(signal.SIGINT)  # ends --serve-log-for
            acq_out, acq_err = acquire.communicate(timeout=60)
            assert acquire.returncode == 0, acq_err[-3000:]
            assert "Traceback" not in acq_err and "ZError" not in acq_err, acq_err[-3000:]
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait(timeout=10)
    (live,) = [line for line in recon_out.splitlines() if line.startswith("{")]
    got = json.loads(live)
    assert got["status"] == "final" and got.get("missing_steps", []) == [], "".join(recon_err)[-4000:]
    acc = got["accounting"]
    assert acc["published"] == 184 and acc["missing"] == 0
    # Whether Zenoh buffered the samples across the cut or they came back from the log, none is missing.
    assert acc["received_live"] + acc["recovered"] == 184, acc
    replay = subprocess.run(
        [sys.executable, "-m", "lelsonar", "reconstruct", "--source", str(tmp_path / "scan.mcap"), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        env=ENV,
    )
    assert replay.returncode == 0, replay.stderr
    (replayed,) = [line for line in replay.stdout.splitlines() if line.startswith("{")]
    assert _estimate(replayed) == _estimate(live)


def test_a_3_s_partition_mid_scan_loses_nothing(tmp_path):
    partition_mid_scan(tmp_path, 3.0)


@pytest.mark.slow
def test_a_15_s_partition_mid_scan_outlives_the_zenoh_lease_and_loses_nothing(tmp_path):
    partition_mid_scan(tmp_path, 15.0)


@pytest.mark.slow
def test_a_router_killed_mid_scan_and_restarted_6_s_later_loses_nothing(tmp_path):
    """`acquire` (one namespace) and `reconstruct` (the other) are clients of one router; it is killed
    mid-scan and started again 6 s later.  Both sessions drop at once (their liveliness tokens go), and
    come back within their connect retry period.  Default flags everywhere."""
    reason = _why_no_netns()
    if reason:
        pytest.skip(f"no network namespaces here: {reason}")
    router_at = f"tcp/{IP_B}:{PORT}"
    link = ["--mode", "client", "--connect", router_at]
    procs: list[subprocess.Popen] = []
    with veth_pair() as (ns_a, ns_b, _dev_a):
        try:

            def router() -> subprocess.Popen:
                r = _lelsonar(ns_b, "router", "--listen", router_at, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                procs.append(r)
                assert "listening" in r.stdout.readline(), r.stderr.read()[-2000:]
                return r

            first = router()
            recon = _lelsonar(
                ns_b,
                "reconstruct",
                "--json",
                "--until-scans",
                "1",
                *link,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
            watcher = _in(
                ns_b,
                sys.executable,
                "-c",
                WATCHER.replace('"peer"', '"client"')
                .replace("listen/endpoints", "connect/endpoints")
                .replace(f"tcp/{IP_B}:{PORT + 1}", router_at),
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
            )
            procs += [recon, watcher]
            seen = [0]
            mid_scan, watching, listening = threading.Event(), threading.Event(), threading.Event()

            def count(line: str) -> None:
                if line.startswith("ready"):
                    watching.set()
                    return
                seen[0] += 1
                if seen[0] >= 40:
                    mid_scan.set()

            _drain(watcher.stdout, [], count)
            recon_err: list[str] = []
            recon_lines: list[str] = []
            recon_drains = [
                _drain(recon.stderr, recon_err, lambda line: "listening on" in line and listening.set()),
                _drain(recon.stdout, recon_lines),
            ]
            assert watching.wait(60) and listening.wait(60), f"not up: {''.join(recon_err)[-2000:]}"
            acquire = _lelsonar(
                ns_a,
                "acquire",
                "--device",
                "emulated",
                "--out",
                str(tmp_path),
                *link,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
            procs.append(acquire)
            assert mid_scan.wait(60), f"the scan never got under way; reconstruct said: {''.join(recon_err)[-2000:]}"
            first.kill()  # the router dies mid-scan ...
            first.wait(timeout=10)
            threading.Event().wait(6.0)  # (the fault itself is timed)
            router()  # ... and comes back 6 s later
            recon.wait(timeout=150)
            for t in recon_drains:
                t.join(timeout=30)
            assert recon.returncode == 0, "".join(recon_err)[-3000:]
            acq_out, acq_err = acquire.communicate(timeout=150)
            assert acquire.returncode == 0 and "Traceback" not in acq_err, acq_err[-3000:]
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait(timeout=10)
    (live,) = [line for line in "".join(recon_lines).splitlines() if line.startswith("{")]
    got = json.loads(live)
    assert got["status"] == "final" and got.get("missing_steps", []) == [], "".join(recon_err)[-4000:]
    assert got["accounting"]["published"] == 184 and got["accounting"]["missing"] == 0
    replay = subprocess.run(
        [sys.executable, "-m", "lelsonar", "reconstruct", "--source", str(tmp_path / "scan.mcap"), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        env=ENV,
    )
    assert replay.returncode == 0, replay.stderr
    (replayed,) = [line for line in replay.stdout.splitlines() if line.startswith("{")]
    assert _estimate(replayed) == _estimate(live)
