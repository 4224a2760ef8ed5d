"""`lelsonar reconstruct`: live from Zenoh or replayed from a recording; the flags the commands that
reconstruct share."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

from lelsonar import codec
from lelsonar.cli.values import count, seconds
from lelsonar.errors import InternalError

_log = logging.getLogger("lelsonar.reconstruct")


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.paths import add_overwrite_argument
    from lelsonar.cli.secure import add_secure_argument
    from lelsonar.net.transport import add_zenoh_arguments

    p = sub.add_parser(
        "reconstruct",
        help="estimate planes live from Zenoh, or from an MCAP recording",
        description="Consume samples incrementally, find the corner, fit both planes and publish the estimates "
        "on <prefix>/<scanner>/planes (a get there returns the latest).",
    )
    p.add_argument(
        "--source", type=Path, metavar="FILE.mcap", help="replay a recording instead of subscribing to Zenoh"
    )
    p.add_argument("--scanner", default="*", help="only this scanner id (default: all)")
    p.add_argument(
        "--json",
        action="store_true",
        help="print terminal estimates (final, final_timeout, incomplete) as JSON lines (SI units), "
        'and, on stderr, one line {"stats": {...}} with the service\'s accounting',
    )
    p.add_argument(
        "--publish",
        action="store_true",
        help="with --source: also publish the estimates on Zenoh (live mode always publishes)",
    )
    p.add_argument(
        "--until-scans",
        type=count,
        default=0,
        metavar="N",
        help="live: exit after N final estimates (default: run until Ctrl-C)",
    )
    p.add_argument("--record", type=Path, metavar="FILE.mcap", help="record the estimates to an MCAP file")
    add_truth_preset_argument(p, "draw the true planes of a simulator preset in Rerun and Foxglove")
    add_overwrite_argument(p)
    g = p.add_argument_group(
        "gap recovery (live)",
        "Missing steps are asked from the acquirer's log "
        "(<prefix>/<scanner>/log/<scan_id>); past the attempts a scan asks on, every 4 s, while the "
        "acquirer's liveliness token has not been gone 30 s; a scan still lacking steps then "
        "is published INCOMPLETE with its missing_steps, never FINAL.",
    )
    g.add_argument(
        "--recovery-attempts",
        type=int,
        default=5,
        metavar="N",
        help="requests per scan without progress before giving up, unless the acquirer's log may still "
        "answer (default: 5; 0 disables recovery)",
    )
    g.add_argument(
        "--recovery-interval",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds before the second request for one scan; the wait doubles up to 4 s (default: 1)",
    )
    g.add_argument(
        "--recovery-after",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds of silence before an open scan without ScanEnd asks the log for the rest (default: 1)",
    )
    g = p.add_argument_group(
        "scaling out (live)",
        "Reconstructors with the same --group share the scanners of "
        "their prefix, each scanner processed by one member (rendezvous hashing over the "
        "members' liveliness tokens). A member keeps a scan it started until its final; "
        "a joining member takes its share at the scans that start after it settled; the "
        "scans of a member that dies are completed by the others from the acquirers' logs.",
    )
    g.add_argument("--group", metavar="NAME", help="share the scanners with the other members of group NAME")
    g.add_argument("--member-id", metavar="ID", help="this member's id, unique in the group (default: host-pid-random)")
    g.add_argument(
        "--group-settle",
        type=float,
        default=2.0,
        metavar="S",
        help="a joining member takes part in scans starting S s after it joined; members' clocks must "
        "agree within S (default: 2)",
    )
    add_estimator_arguments(p, scan_timeout=True)
    _add_rerun_arguments(p)
    _add_foxglove_arguments(p)
    add_zenoh_arguments(p, default_mode="client")
    add_secure_argument(p)
    p.set_defaults(run=run_reconstruct)


def add_truth_preset_argument(p, text: str) -> None:
    """``--truth-preset``, checked against the simulator's presets."""
    from lelsonar.sim import preset_names

    names = preset_names()
    p.add_argument("--truth-preset", choices=names, metavar="PRESET", help=f"{text}; one of {', '.join(names)}")


