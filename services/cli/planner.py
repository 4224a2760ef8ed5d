"""`lelsonar planner`: an example remote consumer that prints plane estimates as they arrive, or, with
``--map``, gets the mapper's map and prints the route out of it."""

from __future__ import annotations

import argparse
import sys
import threading

from lelsonar.cli.reconstruct import stop_on_signals, zenoh_settings
from lelsonar.cli.values import count, seconds


def register(sub: argparse._SubParsersAction) -> None:
    from lelsonar.cli.secure import add_secure_argument
    from lelsonar.net.transport import add_zenoh_arguments

    p = sub.add_parser("planner", help="an example remote consumer: print plane estimates as they arrive")
    p.add_argument("--scanner", default="*", help="only this scanner id (default: all)")
    p.add_argument("--json", action="store_true", help="JSON lines instead of tables")
    p.add_argument(
        "--until-final",
        type=count,
        default=0,
        metavar="N",
        help="exit after N final estimates (default: run until Ctrl-C)",
    )
    p.add_argument(
        "--timeout",
        type=seconds,
        default=0.0,
        metavar="S",
        help="give up after S seconds without a final estimate (default: never)",
    )
    p.add_argument(
        "--map",
        action="store_true",
        help="get the map on <prefix>/map (the mapper's) instead, print its walls and the route out of it, and exit",
    )
    p.add_argument(
        "--robot-radius", type=float, default=0.15, metavar="M", help="with --map: the route keeps this from walls"
    )
    p.add_argument(
        "--start",
        metavar="X,Y",
        help="with --map: route from here, m in the map's frame (default: the map's latest pose, where the robot is)",
    )
    add_zenoh_arguments(p, default_mode="client")
    add_secure_argument(p)
    p.set_defaults(run=run_planner)


def _start(text: str | None, fused) -> tuple[float, float]:
    from lelsonar.errors import ConfigError

    if text is None:
        if not fused.poses:
            raise ConfigError("the map has no poses: give --start X,Y")
        return fused.poses[-1].x, fused.poses[-1].y
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--start takes X,Y in metres, as 1.5,0.75; got {text!r}") from None
    return x, y


def run_map_planner(args: argparse.Namespace) -> int:
    """``planner --map``: the latest map (a ``get``, or the next one published), its walls and the route out."""
    import queue

    from lelsonar.cli.route_report import print_map, print_route
    from lelsonar.errors import DecodeError
    from lelsonar.map import floorplan
    from lelsonar.map.service import map_key
    from lelsonar.map.wire import decode_map, map_from_message
    from lelsonar.net.transport import open_session
    from lelsonar.view import present

    prefix = args.prefix or "lelsonar"
    key = map_key(prefix)
    plan = floorplan.PlanConfig(robot_radius=args.robot_radius)
    settings = zenoh_settings(args, "planner", prefix)
    console = present.console()
    stop = stop_on_signals()
    got: queue.Queue[bytes] = queue.Queue()
    with open_session(settings) as session:
        sub = session.declare_subscriber(key, lambda sample: got.put(sample.payload.to_bytes()))
        print(f"planner: waiting for the map on {key} ({settings.describe()}); Ctrl-C to stop", file=sys.stderr)
        for reply in session.get(key, timeout=2.0):
            if reply.ok is not None:
                got.put(reply.ok.payload.to_bytes())
        if args.timeout:
            timer = threading.Timer(args.timeout, stop.set)
            timer.daemon = True
            timer.start()
        payload = None
        while payload is None and not stop.is_set():
            try:
                payload = got.get(timeout=0.2)
            except queue.Empty:
                continue
        sub.undeclare()
    if payload is None:
        print(f"planner: no map on {key}" + (f" within {args.timeout:.0f} s" if args.timeout else ""), file=sys.stderr)
        return 1
    try:
        fused = map_from_message(decode_map(payload))
    except DecodeError as exc:
        raise type(exc)(f"the map on {key}: {exc}") from None
    print_map(console, fused, key)
    begin = _start(args.start, fused)
    path = floorplan.route(fused, begin, None, plan)
    print_route(console, fused, begin, path, plan)
    return 0 if path is not None else 1


def run_planner(args: argparse.Namespace) -> int:
    if args.map:
        return run_map_planner(args)
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
