"""A group member cut off from the router mid-scan (network namespaces the test creates).

The hub namespace holds the router, `acquire` (emulated devices, serving its log), member A and
a watcher of the planes; member B, which owns the scanner, is alone in the other.  The link goes
down mid-scan for longer than the (shortened) Zenoh lease, so each side sees the other's token
go: A adopts B's scan, completes it from the acquirer's log and publishes its final.  When the
link comes back, B (still alive, the same token) completes the scan as well — and the fence
(`GroupMembership.may_publish`) must keep it from publishing a second final: its scan's group
changed while it ran, so it asks A's table of finals first.  Needs root and `ip netns`.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from lelsonar.reconstruct.stream.group import owner

from .test_partition import IP_B, PORT, _drain, _in, _ip, _lelsonar, _why_no_netns, veth_pair

SCANNER = "scanner1"
LEASE_MS = 2000
DOWN_S = 6.0  # three leases: both sides give the other up
WATCHER = f"""
import sys, zenoh
from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
cfg = zenoh.Config()
cfg.insert_json5("mode", '"client"')
cfg.insert_json5("connect/endpoints", '["tcp/{IP_B}:{PORT}"]')
cfg.insert_json5("connect/timeout_ms", "-1")  # until the router is up
cfg.insert_json5("scouting/multicast/enabled", "false")

def on_planes(sample):
    msg = codec.Reconstruction.FromString(sample.payload.to_bytes())
    if wire.is_terminal(msg):
        print("final", msg.scan_id, wire.status_name(msg), len(msg.missing_steps), flush=True)

def on_token(sample):
    if sample.kind == zenoh.SampleKind.PUT:
        print("alive" if "/alive/" in str(sample.key_expr) else "member", flush=True)

with zenoh.open(cfg) as s:
    s.declare_subscriber("lelsonar/*/sample", lambda sample: print("sample", flush=True))
    s.declare_subscriber("lelsonar/*/planes", on_planes)
    # Members' tokens are one per process; "alive" (listening) is one key for all of them.
    s.liveliness().declare_subscriber("lelsonar/_group/g/member/**", on_token, history=True)
    s.liveliness().declare_subscriber("lelsonar/*/alive/reconstruct", on_token, history=True)
    print("ready", flush=True)
    sys.stdin.read()