def add_method_arguments(g, compare_help: str) -> None:
    """``--method`` and ``--compare``, for every command that reconstructs (see :func:`compared_methods`)."""
    from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD, METHODS

    g.add_argument(
        "--method",
        default=DEFAULT_METHOD,
        choices=sorted(METHODS),
        help=f"estimator of record (default: {DEFAULT_METHOD})",
    )
    g.add_argument("--compare", default="ls", metavar="M1,M2", help=compare_help)


def add_jobs_argument(g) -> None:
    """``--jobs N``: worker processes for the finals, for every command that replays or listens."""
    g.add_argument(
        "--jobs",
        type=int,
        default=None,
        metavar="N",
        help="worker processes that estimate the finals while the stream goes on (default: live, one per core "
        "beyond the first, at most 2; a replay, as many of those as the load leaves idle, none for a file of "
        "under 50 scans; 0 estimates them in this process)",
    )


def final_workers(args: argparse.Namespace) -> int | None:
    """The ``--jobs`` of a command (None: the default).

    Raises
    ------
    ConfigError
        A negative count.
    """
    from lelsonar.errors import ConfigError

    jobs = getattr(args, "jobs", None)
    if jobs is not None and jobs < 0:
        raise ConfigError(f"--jobs must be >= 0 (0: the finals in this process), not {jobs}")
    return jobs


def compared_methods(args: argparse.Namespace) -> tuple[str, ...]:
    """The ``--compare`` list, without the method of record.

    Raises
    ------
    ConfigError
        A name that is no method.
    """
    from lelsonar.errors import ConfigError
    from lelsonar.reconstruct.estimate.pipeline import METHODS

    names = tuple(m.strip() for m in args.compare.split(",") if m.strip())
    unknown = [m for m in names if m not in METHODS]
    if unknown:
        raise ConfigError(f"--compare: no method {', '.join(unknown)}; methods: {', '.join(sorted(METHODS))}")
    return tuple(m for m in names if m != args.method)


def add_estimator_arguments(p: argparse.ArgumentParser, *, scan_timeout: bool) -> None:
    g = p.add_argument_group("estimation")
    add_method_arguments(g, "also run these at the end of each scan, e.g. ls,paper (default: ls; '' for none)")
    add_jobs_argument(g)
    if not scan_timeout:  # offline, a scan ends with its recording
        return
    g.add_argument(
        "--scan-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="finalise a scan after S seconds of silence without ScanEnd (default: 10)",
    )
    g.add_argument(
        "--provisional-deadline",
        type=float,
        metavar="S",
        help="shed a provisional estimate as stale, not publish it late, when its newest sample waited over S "
        "beyond its scan's quickest (default: 0.04; 0: publish every one, however late)",
    )


def _add_rerun_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("rerun")
    g.add_argument("--rrd", type=Path, metavar="FILE.rrd", help="save the Rerun recording to a file")
    g.add_argument("--serve", type=int, metavar="PORT", help="serve the recording over gRPC for a remote viewer")
    g.add_argument(
        "--serve-bind",
        default="127.0.0.1",
        metavar="IP",
        help="address --serve listens on (default: 127.0.0.1; 0.0.0.0 exposes it to the network)",
    )
    g.add_argument("--spawn", action="store_true", help="spawn a local Rerun viewer")


def _add_foxglove_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("foxglove")
    g.add_argument(
        "--foxglove",
        metavar="[HOST:]PORT",
        help="serve a live Foxglove WebSocket (e.g. 8765, or 0.0.0.0:8765 for the network; port 0 picks "
        "one); open examples/foxglove-layout.json in Foxglove and connect to ws://HOST:PORT",
    )
    g.add_argument(
        "--foxglove-wait",
        type=seconds,
        default=0.0,
        metavar="S",
        help="with --source: wait up to S s for a Foxglove client to subscribe before replaying, "
        "then keep serving until Ctrl-C (default: replay at once)",
    )


