"""A worker of ``lelsonar bench fleet``: one reconstructor of the group, probed, in its own process.

Wired as ``lelsonar reconstruct --group fleet`` wires itself
(:class:`~lelsonar.reconstruct.stream.group.GroupMembership`,
:class:`~lelsonar.reconstruct.stream.sources.LiveSource`,
:class:`~lelsonar.reconstruct.stream.sources.PlanesServer`, the default
:class:`~lelsonar.reconstruct.stream.config.ReconstructConfig`), plus a probe that timestamps each live
sample it processes and times ``handle``, ``tick`` and ``catch_up``; its report goes to
:mod:`lelsonar.tools.bench_fleet` as tagged JSON on stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import threading
import time
from pathlib import Path

from lelsonar.errors import ConfigError
from lelsonar.tools.bench_fleet_publisher import READY, RESULT
from lelsonar.tools.bench_fleet_stages import STALL_MS

__all__ = ["PREFIX", "TIMED_CALLS", "client_settings", "worker_main"]

PREFIX = "lelsonar"
GROUP = "fleet"
_READY, _RESULT = READY, RESULT
#: The service's calls the probe times on the processing thread (CPU, the longest, the stalls).
TIMED_CALLS = ("handle", "tick", "catch_up")


def client_settings(endpoint: str):
    from lelsonar.net.transport import ZenohSettings

    return ZenohSettings(mode="client", connect=(endpoint,))


def service_config(fields: list[str], **given):
    """The workers' :class:`~lelsonar.reconstruct.stream.config.ReconstructConfig`: its defaults, ``given``, and
    each ``FIELD=VALUE`` of ``--service`` (a number or a word, as the field's default is)."""
    from dataclasses import fields as dataclass_fields

    from lelsonar.reconstruct.stream.config import ReconstructConfig

    defaults = {f.name: f.default for f in dataclass_fields(ReconstructConfig)}
    for item in fields:
        name, _, value = item.partition("=")
        default = defaults.get(name)
        if isinstance(default, bool):
            given[name] = value.lower() in ("1", "true", "yes")
        elif isinstance(default, (int, float, str)):
            try:
                given[name] = type(default)(value)
            except ValueError:
                raise ConfigError(f"--service {item}: {name} takes a number ({type(default).__name__})") from None
        else:
            raise ConfigError(f"--service {item}: not a number or word field of ReconstructConfig")
    return ReconstructConfig(**given)


def _thread_cpu() -> dict[int, tuple[str, float]]:
    """CPU (user + system, s) of each thread of this process so far, by native id, with its OS name."""
    out: dict[int, tuple[str, float]] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path("/proc/self/task").glob("*"):
        try:
            fields = (task / "stat").read_text().rpartition(")")[2].split()
            out[int(task.name)] = ((task / "comm").read_text().strip(), (int(fields[11]) + int(fields[12])) / tick)
        except (OSError, ValueError, IndexError):
            continue
    return out


def _by_thread(before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]]) -> dict[str, float]:
    """CPU s between two :func:`_thread_cpu` readings, by thread: Python's by their names, the others (Zenoh's
    runtime) by their OS names without a trailing number."""
    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, float] = {}
    for tid, (comm, cpu) in after.items():
        name = names.get(tid) or comm.rstrip("0123456789-_") or comm
        out[name] = out.get(name, 0.0) + cpu - before.get(tid, (comm, 0.0))[1]
    return {k: round(v, 3) for k, v in sorted(out.items(), key=lambda kv: -kv[1]) if v > 0}


