"""`lelsonar planner`: an example remote consumer that prints plane estimates as they arrive."""

from __future__ import annotations

import argparse
import sys
import threading

from lelsonar.cli.reconstruct import stop_on_signals, zenoh_settings


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.secure import add_secure_argument
    from lelsonar.net.transport import add_zenoh_arguments

    p = sub.add_parser("planner", help="an example remote consumer: print plane estimates as they arrive")
    p.add_argument("--scanner", default="*", help="only this scanner id (default: all)")
    p.add_argument("--json", action="store_true", help="JSON lines instead of tables")
    p.add_argument(
        "--until-final",
        type=int,
        default=0,
        metavar="N",
        help="exit after N final estimates (default: run until Ctrl-C)",
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=0.0,
        metavar="S",
        help="give up after S seconds without a final estimate (default: never)",
    )
    add_zenoh_arguments(p, default_mode="client")
    add_secure_argument(p)
    p.set_defaults(run=run_planner)


def run_planner(args: argparse.Namespace) -> int:
    from collections import Counter

    import zenoh

    from lelsonar.errors import LelsonarError
    from lelsonar.keys import ScannerKeys
    from lelsonar.net.transport import open_session
    from lelsonar.reconstruct.estimate import wire
    from lelsonar.view import present

    keys = ScannerKeys(args.prefix or "lelsonar", args.scanner)
    settings = zenoh_settings(args, "planner", keys.prefix)
    console = present.console()
    stop = stop_on_signals()
    done = threading.Event()
    finals = 0
    lock = threading.Lock()

    rejected: Counter[str] = Counter()

    def show(key: str, payload: bytes, origin: str) -> None:
        nonlocal finals
        try:
            msg = wire.decode_estimate(key, payload, keys.prefix)
        except LelsonarError as exc:
            with lock:
                rejected[type(exc).__name__] += 1
            print(
                f"planner: rejected an estimate ({type(exc).__name__}, {rejected[type(exc).__name__]} so far): {exc}",
                file=sys.stderr,
                flush=True,
            )
            return
        with lock:
            if args.json:
                print(present.to_json(msg), flush=True)
            else:
                console.print(
                    present.planes_table(msg, title=None)
                    if wire.status_name(msg) != "provisional"
                    else f"{origin}: {msg.scanner_id} scan {msg.scan_id} provisional, "
                    f"{msg.samples_used} samples, {len(msg.planes)} planes"
                )
                surfaces = present.surfaces_table(msg)
                if surfaces is not None:
                    console.print(surfaces)
            if wire.is_terminal(msg):
                finals += 1
                if args.until_final and finals >= args.until_final:
                    done.set()

    with open_session(settings) as session:
        sub = session.declare_subscriber(keys.planes, zenoh.handlers.FifoChannel(256))
        token = session.liveliness().declare_token(keys.alive("planner"))

        def drain() -> None:
            try:
                for s in sub:
                    show(str(s.key_expr), s.payload.to_bytes(), "update")
            except zenoh.ZError:
                pass

        worker = threading.Thread(target=drain, daemon=True)
        worker.start()
        print(
            f"planner: listening on {keys.planes} ({settings.describe()}); Ctrl-C to stop", file=sys.stderr, flush=True
        )
        for reply in session.get(keys.planes, timeout=2.0):  # the latest, if any, on start
            if reply.ok is not None:
                show(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), "latest")
        if args.timeout:
            timer = threading.Timer(args.timeout, stop.set)
            timer.daemon = True
            timer.start()
        while not (stop.is_set() or done.is_set()):
            stop.wait(0.2)
        sub.undeclare()  # ends the drain loop: its channel closes
        token.undeclare()
        # A daemon thread still inside Zenoh's native recv when the interpreter exits is cancelled
        # mid-unwind and aborts the process ("FATAL: exception not rethrown"): let it finish first.
        worker.join(timeout=5.0)
    if rejected:
        print(f"planner: rejected estimates: {dict(rejected)}", file=sys.stderr)
    if args.until_final and not done.is_set():
        print(f"planner: no final estimate within {args.timeout:.0f} s", file=sys.stderr)
        return 1
    return 0