def check_outputs(args: argparse.Namespace) -> None:
    """``--record`` and ``--rrd``: new files, or ``--overwrite``; the same file twice is refused."""
    from lelsonar.cli.paths import output_file
    from lelsonar.errors import ConfigError

    outs: list[tuple[str, Path]] = [
        (flag, path)
        for flag, path in (("--record", getattr(args, "record", None)), ("--rrd", getattr(args, "rrd", None)))
        if path is not None
    ]
    for flag, path in outs:
        output_file(path, overwrite=args.overwrite, what=f"{flag} file")
    src = getattr(args, "source", None)
    paths = [Path(p).resolve() for _, p in outs] + ([Path(src).resolve()] if src is not None else [])
    if len(set(paths)) < len(paths):
        raise ConfigError("the input and the output files must differ: " + ", ".join(str(p) for p in paths))


def _foxglove_observer(args: argparse.Namespace, stack: ExitStack, console):
    if not getattr(args, "foxglove", None):
        return None
    from lelsonar.bridge.foxglove import open_foxglove

    observer = stack.enter_context(open_foxglove(args.foxglove, truth_preset=args.truth_preset))
    console.print(f"reconstruct: Foxglove live on {observer.server.url}", highlight=False)
    return observer


def service_config(args: argparse.Namespace, *, provisional: bool = True):
    from lelsonar.reconstruct.stream.config import ReconstructConfig

    compare = compared_methods(args)
    live = {  # the live service's settings that were given
        k: getattr(args, k)
        for k in ("recovery_attempts", "recovery_interval", "recovery_after", "scan_timeout", "provisional_deadline")
        if getattr(args, k, None) is not None
    }
    return ReconstructConfig(
        method=args.method,
        compare_methods=compare,
        provisional=provisional,
        final_workers=final_workers(args),
        **live,
    )


def _group_config(args: argparse.Namespace):
    """The group membership from --group / --member-id / --group-settle (None without --group)."""
    from lelsonar.errors import ConfigError
    from lelsonar.reconstruct.stream.group import GroupConfig

    if not getattr(args, "group", None):
        if getattr(args, "member_id", None):
            raise ConfigError("--member-id needs --group NAME")
        return None
    if args.source is not None:
        raise ConfigError("--group shares live scanners; drop --source (a replay is not shared)")
    extra = {"member_id": args.member_id} if args.member_id else {}
    return GroupConfig(group=args.group, settle=args.group_settle, **extra)


def zenoh_settings(args: argparse.Namespace, role: str, prefix: str):
    """The session settings from the flags, switched to mutual TLS as ``role`` with --secure."""
    from lelsonar.net.transport import zenoh_settings_from_args

    settings = zenoh_settings_from_args(args)
    if getattr(args, "secure", None) is None:
        return settings
    from lelsonar.net.secure import secure_settings

    return secure_settings(settings, args.secure, role, prefix)


def stop_on_signals() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _rerun_observer(args: argparse.Namespace, stack: ExitStack, application_id: str = "lelsonar"):
    if not (getattr(args, "rrd", None) or getattr(args, "serve", None) or getattr(args, "spawn", False)):
        return None
    from lelsonar.view.rerun_observer import open_rerun

    return stack.enter_context(
        open_rerun(
            rrd=args.rrd,
            serve_port=args.serve,
            serve_bind=args.serve_bind,
            spawn=args.spawn,
            application_id=application_id,
            truth_preset=args.truth_preset,
            main_method=args.method,
        )
    )


def open_source(path: Path):
    """The recording to replay, opened tolerantly (its messages are read by the replay, chunk by chunk).

    Raises the typed :class:`~lelsonar.errors.RecordingError` subclasses (one line, exit 2) for a missing path,
    a directory, a pipe, a file that is not MCAP, and one without lelsonar scans.
    """
    from lelsonar.cli.paths import input_file
    from lelsonar.log.recording import open_recording

    return open_recording(input_file(path)).require_scans()