def worker_main(args: argparse.Namespace) -> int:
    import resource

    from lelsonar.cli.warm_up import exercise_kernels
    from lelsonar.keys import ScannerKeys
    from lelsonar.net.transport import open_session
    from lelsonar.reconstruct.estimate import wire
    from lelsonar.reconstruct.stream.group import GroupConfig, GroupMembership
    from lelsonar.reconstruct.stream.ingest import Accepted
    from lelsonar.reconstruct.stream.recovery import RecoveryConfig
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.reconstruct.stream.sources import LiveSource, PlanesServer

    exercise_kernels()  # as `lelsonar reconstruct` does before it listens
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    keys = ScannerKeys(PREFIX, "*")
    processed_ns: list[int] = []
    provisional_ns: list[int] = []
    handled: list[float] = []  # monotonic time of each live sample processed
    forward: list = []

    def publish(msg) -> None:  # behind the group's fence, as `reconstruct --group` publishes
        for fn in forward:
            fn(msg)
        if not wire.is_terminal(msg):
            scan = service.ingest.scans.get((msg.scanner_id, msg.scan_id))
            if scan is not None:
                provisional_ns.append(time.time_ns() - int(scan.time_ns[msg.last_step]))

    last: list = []
    # (monotonic, process CPU of all threads) when the first live sample was handled, and at the latest read.
    busy_cpu: list[tuple[float, float]] = []

    # CPU of the worker's thread inside handle and inside tick (s), and each provisional refit's:
    # (steps the scan held, µs of the call that made it, shared among the refits of that call).
    thread_cpu = dict.fromkeys(TIMED_CALLS, 0.0)
    # The longest call of each (s of thread CPU), and the calls over STALL_MS: no sample is handled meanwhile.
    longest = dict.fromkeys(TIMED_CALLS, 0.0)
    stalls = dict.fromkeys(TIMED_CALLS, 0)
    refits: list[tuple[int, float]] = []

    def timed(name: str, fn):
        def call(*a, **kw):
            c0 = time.thread_time()
            out = fn(*a, **kw)
            spent = time.thread_time() - c0
            thread_cpu[name] += spent
            longest[name] = max(longest[name], spent)
            stalls[name] += spent * 1e3 > STALL_MS
            provisional = [m for m in out if not wire.is_terminal(m)]
            for m in provisional:
                refits.append((int(m.last_step) + 1, spent * 1e6 / len(provisional)))
            return out

        return call

    def probe(service: ReconstructionService) -> None:
        """Timestamp each live sample the service handles (put → processed); time handle and tick."""
        accept, handle = service.ingest.accept, timed("handle", service.handle)
        service.tick = timed("tick", service.tick)  # type: ignore[method-assign]
        # What waited for a backlog, run once it drains: on the processing thread too, not "outside" the service.
        service.catch_up = timed("catch_up", service.catch_up)  # type: ignore[method-assign]

        def probe_accept(type_name, payload, **kw):
            events = accept(type_name, payload, **kw)
            last[:] = events if kw.get("origin", "live") == "live" else []
            return events

        def probe_handle(type_name, payload, **kw):
            last.clear()
            out = handle(type_name, payload, **kw)
            now_ns, now = time.time_ns(), time.monotonic()
            for ev in last:
                if isinstance(ev, Accepted) and ev.kind == "sample":
                    processed_ns.append(now_ns - int(ev.scan.time_ns[ev.step]))
                    handled.append(now)
                    if len(busy_cpu) < 2 or now - busy_cpu[-1][0] >= 0.01:
                        # The process clock sums every thread's time (a syscall): read at most every 10 ms,
                        # so the probe does not weigh on the rate it measures.
                        busy_cpu[min(len(busy_cpu), 1) :] = [(now, time.process_time())]
            return out

        # The probes replace the bound methods of this one instance: the bench's measurement, not a change of it.
        service.ingest.accept, service.handle = probe_accept, probe_handle  # type: ignore[method-assign]

    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    wall0 = time.monotonic()
    with open_session(client_settings(args.endpoint)) as session:
        with GroupMembership(session, PREFIX, GroupConfig(GROUP, args.member, settle=0.5)) as group:
            service = ReconstructionService(
                service_config(args.service, provisional=not args.no_provisional), publish=group.fenced(publish)
            )
            probe(service)
            server = PlanesServer(session, keys, service.latest, answers_for=group.answers_for)
            forward.append(server.publish)
            with LiveSource(session, keys, service, stop, recovery=RecoveryConfig(), group=group) as live:
                token = session.liveliness().declare_token(f"{PREFIX}/{args.member}/alive/bench-worker")
                group.wait_members(args.workers, 60)
                print(_READY + json.dumps({"members": len(group.members)}), flush=True)
                threads0 = _thread_cpu()
                stop.wait()
                threads = _by_thread(threads0, _thread_cpu())
                token.undeclare()
            server.close()
            gstats = group.stats_dict()
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    wall = time.monotonic() - wall0
    print(
        _RESULT
        + json.dumps(
            {
                "member": args.member,
                "processed_ns": processed_ns,
                "provisional_ns": provisional_ns,
                "first": min(handled, default=None),
                "last": max(handled, default=None),
                "samples": len(handled),
                "cpu_s": (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime),
                "wall_s": wall,
                "busy_cpu_s": busy_cpu[-1][1] - busy_cpu[0][1] if len(busy_cpu) == 2 else None,
                "busy_wall_s": busy_cpu[-1][0] - busy_cpu[0][0] if len(busy_cpu) == 2 else None,
                "thread_cpu_s": thread_cpu,
                "longest_call_ms": {k: 1e3 * v for k, v in longest.items()},
                "stalls": stalls,
                "threads_cpu_s": threads,
                "refits": refits,
                "service": {
                    **service.stats_dict(),
                    "recovery": {**service.stats_dict()["recovery"], **live.recovery_stats},
                },
                "group": gstats,
                "errors": dict(live.error_types),
                "doorbell_rings": live.rings,
            }
        ),
        flush=True,
    )
    return 0
