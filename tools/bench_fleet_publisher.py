"""The publishers of ``lelsonar bench fleet``: a pre-encoded payload ring, put on schedule.

The offered load must be met for a run to measure the reconstructor: the scanners are spread over
``--publishers`` processes (:func:`parts`), each putting its share on one schedule common to all of them
(a start time handed over on its stdin), and each reports how far it fell behind it.  A run whose
publishers did not keep their schedule measured them, not the reconstructor (:func:`combine` says so).

A scanner's samples are encoded once, without their header (scanner, scan, step, time): a put joins
a header encoded then to that body, bytes for bytes the payload the acquisition service's
``SerializeToString`` makes (protobuf writes fields in number order, the header's first; checked on
start-up).  Each payload is kept in the scanner's served :class:`~lelsonar.acquire.log_server.ScanLog`
before it is put (recovery after a failover asks for it), and put on the scanner's sample key as the
:class:`~lelsonar.acquire.scan_loop.ScanPublisher` puts it (its encoding, congestion control BLOCK);
the ScanStart and ScanEnd go through :class:`~lelsonar.acquire.scan_loop.ScanOutput` as the acquisition
service emits them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time

#: Scanners one publisher process puts, at most, when ``--publishers`` is left to the bench.
SCANNERS_PER_PUBLISHER = 25
#: A publisher kept its schedule when publishing took at most this share over it.
PUBLISHER_SLACK = 1.05

READY = "FLEET-READY "
RESULT = "FLEET-RESULT "
GO = "GO "


def parts(scanners: int, publishers: int) -> int:
    """Publisher processes for ``scanners`` (``publishers`` ≤ 0: one per :data:`SCANNERS_PER_PUBLISHER`)."""
    if publishers > 0:
        return min(publishers, scanners)
    return max(1, math.ceil(scanners / SCANNERS_PER_PUBLISHER))


def _pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    v = sorted(values)
    return v[min(len(v) - 1, int(round(q / 100 * (len(v) - 1))))]


def publisher_main(args: argparse.Namespace, prefix: str, settings) -> int:
    """One publisher process: scanners ``i`` with ``i % args.parts == args.part`` of ``args.scanners``."""
    import zenoh

    from lelsonar import codec
    from lelsonar.acquire import messages
    from lelsonar.acquire.backends import SimScanner
    from lelsonar.acquire.log_server import LogServer, ScanLog
    from lelsonar.acquire.scan_loop import ScanOutput, ScanPublisher, gamma_schedule
    from lelsonar.keys import ScannerKeys
    from lelsonar.net.transport import open_session
    from lelsonar.sim import preset
    from lelsonar.sim.calibrate import default_energy_model

    sim = preset(args.preset)
    if args.steps:
        sim = dataclasses.replace(sim, steps=args.steps)
    scanner = SimScanner(sim, 0)
    schedule = gamma_schedule(sim.gamma_start, sim.gamma_stop, sim.steps)
    samples = [
        messages.sample("s", 1, step, float(g), scanner.measure(step, float(g)), scanner.info)
        for step, g in enumerate(schedule)
    ]
    version = samples[0].schema_version
    bodies = []
    for s in samples:
        s.schema_version, s.scanner_id, s.scan_id, s.step, s.acquisition_time_ns = 0, "", 0, 0, 0
        bodies.append(s.SerializeToString())
    em = default_energy_model()
    everyone = [f"scanner{i:03d}" for i in range(args.scanners)]
    mine = [(i, sid) for i, sid in enumerate(everyone) if i % args.parts == args.part]
    n, period = len(everyone), 1.0 / args.rate
    sample_encoding = zenoh.Encoding(codec.encoding_name(codec.Sample()))
    lag: list[float] = []
    failures = 0
    blocked = 0.0  # s inside put: congestion control BLOCK holding the publisher back for a slow subscriber
    with open_session(settings) as session:
        outputs, puts, servers = {}, {}, []
        for _, sid in mine:
            keys = ScannerKeys(prefix, sid)
            log = ScanLog(max_scans=2, keep_for=600.0)  # the scan in progress and the one before
            servers.append(LogServer(session, keys, log).__enter__())
            outputs[sid] = ScanOutput(publisher=ScanPublisher(session, keys), scan_log=log)
            puts[sid] = session.declare_publisher(
                keys.sample, encoding=sample_encoding, congestion_control=zenoh.CongestionControl.BLOCK
            )
        # Nothing before the workers' subscriptions are known here (a put before them would be lost).
        probe = session.declare_publisher(ScannerKeys(prefix, mine[-1][1]).sample)
        deadline = time.monotonic() + 60
        # zenoh's stub types matching_status as bool; it is a MatchingStatus.
        while not probe.matching_status.matching and time.monotonic() < deadline:  # type: ignore[attr-defined]
            time.sleep(0.01)
        probe.undeclare()
        print(READY + "{}", flush=True)
        go = sys.stdin.readline()
        if not go.startswith(GO):
            return 1
        start_wall, base = float(go.split()[1]), int(go.split()[2])
        t0 = time.monotonic() + (start_wall - time.time())
        cpu0 = time.process_time()
        tick = 0
        for k in range(args.scans):
            scan_id = base + k
            # One tick per message of a scan (start, samples, end); scanner i at phase i / (n · rate).
            for j in range(len(samples) + 2):
                for i, sid in mine:
                    due = t0 + (tick + i / n) * period
                    delay = due - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    lag.append(max(0.0, time.monotonic() - due))
                    if 0 < j <= len(samples):
                        header = codec.Sample(
                            schema_version=version,
                            scanner_id=sid,
                            scan_id=scan_id,
                            step=j - 1,
                            acquisition_time_ns=time.time_ns(),
                        )
                        payload = header.SerializeToString() + bodies[j - 1]
                        outputs[sid].scan_log.add(header, payload)  # type: ignore[union-attr]  # (set above)
                        p0 = time.monotonic()
                        try:
                            puts[sid].put(payload)
                        except zenoh.ZError:
                            failures += 1
                        blocked += time.monotonic() - p0
                        continue
                    msg: codec.ScanStart | codec.ScanEnd
                    if j == 0:
                        msg = messages.scan_start(sid, scan_id, time.time_ns(), scanner.info, schedule, em)
                    else:
                        msg = messages.scan_end(
                            sid,
                            scan_id,
                            time.time_ns(),
                            complete=True,
                            reason="",
                            steps_planned=len(schedule),
                            samples_sent=len(schedule),
                            echoes_missing=0,
                        )
                    p0 = time.monotonic()
                    outputs[sid].emit(msg)
                    blocked += time.monotonic() - p0
                tick += 1
        wall, cpu = time.monotonic() - t0, time.process_time() - cpu0
        print(
            RESULT
            + json.dumps(
                {
                    "schedule_s": tick * period,
                    "wall_s": wall,
                    "cpu_s": cpu,
                    "blocked_s": blocked,
                    "lag_p50": _pct(lag, 50),
                    "lag_p99": _pct(lag, 99),
                    "lag_max": max(lag),
                    "puts": len(lag),
                    "samples": len(mine) * args.scans * len(samples),
                    "publish_failures": failures + sum(o.publish_failures for o in outputs.values()),
                }
            ),
            flush=True,
        )
        # Keep serving the logs until told to stop (recovery after a failover needs them).
        sys.stdin.read()
        for server in servers:
            server.close()
        for p in puts.values():
            p.undeclare()
        for o in outputs.values():
            if o.publisher is not None:
                o.publisher.close()
    return 0


def check_encoding(preset_name: str) -> None:
    """The ring's payload is the acquisition service's, bytes for bytes (header + body as encoded here)."""
    from lelsonar import codec
    from lelsonar.acquire import messages
    from lelsonar.acquire.backends import SimScanner
    from lelsonar.sim import preset

    scanner = SimScanner(preset(preset_name), 0)
    whole = messages.sample("scanner007", 12, 3, 0.25, scanner.measure(3, 0.25), scanner.info)
    body = codec.Sample()
    body.CopyFrom(whole)
    body.schema_version, body.scanner_id, body.scan_id, body.step, body.acquisition_time_ns = 0, "", 0, 0, 0
    header = codec.Sample(
        schema_version=whole.schema_version,
        scanner_id=whole.scanner_id,
        scan_id=whole.scan_id,
        step=whole.step,
        acquisition_time_ns=whole.acquisition_time_ns,
    )
    if header.SerializeToString() + body.SerializeToString() != whole.SerializeToString():
        raise SystemExit("bench fleet: a header joined to a pre-encoded body is not the sample's payload")


def combine(reports: list[dict | None], processes: int) -> dict | None:
    """The publishers as one: the latest end, the worst lag, the sums of puts and CPU; None if one is missing.

    ``kept_up``: every process published within :data:`PUBLISHER_SLACK` of its schedule.  One that did not
    was either held back inside its puts (``held_back``: congestion control BLOCK waiting for a subscriber
    that does not keep up — the reconstructor's doing, a valid run) or short of CPU itself (``valid``
    False: the run measured the publishers, not the reconstructor)."""
    if not reports or any(r is None for r in reports):
        return None
    rs = [r for r in reports if r is not None]
    out = {
        "processes": processes,
        "schedule_s": max(r["schedule_s"] for r in rs),
        "wall_s": max(r["wall_s"] for r in rs),
        "cpu_s": sum(r["cpu_s"] for r in rs),
        "blocked_s": max(r["blocked_s"] for r in rs),
        "lag_p50": max(r["lag_p50"] for r in rs),
        "lag_p99": max(r["lag_p99"] for r in rs),
        "lag_max": max(r["lag_max"] for r in rs),
        "puts": sum(r["puts"] for r in rs),
        "samples": sum(r["samples"] for r in rs),
        "publish_failures": sum(r["publish_failures"] for r in rs),
    }
    late = [r for r in rs if r["wall_s"] > PUBLISHER_SLACK * r["schedule_s"]]
    out["kept_up"] = not late
    # Behind because its puts waited (at least half the delay spent inside them), or because it ran late.
    out["held_back"] = bool(late) and all(r["blocked_s"] >= 0.5 * (r["wall_s"] - r["schedule_s"]) for r in late)
    out["valid"] = out["kept_up"] or out["held_back"]
    return out