def report_replay(source) -> None:
    """After the replay: one warning line on stderr if the file was damaged or unfinished; an error if no scan
    message was readable after all."""
    source.require_scans()
    if (line := source.damage_warning()) is not None:
        print(line, file=sys.stderr, flush=True)


def run_reconstruct(args: argparse.Namespace) -> int:
    import json

    from lelsonar.keys import ScannerKeys
    from lelsonar.log.recording import McapRecorder
    from lelsonar.net.transport import open_session
    from lelsonar.reconstruct.estimate import wire
    from lelsonar.reconstruct.stream.replay import replay_mcap
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.reconstruct.stream.sources import LiveSource, PlanesServer
    from lelsonar.view import present

    keys = ScannerKeys(args.prefix or "lelsonar", args.scanner)
    check_outputs(args)
    # A batch replay needs no provisional estimates: the finals are computed from scratch anyway.
    provisional = args.source is None or args.publish or bool(args.rrd) or bool(args.foxglove)
    config = service_config(args, provisional=provisional)
    console = present.console(stderr=True)  # what the command says about itself
    tables = present.console()  # the estimates, on stdout
    finals = threading.Event()
    n_final = 0

    def report(msg) -> None:
        nonlocal n_final
        if wire.is_terminal(msg):
            n_final += 1
            if args.json:
                print(present.to_json(msg), flush=True)
            else:
                tables.print(present.planes_table(msg))
                surfaces = present.surfaces_table(msg)
                if surfaces is not None:
                    tables.print(surfaces)
            if args.until_scans and n_final >= args.until_scans:
                finals.set()

    source = open_source(args.source) if args.source is not None else None
    group_config = _group_config(args)
    from lelsonar.cli.warm_up import ensure_compiled, exercise_kernels

    ensure_compiled(console)
    if source is None:
        exercise_kernels()  # before joining anything: the first live scan does not wait for the kernels to load
    with ExitStack() as stack:
        from lelsonar.reconstruct.stream.observers import combine

        fox = _foxglove_observer(args, stack, console)
        observer = combine(_rerun_observer(args, stack), fox)
        recorder = stack.enter_context(McapRecorder(args.record)) if args.record else None
        publish_to: list[Callable[[codec.Reconstruction], None]] = [report]

        def deliver(msg) -> None:
            for fn in publish_to:
                fn(msg)

        session = group = None
        if args.source is None or args.publish:
            session = stack.enter_context(open_session(zenoh_settings(args, "reconstruct", keys.prefix)))
            if group_config is not None and args.source is None:
                from lelsonar.reconstruct.stream.group import GroupMembership

                # Entered before the live source, so it leaves after it: no final once the token is gone.
                group = stack.enter_context(GroupMembership(session, keys.prefix, group_config))
        # In a group, only what passes the fence is published (and a final is marked done for the group).
        service = ReconstructionService(
            config, publish=group.fenced(deliver) if group is not None else deliver, observer=observer
        )
        if session is not None:
            # A get answers from the service's own table (in a group: for the scanners this member owns).
            server = PlanesServer(
                session, keys, service.latest, answers_for=group.answers_for if group is not None else None
            )
            stack.callback(server.close)
            publish_to.insert(0, server.publish)
        if source is not None:
            stop = stop_on_signals() if fox is not None else None
            if fox is not None and args.foxglove_wait > 0:
                from lelsonar.draw.visual import TOPIC_PLANES

                console.print(
                    f"reconstruct: waiting up to {args.foxglove_wait:g} s for a Foxglove client to subscribe "
                    "(Ctrl-C stops)",
                    highlight=False,
                )
                fox.server.wait_for_subscribers([TOPIC_PLANES], args.foxglove_wait, stop=stop)
                if stop is not None and stop.is_set():
                    console.print("reconstruct: interrupted before the replay", highlight=False)
                    return 130
            if session is not None:
                stack.callback(session.liveliness().declare_token(keys.alive("reconstruct")).undeclare)
            n = replay_mcap(source, service)
            report_replay(source)
            if recorder:
                for msg in service.finals.values():
                    recorder.write(msg)
            _log.info("replayed %d payloads from %s; rejected: %s", n, args.source, dict(service.ingest.rejected))
            stats = service.stats_dict()
            _print_stats(console, stats, args.json, json)
            if fox is not None and stop is not None and args.foxglove_wait > 0:
                console.print(
                    f"reconstruct: replay done, {len(service.finals)} final estimates; serving Foxglove until Ctrl-C",
                    highlight=False,
                )
                stop.wait()
            if not service.finals:
                return 1
            # A scan whose method of record produced no plane is a failure a script must see.
            missing = [
                f"{m.scanner_id} scan {m.scan_id} plane {label}"
                for m in service.finals.values()
                for label in ("a", "b")
                if not any(p.label == label and p.method == config.method for p in m.planes)
            ]
            if missing:
                console.print(f"reconstruct: {config.method} produced no plane for {', '.join(missing)}")
                return 1
            return 0
        if session is None:
            raise InternalError("a live reconstruction opens its Zenoh session first")
        stop = stop_on_signals()
        console.print(f"reconstruct: listening on {keys.sample} and {keys.scan}; estimates on {keys.planes}")
        from lelsonar.reconstruct.stream.recovery import RecoveryConfig

        recovery = RecoveryConfig() if config.recovery_attempts > 0 else None
        if group is not None:
            console.print(f"reconstruct: member {group.me} of group {group_config.group}", highlight=False)
        with (
            LiveSource(session, keys, service, stop, record=recorder, recovery=recovery, group=group) as live,
            session.liveliness().declare_token(keys.alive("reconstruct")),
        ):  # alive = listening
            while not stop.is_set() and not finals.is_set():
                stop.wait(0.2)
        stats = service.stats_dict()
        count_open_scans(stats, service)
        if group is not None:
            stats["group"] = group.stats_dict()
        stats["worker_errors"] = dict(live.error_types)
        stats["recovery"].update(live.recovery_stats)
        stats["evicted"].update(server.evicted)
        _print_stats(console, stats, args.json, json)
    return 0