"""


def _zenoh_config(path: Path, mode: str, **endpoints: list[str]) -> Path:
    # A client waits for the router however long it takes to come up.
    wait = ", timeout_ms: -1" if mode == "client" else ""
    eps = ", ".join(f"{k}: {{ endpoints: {json.dumps(v)}{wait} }}" for k, v in endpoints.items())
    path.write_text(
        f'{{ mode: "{mode}", {eps}, scouting: {{ multicast: {{ enabled: false }} }}, '
        f"transport: {{ link: {{ tx: {{ lease: {LEASE_MS}, keep_alive: 4 }} }} }} }}"
    )
    return path


@pytest.mark.slow
def test_a_member_cut_off_mid_scan_does_not_publish_a_second_final_when_the_link_returns(tmp_path):
    reason = _why_no_netns()
    if reason:
        pytest.skip(f"no network namespaces here: {reason}")
    # B owns the scanner, so the cut takes the scan's owner away from the data.
    a_id, b_id = next((f"a{i}", f"b{i}") for i in range(100) if owner(SCANNER, [f"a{i}", f"b{i}"]) == f"b{i}")
    router_cfg = _zenoh_config(tmp_path / "router.json5", "router", listen=[f"tcp/{IP_B}:{PORT}"])
    client_cfg = _zenoh_config(tmp_path / "client.json5", "client", connect=[f"tcp/{IP_B}:{PORT}"])
    member = (
        "reconstruct",
        "--group",
        "g",
        "--group-settle",
        "0",
        "--json",
        "--compare",
        "",
        "--zenoh-config",
        str(client_cfg),
        "--recovery-attempts",
        "60",
        "--scan-timeout",
        "90",
    )
    procs: list[subprocess.Popen] = []
    with veth_pair() as (ns_a, ns_b, dev_a):
        try:
            router = _lelsonar(
                ns_b, "router", "--zenoh-config", str(router_cfg), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
            )
            procs.append(router)
            watcher = _in(
                ns_b,
                sys.executable,
                "-c",
                WATCHER,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
            )
            procs.append(watcher)
            events = {
                "ready": threading.Event(),
                "up": threading.Event(),
                "mid": threading.Event(),
                "final": threading.Event(),
                "settled": threading.Event(),
            }
            counts = {"sample": 0, "alive": 0, "member": 0}
            finals: list[str] = []

            def on_line(line: str) -> None:
                word = line.split()[0] if line.strip() else ""
                if word == "ready":
                    events["ready"].set()
                elif word in counts:
                    counts[word] += 1
                    if counts["member"] >= 2 and counts["alive"]:
                        events["up"].set()
                    if counts["sample"] >= 40:
                        events["mid"].set()
                elif word == "final":
                    finals.append(line.strip())
                    events["final"].set()
                    if len(finals) > 1:
                        events["settled"].set()  # a second final: the fence failed

            _drain(watcher.stdout, [], on_line)
            assert events["ready"].wait(60), "the watcher never connected"
            out = {"a": [], "b": []}
            err = {"a": [], "b": []}
            a = _lelsonar(ns_b, *member, "--member-id", a_id, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            b = _lelsonar(ns_a, *member, "--member-id", b_id, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            procs += [a, b]
            drains = [_drain(p.stdout, out[k], None) for k, p in (("a", a), ("b", b))] + [
                _drain(a.stderr, err["a"], None),
                _drain(b.stderr, err["b"], lambda line: "fenced: the final" in line and events["settled"].set()),
            ]
            assert events["up"].wait(60), f"members not up: {''.join(err['a'] + err['b'])[-2000:]}"
            acquire = _lelsonar(
                ns_b,
                "acquire",
                "--device",
                "emulated",
                "--scanner-id",
                SCANNER,
                "--out",
                str(tmp_path),
                "--zenoh-config",
                str(client_cfg),
                "--serve-log-for",
                "120",
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
            )
            procs.append(acquire)
            acquire_err: list[str] = []
            drains.append(_drain(acquire.stderr, acquire_err, None))
            assert events["mid"].wait(60), "the scan never got under way"
            assert _ip("-n", ns_a, "link", "set", dev_a, "down").returncode == 0
            # The fault itself is timed: the link stays down for DOWN_S, mid-scan.
            threading.Event().wait(DOWN_S)
            assert events["final"].wait(90), f"A never published the final: {''.join(err['a'])[-3000:]}"
            assert _ip("-n", ns_a, "link", "set", dev_a, "up").returncode == 0
            # B catches up from the log and reaches its own final: the fence must hold it back.
            assert events["settled"].wait(120), f"B never reached its final: {''.join(err['b'])[-3000:]}"
            for p in (a, b):
                p.send_signal(signal.SIGINT)
            for p in (a, b):
                p.wait(timeout=60)
            for t in drains:
                t.join(timeout=30)
            stats_a, stats_b = _stats(err["a"]), _stats(err["b"])
            acquire.send_signal(signal.SIGINT)  # ends --serve-log-for
            assert acquire.wait(timeout=60) == 0, "".join(acquire_err)[-3000:]
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait(timeout=10)
            if watcher.stdin:
                watcher.stdin.close()
    assert len(finals) == 1, finals
    assert finals[0].split()[2] == "final" and finals[0].split()[3] == "0", finals
    assert stats_a["group"].get("scans adopted") == 1, stats_a["group"]
    assert stats_b["finals"] == 1 and stats_b["group"].get("fenced: final another member already published") == 1, (
        stats_b
    )


def _stats(lines: list[str]) -> dict:
    (line,) = [x for x in lines if x.startswith('{"stats"')]
    return json.loads(line)["stats"]
