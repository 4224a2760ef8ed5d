"""`lelsonar reconstruct`, `lelsonar review` and `lelsonar planner`."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from contextlib import ExitStack
from pathlib import Path

_log = logging.getLogger("lelsonar.reconstruct")


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.transport import add_zenoh_arguments

    p = sub.add_parser(
        "reconstruct", help="estimate planes live from Zenoh, or from an MCAP recording",
        description="Consume samples incrementally, find the corner, fit both planes and publish the estimates "
                    "on <prefix>/<scanner>/planes (a get there returns the latest).")
    p.add_argument("--source", type=Path, metavar="FILE.mcap",
                   help="replay a recording instead of subscribing to Zenoh")
    p.add_argument("--scanner", default="*", help="only this scanner id (default: all)")
    p.add_argument("--json", action="store_true", help="print final estimates as JSON lines (SI units)")
    p.add_argument("--publish", action="store_true",
                   help="with --source: also publish the estimates on Zenoh (live mode always publishes)")
    p.add_argument("--until-scans", type=int, default=0, metavar="N",
                   help="live: exit after N final estimates (default: run until Ctrl-C)")
    p.add_argument("--record", type=Path, metavar="FILE.mcap", help="record the estimates to an MCAP file")
    p.add_argument("--truth-preset", metavar="PRESET",
                   help="draw the true planes of a simulator preset in Rerun (e.g. paper-test1)")
    _add_estimator_arguments(p)
    _add_rerun_arguments(p)
    _add_foxglove_arguments(p)
    add_zenoh_arguments(p, default_mode="client")
    p.set_defaults(run=run_reconstruct)

    p = sub.add_parser("review", help="reconstruct a recording offline into a Rerun .rrd with the default layout")
    p.add_argument("source", type=Path, metavar="FILE.mcap")
    p.add_argument("-o", "--output", type=Path, metavar="FILE.rrd", help="default: next to the input")
    p.add_argument("--truth-preset", metavar="PRESET",
                   help="draw the true planes of a simulator preset (e.g. paper-test1)")
    _add_estimator_arguments(p)
    p.set_defaults(run=run_review)

    p = sub.add_parser("planner", help="an example remote consumer: print plane estimates as they arrive")
    p.add_argument("--scanner", default="*", help="only this scanner id (default: all)")
    p.add_argument("--json", action="store_true", help="JSON lines instead of tables")
    p.add_argument("--until-final", type=int, default=0, metavar="N",
                   help="exit after N final estimates (default: run until Ctrl-C)")
    p.add_argument("--timeout", type=float, default=0.0, metavar="S",
                   help="give up after S seconds without a final estimate (default: never)")
    add_zenoh_arguments(p, default_mode="client")
    p.set_defaults(run=run_planner)


def _add_estimator_arguments(p: argparse.ArgumentParser) -> None:
    from lelsonar.reconstruct.pipeline import DEFAULT_METHOD, METHODS

    g = p.add_argument_group("estimation")
    g.add_argument("--method", default=DEFAULT_METHOD, choices=sorted(METHODS),
                   help=f"estimator of record (default: {DEFAULT_METHOD})")
    g.add_argument("--compare", default="ls", metavar="M1,M2",
                   help="also run these at the end of each scan, e.g. ls,paper (default: ls; '' for none)")
    g.add_argument("--scan-timeout", type=float, default=10.0, metavar="S",
                   help="finalise a scan after S seconds of silence without ScanEnd (default: 10)")


def _add_rerun_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("rerun")
    g.add_argument("--rrd", type=Path, metavar="FILE.rrd", help="save the Rerun recording to a file")
    g.add_argument("--serve", type=int, metavar="PORT", help="serve the recording over gRPC for a remote viewer")
    g.add_argument("--serve-bind", default="127.0.0.1", metavar="IP",
                   help="address --serve listens on (default: 127.0.0.1; 0.0.0.0 exposes it to the network)")
    g.add_argument("--spawn", action="store_true", help="spawn a local Rerun viewer")


def _add_foxglove_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("foxglove")
    g.add_argument("--foxglove", metavar="[HOST:]PORT",
                   help="serve a live Foxglove WebSocket (e.g. 8765, or 0.0.0.0:8765 for the network; port 0 picks "
                        "one); open examples/foxglove-layout.json in Foxglove and connect to ws://HOST:PORT")
    g.add_argument("--foxglove-wait", type=float, default=0.0, metavar="S",
                   help="with --source: wait up to S s for a Foxglove client to subscribe before replaying, "
                        "then keep serving until Ctrl-C (default: replay at once)")


def _foxglove_observer(args: argparse.Namespace, stack: ExitStack, console):
    if not getattr(args, "foxglove", None):
        return None
    from lelsonar.bridge.foxglove import open_foxglove

    observer = stack.enter_context(open_foxglove(args.foxglove, truth_preset=args.truth_preset))
    console.print(f"reconstruct: Foxglove live on {observer.server.url}", highlight=False)
    return observer


def _config(args: argparse.Namespace, *, provisional: bool = True):
    from lelsonar.reconstruct.service import ReconstructConfig

    compare = tuple(m for m in args.compare.split(",") if m and m != args.method)
    return ReconstructConfig(method=args.method, compare_methods=compare, scan_timeout=args.scan_timeout,
                             provisional=provisional)


def _stop_on_signals() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _rerun_observer(args: argparse.Namespace, stack: ExitStack, application_id: str = "lelsonar"):
    if not (getattr(args, "rrd", None) or getattr(args, "serve", None) or getattr(args, "spawn", False)):
        return None
    from lelsonar.reconstruct.rerun_observer import open_rerun

    return stack.enter_context(open_rerun(rrd=args.rrd, serve_port=args.serve, serve_bind=args.serve_bind, spawn=args.spawn,
                                          application_id=application_id, truth_preset=args.truth_preset,
                                          main_method=args.method))


def run_reconstruct(args: argparse.Namespace) -> int:

    from lelsonar.keys import ScannerKeys
    from lelsonar.reconstruct import present
    from lelsonar.reconstruct.service import ReconstructionService
    from lelsonar.reconstruct.sources import LiveSource, PlanesServer, replay_mcap
    from lelsonar.recording import McapRecorder
    from lelsonar.transport import open_session, zenoh_settings_from_args

    keys = ScannerKeys(args.prefix or "lelsonar", args.scanner)
    # A batch replay needs no provisional estimates: the finals are computed from scratch anyway.
    config = _config(args, provisional=args.source is None or args.publish or bool(args.rrd) or bool(args.foxglove))
    console = present.console(stderr=True)
    finals = threading.Event()
    n_final = 0

    def report(msg) -> None:
        nonlocal n_final
        if present.status_name(msg).startswith("final"):
            n_final += 1
            if args.json:
                print(present.to_json(msg), flush=True)
            else:
                console.print(present.planes_table(msg))
            if args.until_scans and n_final >= args.until_scans:
                finals.set()

    with ExitStack() as stack:
        from lelsonar.reconstruct.observers import combine

        fox = _foxglove_observer(args, stack, console)
        observer = combine(_rerun_observer(args, stack), fox)
        recorder = stack.enter_context(McapRecorder(args.record)) if args.record else None
        publish_to = [report]
        service = ReconstructionService(config, publish=lambda msg: [fn(msg) for fn in publish_to],
                                        observer=observer)
        if args.source is None or args.publish:
            session = stack.enter_context(open_session(zenoh_settings_from_args(args)))
            server = PlanesServer(session, keys, service.latest)  # a get answers from the service's own table
            stack.callback(server.close)
            publish_to.insert(0, server.publish)
            stack.callback(session.liveliness().declare_token(keys.alive("reconstruct")).undeclare)
        if args.source is not None:
            stop = _stop_on_signals() if fox is not None else None
            if fox is not None and args.foxglove_wait > 0:
                from lelsonar.visual import TOPIC_PLANES

                console.print("reconstruct: waiting for a Foxglove client to subscribe", highlight=False)
                fox.server.wait_for_subscribers([TOPIC_PLANES], args.foxglove_wait)
            n = replay_mcap(args.source, service)
            if recorder:
                for msg in service.finals.values():
                    recorder.write(msg)
            _log.info("replayed %d payloads from %s; rejected: %s", n, args.source, dict(service.ingest.rejected))
            if fox is not None and args.foxglove_wait > 0:
                console.print(f"reconstruct: replay done, {len(service.finals)} final estimates; "
                              "serving Foxglove until Ctrl-C", highlight=False)
                stop.wait()
            return 0 if service.finals else 1
        stop = _stop_on_signals()
        console.print(f"reconstruct: listening on {keys.sample} and {keys.scan}; estimates on {keys.planes}")
        with LiveSource(session, keys, service, stop, record=recorder):
            while not stop.is_set() and not finals.is_set():
                stop.wait(0.2)
        console.print(f"reconstruct: {service.stats.finals} final estimates, rejected {dict(service.ingest.rejected)}")
    return 0


def run_review(args: argparse.Namespace) -> int:
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from lelsonar.reconstruct import present
    from lelsonar.reconstruct.rerun_observer import open_rerun
    from lelsonar.reconstruct.service import ReconstructionService
    from lelsonar.reconstruct.sources import replay_mcap
    from lelsonar.recording import iter_payloads

    out = args.output or args.source.with_suffix(".rrd")
    total = sum(1 for _ in iter_payloads(args.source))
    console = present.console(stderr=True)
    with open_rerun(rrd=out, application_id="lelsonar", truth_preset=args.truth_preset,
                    main_method=args.method) as observer, \
            Progress(TextColumn("review"), BarColumn(), TextColumn("{task.completed}/{task.total} messages"),
                     TimeRemainingColumn(), console=console, transient=True) as progress:
        task = progress.add_task("replay", total=total)
        service = ReconstructionService(_config(args), observer=observer)
        replay_mcap(args.source, service, on_payload=lambda _t: progress.advance(task))
    for msg in service.finals.values():
        console.print(present.planes_table(msg))
    console.print(f"wrote {out} — open it with: rerun {out}")
    return 0 if service.finals else 1


def run_planner(args: argparse.Namespace) -> int:
    import zenoh

    from lelsonar import codec
    from lelsonar.errors import LelsonarError
    from lelsonar.keys import ScannerKeys
    from lelsonar.reconstruct import present
    from lelsonar.transport import open_session, zenoh_settings_from_args

    keys = ScannerKeys(args.prefix or "lelsonar", args.scanner)
    console = present.console()
    stop = _stop_on_signals()
    done = threading.Event()
    finals = 0
    lock = threading.Lock()

    def show(payload: bytes, origin: str) -> None:
        nonlocal finals
        try:
            msg = codec.decode(payload, codec.Reconstruction)
        except LelsonarError as exc:
            console.print(f"[yellow]planner: ignored a bad estimate: {exc}", highlight=False)
            return
        with lock:
            if args.json:
                print(present.to_json(msg), flush=True)
            else:
                console.print(present.planes_table(msg, title=None) if present.status_name(msg) != "provisional"
                              else f"{origin}: {msg.scanner_id} scan {msg.scan_id} provisional, "
                                   f"{msg.samples_used} samples, {len(msg.planes)} planes")
            if present.status_name(msg).startswith("final"):
                finals += 1
                if args.until_final and finals >= args.until_final:
                    done.set()

    with open_session(zenoh_settings_from_args(args)) as session:
        sub = session.declare_subscriber(keys.planes, zenoh.handlers.FifoChannel(256))
        token = session.liveliness().declare_token(keys.alive("planner"))

        def drain() -> None:
            try:
                for s in sub:
                    show(s.payload.to_bytes(), "update")
            except zenoh.ZError:
                pass

        worker = threading.Thread(target=drain, daemon=True)
        worker.start()
        for reply in session.get(keys.planes, timeout=2.0):  # the latest, if any, on start
            if reply.ok is not None:
                show(reply.ok.payload.to_bytes(), "latest")
        if args.timeout:
            timer = threading.Timer(args.timeout, stop.set)
            timer.daemon = True
            timer.start()
        while not (stop.is_set() or done.is_set()):
            stop.wait(0.2)
        sub.undeclare()
        token.undeclare()
    if args.until_final and not done.is_set():
        print(f"planner: no final estimate within {args.timeout:.0f} s", file=sys.stderr)
        return 1
    return 0