def count_open_scans(stats: dict, service) -> None:
    """Add what the scans still open at exit (stopped by Ctrl-C mid-scan) received: the totals count every
    sample ingested, not only those of the finished scans."""
    open_scans = list(service.ingest.scans.values())
    s = stats["samples"]
    s["received_live"] += sum(scan.n_received - scan.n_recovered for scan in open_scans)
    s["recovered"] += sum(scan.n_recovered for scan in open_scans)
    s["open_scans"] = len(open_scans)


def _print_stats(console, stats: dict, as_json: bool, json) -> None:
    """The service's accounting on exit: a line for people on stderr, and a JSON line with --json."""
    s = stats["samples"]
    console.print(
        f"reconstruct: {stats['finals']} terminal estimates ({stats['incomplete']} incomplete, "
        f"{stats['final_timeouts']} final_timeout); samples: published {s['published']}, live "
        f"{s['received_live']}, recovered {s['recovered']}, duplicates {s['duplicates']}, missing {s['missing']}"
        + (f", in {s['open_scans']} unfinished scans" if s.get("open_scans") else "")
        + (f", energy mismatches {s['energy_mismatches']}" if s.get("energy_mismatches") else "")
        + "; "
        f"rejected {stats['rejected']}; evicted {stats['evicted']}; recovery {stats['recovery']}"
        + (f"; worker errors {stats['worker_errors']}" if stats.get("worker_errors") else "")
        + (f"; group {stats['group']}" if stats.get("group") else ""),
        highlight=False,
    )
    if as_json:  # on stderr: stdout carries only estimates, one per line
        print(json.dumps({"stats": stats}, sort_keys=True, separators=(",", ":")), file=sys.stderr, flush=True)
