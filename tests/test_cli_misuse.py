"""Every user-facing command, misused: one line on stderr, the documented exit code, never a traceback.

The table covers bad flags, bad values and bad paths (missing, a directory, a named pipe, a folder that
cannot be made, an output that exists) for each command `lelsonar --help` lists; those run in this process
through ``main(argv)``.  Ctrl-C at start-up (a SIGINT raised by the process itself at its first import
after parsing, and one during the parser's own imports), Ctrl-C mid-run (once the command says it runs)
and a closed stdout need a process each: they run side by side.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from lelsonar.cli.main import EXIT_CODES, build_parser, main
from lelsonar.log import recording

from .conftest import simulated_messages

LELSONAR = str(Path(sys.executable).with_name("lelsonar"))
COMMANDS = sorted(next(a for a in build_parser()._actions if a.dest == "command").choices)
NOWHERE = "/proc/lelsonar-misuse/x"  # a folder that cannot be made, even by root
#: Commands that run until Ctrl-C, and exit 0 when it stops them.
SERVICES = {"router", "planner", "emulate", "ros2-bridge"}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A small recording, a directory, a named pipe, a TOML rig and a plain file, in one folder."""
    d = tmp_path_factory.mktemp("misuse")
    scan = d / "scan.mcap"
    with recording.McapRecorder(scan) as rec:
        for m in simulated_messages("paper-test1", seed=1, steps=60):
            rec.write(m)
    fifo = d / "fifo"
    os.mkfifo(fifo)
    (d / "dir").mkdir()
    (d / "text.txt").write_text("not a recording\n")
    (d / "exists.rrd").write_bytes(b"")
    (d / "misspelt.toml").write_text('[reconstuct]\nmethod = "ls"\n')
    (d / "wrong-type.toml").write_text("[planner]\ntimeout = [1, 2]\n")
    (d / "negative.toml").write_text("[planner]\nuntil_final = -1\n")
    return d


#: The command families, each with its own table of misuses.
FAMILIES = {
    "recordings": ("review", "info", "recover", "export", "batch", "map"),
    "live": ("acquire", "reconstruct", "planner", "router", "mapper", "emulate", "ros2-bridge", "demo"),
    "setup": ("simulate", "calibrate", "secure", "schemas", "version", "warm-up", "bench"),
}


def _common_cases(d: Path, commands: tuple[str, ...]) -> list[tuple[str, list[str], str]]:
    """A flag no command has, and --config pointing at nothing useful, for each of ``commands``."""
    scan, fifo, dirp = str(d / "scan.mcap"), str(d / "fifo"), str(d / "dir")
    missing = str(d / "missing.mcap")
    positional = {"review": [scan], "recover": [scan, "-o", str(d / "r.mcap")], "info": [scan]}
    positional |= {"export": [scan, "-o", str(d / "bag")], "secure": ["init", str(d / "pki"), "--scanner", "s1"]}
    positional |= {"bench": ["sim"], "map": ["--source", scan], "mapper": ["--scanner", "s1"]}
    positional |= {"batch": ["info", scan, "--out", str(d / "batch")]}
    cases: list[tuple[str, list[str], str]] = []
    for command in commands:
        extra = positional.get(command, [])
        cases.append((command, [command, *extra, "--no-such-flag"], "unrecognized arguments"))
        if command == "bench":
            continue
        for config, word in (
            (missing, "no config file"),
            (dirp, "directory"),
            (fifo, "not a regular file"),
            (str(d / "misspelt.toml"), "did you mean [reconstruct]"),
        ):
            # `secure` takes --config before its action
            first = command == "secure"
            argv = [command, "--config", config, *extra] if first else [command, *extra, "--config", config]
            cases.append((command, argv, word))
    return cases


def _recordings_cases(d: Path) -> list[tuple[str, list[str], str]]:
    """review, info, recover, export, batch, map: inputs (missing, a directory, a named pipe, not a recording),
    outputs (a directory, an existing file, a folder that cannot be made, the input itself) and values."""
    scan, fifo, dirp, text = str(d / "scan.mcap"), str(d / "fifo"), str(d / "dir"), str(d / "text.txt")
    missing, exists, bag, batch = str(d / "missing.mcap"), str(d / "exists.rrd"), str(d / "bag"), str(d / "batch")
    return [
        ("review", ["review", scan, "--method", "nope"], "invalid choice"),
        ("review", ["review", scan, "--compare", "nope"], "nope"),
        ("review", ["review", missing], "missing.mcap"),
        ("review", ["review", dirp], "directory"),
        ("review", ["review", fifo], "not a regular file"),
        ("review", ["review", text], "text.txt"),
        ("review", ["review", scan, "-o", dirp], "directory"),
        ("review", ["review", scan, "-o", exists], "--overwrite"),
        ("review", ["review", scan, "-o", f"{NOWHERE}.rrd"], "cannot make"),
        ("review", ["review", scan, "-o", scan], "--overwrite"),
        ("review", ["review", scan, "--screenshot", dirp], "directory"),
        ("info", ["info", missing], "missing.mcap"),
        ("info", ["info", fifo], "not a regular file"),
        ("info", ["info", dirp], "directory"),
        ("info", ["info", text], "text.txt"),
        ("info", ["info", scan, missing], "missing.mcap"),
        ("recover", [*["recover", scan, "-o", str(d / "r.mcap")], "--compression", "rar"], "invalid choice"),
        ("recover", ["recover", fifo, "-o", str(d / "r.mcap")], "not a regular file"),
        ("recover", ["recover", missing, "-o", str(d / "r.mcap")], "missing.mcap"),
        ("recover", ["recover", dirp, "-o", str(d / "r.mcap")], "directory"),
        ("recover", ["recover", text, "-o", str(d / "r.mcap")], "text.txt"),
        ("recover", ["recover", scan, "-o", dirp], "directory"),
        ("recover", ["recover", scan, "-o", exists], "--overwrite"),
        ("recover", ["recover", scan, "-o", f"{NOWHERE}.mcap"], "cannot make"),
        ("recover", ["recover", scan, "-o", scan, "--overwrite"], "another name"),
        ("export", ["export", scan, "-o", bag, "--distro", "kinetic"], "invalid choice"),
        ("export", ["export", scan, "-o", bag, "--format", "csv"], "invalid choice"),
        ("export", ["export", scan, "-o", bag, "--fov-deg", "-5"], "field of view"),
        ("export", ["export", scan, "-o", bag, "--jobs", "-1"], "--jobs"),
        ("export", ["export", fifo, "-o", bag], "not a regular file"),
        ("export", ["export", missing, "-o", bag], "missing.mcap"),
        ("export", ["export", text, "-o", bag], "text.txt"),
        ("export", ["export", scan, "-o", dirp], "--overwrite"),
        ("export", ["export", scan, "-o", dirp, "--overwrite"], "not a rosbag2"),
        ("batch", ["batch", "nope", scan, "--out", batch], "invalid choice"),
        ("batch", ["batch", "info", missing, "--out", batch], "names no file"),
        ("batch", ["batch", "info", str(d / "nowhere" / "*.mcap"), "--out", batch], "names no file"),
        ("batch", ["batch", "info", scan, "--out", text], "not a folder"),
        ("batch", ["batch", "info", scan, "--out", NOWHERE], "cannot make"),
        ("batch", ["batch", "info", scan, "--out", batch, "--workers", "0"], "--workers"),
        ("batch", ["batch", "info", scan, "--out", batch, "--workers", "many"], "invalid int"),
        ("batch", ["batch", "info", scan, "--out", batch, "--timings", dirp], "directory"),
        ("batch", ["batch", "reconstruct", scan, "--out", batch, "--compare", "ls,nope"], "nope"),
        ("map", ["map", "--source", missing], "missing.mcap"),
        ("map", ["map", "--source", dirp], "directory"),
        ("map", ["map", "--source", fifo], "not a regular file"),
        ("map", ["map", "--source", text], "text.txt"),
        ("map", ["map", "--source", scan, "--goal", "1"], "--goal"),
        ("map", ["map", "--source", scan, "--robot-radius", "-1"], "robot_radius"),
        ("map", ["map", "--source", scan, "--resolution", "0"], "resolution"),
        ("map", ["map", "--source", scan, "--gate", "-3"], "gate"),
        ("map", ["map", "--source", scan, "--jobs", "-1"], "--jobs"),
        ("map", ["map", "--source", scan, "--scanner", "bad/id"], "scanner id"),
        ("map", ["map", "--source", scan, "--scanner", "s9"], "no scan of scanner s9"),
        ("map", ["map", "--source", scan, "--geojson", dirp], "directory"),
        ("map", ["map", "--source", scan, "--geojson", exists], "--overwrite"),
        ("map", ["map", "--source", scan, "--grid", f"{NOWHERE}.json"], "cannot make"),
        ("map", ["map", "--source", scan, "--rrd", exists], "--overwrite"),
        ("map", ["map", "--source", scan, "--rrd", scan, "--overwrite"], "differ"),
        ("map", ["map", "--source", scan, "--screenshot", str(d / "x.xyz")], ".png"),
        ("map", ["map", "--source", scan, "--ros2-bag", text], "--overwrite"),
    ]


def _live_cases(d: Path) -> list[tuple[str, list[str], str]]:
    """acquire, reconstruct, planner, router, mapper, emulate, ros2-bridge, demo: values, names and the files
    they write, refused before any Zenoh session opens (none is up here)."""
    scan, fifo, dirp, text = str(d / "scan.mcap"), str(d / "fifo"), str(d / "dir"), str(d / "text.txt")
    missing, exists = str(d / "missing.mcap"), str(d / "exists.rrd")
    acquire = ["acquire", "--no-zenoh", "--out", str(d / "a")]
    replay = ["reconstruct", "--source", scan]
    return [
        ("acquire", [*acquire, "--steps", "1"], "steps"),
        ("acquire", ["acquire", "--steps", "many"], "invalid int"),
        ("acquire", ["acquire", "--device", "nope"], "invalid choice"),
        ("acquire", [*acquire, "--seed", "-1"], "--seed"),
        ("acquire", [*acquire, "--scans", "0"], "scans"),
        ("acquire", [*acquire, "--serve-log-for", "-1"], "serve_log_for"),
        ("acquire", ["acquire", "--no-zenoh", "--out", text], "not a folder"),
        ("acquire", ["acquire", "--no-zenoh", "--out", str(d), "--mcap-name", "scan.mcap"], "--overwrite"),
        ("acquire", ["acquire", "--no-zenoh", "--out", NOWHERE], "cannot make"),
        ("reconstruct", [*replay, "--truth-preset", "nope"], "invalid choice"),
        ("reconstruct", [*replay, "--compare", "ls,nope"], "nope"),
        ("reconstruct", [*replay, "--foxglove", "notaport"], "--foxglove"),
        ("reconstruct", [*replay, "--serve", "99999"], "--serve"),
        ("reconstruct", [*replay, "--until-scans", "-1"], "--until-scans"),
        ("reconstruct", [*replay, "--foxglove", "0", "--foxglove-wait", "-5"], "--foxglove-wait"),
        ("reconstruct", [*replay, "--jobs", "-1"], "--jobs"),
        ("reconstruct", [*replay, "--scan-timeout", "-1"], "scan_timeout"),
        ("reconstruct", [*replay, "--provisional-deadline", "-0.1"], "provisional_deadline"),
        ("reconstruct", [*replay, "--provisional-deadline", "nan"], "provisional_deadline"),
        ("reconstruct", ["reconstruct", "--member-id", "x"], "--group"),
        ("reconstruct", ["reconstruct", "--source", missing], "missing.mcap"),
        ("reconstruct", ["reconstruct", "--source", dirp], "directory"),
        ("reconstruct", ["reconstruct", "--source", fifo], "not a regular file"),
        ("reconstruct", ["reconstruct", "--source", text], "text.txt"),
        ("reconstruct", [*replay, "--rrd", dirp], "directory"),
        ("reconstruct", [*replay, "--record", dirp], "directory"),
        ("reconstruct", [*replay, "--record", scan, "--overwrite"], "differ"),
        ("reconstruct", [*replay, "--rrd", exists], "--overwrite"),
        ("reconstruct", [*replay, "--rrd", f"{NOWHERE}.rrd"], "cannot make"),
        ("planner", ["planner", "--timeout", "soon"], "duration"),
        ("planner", ["planner", "--timeout", "-1"], "--timeout"),
        ("planner", ["planner", "--until-final", "-1"], "--until-final"),
        ("planner", ["planner", "--prefix", "bad prefix"], "prefix"),
        ("planner", ["planner", "--config", str(d / "wrong-type.toml")], "timeout"),
        ("planner", ["planner", "--config", str(d / "negative.toml")], "until_final"),
        ("router", ["router", "--listen", "nonsense"], "nonsense"),
        ("mapper", ["mapper", "--scanner", "bad/id"], "scanner id"),
        ("mapper", ["mapper", "--scanner", "s1", "--until-scans", "-1"], "--until-scans"),
        ("mapper", ["mapper", "--scanner", "s1", "--record", exists], "--overwrite"),
        ("mapper", ["mapper", "--scanner", "s1", "--record", dirp], "directory"),
        ("mapper", ["mapper", "--scanner", "s1", "--foxglove", "notaport"], "--foxglove"),
        ("mapper", ["mapper", "--scanner", "s1", "--gate", "-1"], "gate"),
        ("emulate", ["emulate", "--source", "nope"], "invalid choice"),
        ("emulate", ["emulate", "--seed", "-1"], "--seed"),
        ("ros2-bridge", ["ros2-bridge", "--source", scan, "--domain-id", "999"], "DOMAIN"),
        ("ros2-bridge", ["ros2-bridge", "--source", scan, "--until-scans", "-1"], "--until-scans"),
        ("ros2-bridge", ["ros2-bridge", "--source", dirp], "directory"),
        ("ros2-bridge", ["ros2-bridge", "--source", missing], "missing.mcap"),
        ("demo", ["demo", "--preset", "nope"], "invalid choice"),
        ("demo", ["demo", "--device", "serial"], "invalid choice"),
        ("demo", ["demo", "--seed", "-1"], "--seed"),
        ("demo", ["demo", "--out", text], "not a folder"),
        ("demo", ["demo", "--secure", text], "cannot make"),
        ("demo", ["demo", "--world", "nope"], "--world"),
        ("demo", ["demo", "--world", "maze:x"], "FAMILY:SEED"),
        ("demo", ["demo", "--world", text], "TOML"),
        ("demo", ["demo", "--world", "maze", "--robot-radius", "-1"], "robot_radius"),
        ("demo", ["demo", "--world", "maze", "--scan-every", "-1"], "--scan-every"),
    ]


def _setup_cases(d: Path) -> list[tuple[str, list[str], str]]:
    """simulate, calibrate, secure, schemas, version, warm-up, bench: values, names and paths, refused before
    any work (a benchmark's flags before its runs)."""
    scan, dirp, text = str(d / "scan.mcap"), str(d / "dir"), str(d / "text.txt")
    return [
        ("simulate", ["simulate", "--preset", "nope"], "invalid choice"),
        ("simulate", ["simulate", "--family", "nope"], "invalid choice"),
        ("simulate", ["simulate", "--seed", "-1"], "--seed"),
        ("simulate", ["simulate", "--plot", str(d / "x.xyz")], ".png"),
        ("simulate", ["simulate", "--mcap", dirp], "directory"),
        ("simulate", ["simulate", "--mcap", scan], "--overwrite"),
        ("simulate", ["simulate", "--mcap", f"{NOWHERE}.mcap"], "cannot make"),
        ("calibrate", ["calibrate", "--distances", "far"], "invalid float"),
        ("calibrate", ["calibrate", "--distances", "-1"], "positive"),
        ("calibrate", ["calibrate", "--seed", "-1"], "--seed"),
        ("calibrate", ["calibrate", "--device", "serial"], "--config"),
        ("calibrate", ["calibrate", "--device", "serial", "--config", str(d / "fifo")], "not a regular file"),
        ("secure", ["secure", "nope"], "invalid choice"),
        ("secure", ["secure", "init", text, "--scanner", "s1"], "cannot make"),
        ("secure", ["secure", "init", f"{NOWHERE}/pki", "--scanner", "s1"], "cannot make"),
        ("secure", ["secure", "init", str(d / "pki2"), "--scanner", "bad/id"], "scanner id"),
        ("secure", ["secure", "add-scanner", dirp, "s2"], "no CA"),
        ("secure", ["secure", "rotate", dirp, "router"], "nothing to rotate"),
        ("secure", ["secure", "rotate", dirp], "required"),
        ("secure", ["secure", "config", dirp, "--role", "nope"], "unknown role"),
        ("schemas", ["schemas", "--prefix", "bad prefix"], "prefix"),
        ("version", ["version", "extra"], "unrecognized arguments"),
        ("warm-up", ["warm-up", "now"], "unrecognized arguments"),
        ("warm-up", ["warm-up", "--in-process", "now"], "unrecognized arguments"),
        ("bench", ["bench", "nope"], "invalid choice"),
        ("bench", ["bench", "all", "--runs", "1"], "unrecognized arguments"),
        ("bench", ["bench", "sim", "--runs", "0"], "--runs"),
        ("bench", ["bench", "sim", "--preset", "nope"], "preset"),
        ("bench", ["bench", "estimators", "--seeds", "0"], "--seeds"),
        ("bench", ["bench", "estimators", "--families", "nope"], "family"),
        ("bench", ["bench", "estimators", "--json", dirp], "directory"),
        ("bench", ["bench", "acquire", "--steps", "0"], "steps"),
        ("bench", ["bench", "ingest", "--scans", "0"], "--scans"),
        ("bench", ["bench", "recording", "--dir", text], "not a folder"),
        ("bench", ["bench", "surfaces", "--worlds", "nope"], "world family"),
        ("bench", ["bench", "fleet", "--scanners", "0"], "--scanners"),
        ("bench", ["bench", "fleet", "--service", "nope=1"], "nope"),
        ("bench", ["bench", "map", "--worlds", "nope"], "world family"),
        ("bench", ["bench", "batch", "--files", "0"], "--files"),
        ("bench", ["bench", "stress-worlds", "--classes", "nope"], "stress class"),
    ]


_TABLES = {"recordings": _recordings_cases, "live": _live_cases, "setup": _setup_cases}


def _cases(d: Path, family: str) -> list[tuple[str, list[str], str]]:
    """(command, argv, a word the error line must hold) of one family; every one exits 2."""
    return _common_cases(d, FAMILIES[family]) + _TABLES[family](d)


def test_every_command_is_in_a_table(files):
    assert sorted(c for commands in FAMILIES.values() for c in commands) == COMMANDS
    for family, commands in FAMILIES.items():
        assert {command for command, _argv, _word in _TABLES[family](files)} == set(commands)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_misuse_is_one_line_and_exit_2(family, files, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # commands' default outputs (out/…) must not meet a developer's own
    failures = []
    for command, argv, word in _cases(files, family):
        code = main(argv)
        err = capsys.readouterr().err
        one_line = err.count("\n") == 1 and err.endswith("\n")
        named = err.startswith(("lelsonar: error:", f"lelsonar {command}: error:", f"lelsonar {command} "))
        clean = "Traceback" not in err and ".rs:" not in err  # nor a Rust source location from a library
        if not (code == 2 and one_line and named and word in err and clean):
            failures.append(f"lelsonar {' '.join(argv)}: exit {code}, wanted 2 and {word!r}; stderr {err!r}")
    assert not failures, "\n".join(failures)
    # nothing half-written, nothing replaced
    assert not any((files / name).exists() for name in ("r.mcap", "bag", "batch", "a", "pki2", "x.xyz"))
    assert (files / "exists.rrd").read_bytes() == b""


def test_a_config_file_fills_range_checked_flags_as_the_command_line_does(tmp_path):
    from lelsonar.cli.config_file import parse_args

    cfg = tmp_path / "planner.toml"
    cfg.write_text("[planner]\nuntil_final = 2\ntimeout = 1.5\n")
    args = parse_args(build_parser(), ["planner", "--config", str(cfg)])
    assert (args.until_final, args.timeout) == (2, 1.5)
    assert parse_args(build_parser(), ["planner", "--config", str(cfg), "--timeout", "3"]).timeout == 3.0


def test_a_service_with_no_router_says_which_to_start(capsys):
    """The live commands dial a router by default: without one, one line names the endpoint and the fix."""
    code = main(["planner", "--connect", "tcp/127.0.0.1:9"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "tcp/127.0.0.1:9" in err and "lelsonar router" in err
    assert ".rs:" not in err


def test_exit_codes_are_documented_in_the_help(capsys):
    assert main(["--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    for code in EXIT_CODES:
        assert f"{code} " in out
    assert "--overwrite" in out


# --- processes: Ctrl-C and a closed stdout --------------------------------------------------------

# Arms a SIGINT that the process sends itself at its first import after parsing (the command's own
# start-up) or its first wait on an event (a command that imports nothing more and then waits), whichever
# comes first; with LELSONAR_TEST_SIGINT_AT=parse, at the parser's first import of a subcommand.
_WRAPPER = """
import os, signal, sys, threading
import lelsonar.cli.config_file as config_file
from lelsonar.cli.main import main

fired = []

def fire():
    if not fired:
        fired.append(True)
        os.kill(os.getpid(), signal.SIGINT)

class SigintOnImport:
    def find_spec(self, name, path=None, target=None):
        fire()
        return None

def arm():
    sys.meta_path.insert(0, SigintOnImport())
    wait = threading.Event.wait
    def wait_then_fire(self, timeout=None):
        fire()
        return wait(self, timeout)
    threading.Event.wait = wait_then_fire

if os.environ.get("LELSONAR_TEST_SIGINT_AT") == "parse":
    sys.meta_path.insert(0, SigintOnImport())
else:
    parse = config_file.parse_args
    def parse_then_arm(*a, **kw):
        args = parse(*a, **kw)
        arm()
        return args
    config_file.parse_args = parse_then_arm
code = main(sys.argv[1:])
print("fired" if fired else "not fired", file=sys.stderr)
sys.exit(code)
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _startup_argv(d: Path, command: str) -> list[str]:
    scan = str(d / "scan.mcap")
    return {
        "acquire": ["acquire", "--no-zenoh", "--device", "sim", "--out", str(d / "startup")],
        "calibrate": ["calibrate"],
        "demo": ["demo", "--out", str(d / "startup-demo")],
        "emulate": ["emulate", "--source", "echo"],
        "export": ["export", scan, "-o", str(d / "startup-bag")],
        "info": ["info", scan],
        "planner": ["planner", "--connect", "tcp/127.0.0.1:9"],
        "reconstruct": ["reconstruct", "--source", scan],
        "recover": ["recover", scan, "-o", str(d / "startup.mcap")],
        "review": ["review", scan, "-o", str(d / "startup.rrd")],
        "ros2-bridge": ["ros2-bridge", "--source", scan],
        "router": ["router", "--listen", f"tcp/127.0.0.1:{_free_port()}"],
        "secure": ["secure", "init", str(d / "startup-pki"), "--scanner", "s1"],
        "bench": ["bench", "sim"],
        "map": ["map", "--source", scan],
        "mapper": ["mapper", "--scanner", "s1", "--connect", "tcp/127.0.0.1:9"],
        "batch": ["batch", "info", scan, "--out", str(d / "startup-batch")],
    }.get(command, [command])


def _default_sigint() -> None:
    """In the child: Ctrl-C as a terminal delivers it, even where this test was started with SIGINT ignored
    (a background job of a non-interactive shell), which Python would otherwise inherit."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _run(argv, *, env=None, stdout=subprocess.DEVNULL, until: str | None = None):
    """Run ``argv`` (killed after 300 s); with ``until``, SIGINT once a line holding it appears on stdout or
    stderr (then merged).  Returns (exit code, stderr lines)."""
    merged = until is not None
    proc = subprocess.Popen(
        argv,
        preexec_fn=_default_sigint,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE if merged else stdout,
        stderr=subprocess.STDOUT if merged else subprocess.PIPE,
        text=True,
        env=env,
    )
    stream = proc.stdout if merged else proc.stderr
    watchdog = threading.Timer(300.0, proc.kill)
    watchdog.start()
    lines = []
    try:
        if merged:
            for line in stream:
                lines.append(line)
                if until in line:
                    proc.send_signal(signal.SIGINT)
                    break
        lines += stream.readlines()
        proc.wait()
    finally:
        watchdog.cancel()
        stream.close()
    if proc.returncode == -signal.SIGKILL:
        lines.append("TIMEOUT\n")
    return proc.returncode, lines


def _side_by_side(jobs: dict[str, callable]) -> dict[str, tuple[int, list[str]]]:
    results: dict[str, tuple[int, list[str]]] = {}

    slots = threading.Semaphore(8)  # a few at a time: each process loads the whole package

    def one(name, fn):
        with slots:
            t0 = time.monotonic()
            results[name] = fn()
        if os.environ.get("LELSONAR_TEST_TIMES"):
            print(f"{time.monotonic() - t0:6.1f} s  {name}", file=sys.stderr)

    threads = [threading.Thread(target=one, args=item) for item in jobs.items()]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


@pytest.mark.slow
def test_ctrl_c_and_closed_pipes_in_processes(files, tmp_path):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    jobs = {}
    for command in COMMANDS:
        argv = [sys.executable, "-c", _WRAPPER, *_startup_argv(files, command)]
        jobs[f"startup {command}"] = lambda argv=argv: _run(argv, env=env)
    jobs["parser imports"] = lambda: _run(
        [sys.executable, "-c", _WRAPPER, "version"], env={**env, "LELSONAR_TEST_SIGINT_AT": "parse"}
    )
    port = _free_port()
    router = f"tcp/127.0.0.1:{port}"
    client = ["--mode", "client", "--connect", router]
    # Mid-run, once each says it runs: services that run until Ctrl-C exit 0, a job cut short 130.
    midrun = {
        "router": (["router", "--listen", f"tcp/127.0.0.1:{_free_port()}"], "listening", 0),
        "planner": (["planner", *client], "planner: listening", 0),
        "emulate": (["emulate", "--source", "echo"], "Ctrl-C to stop", 0),
        "reconstruct": (["reconstruct", *client], "reconstruct: listening", 0),
        "acquire": (
            ["acquire", "--device", "emulated", *client, "--out", str(tmp_path / "acq"), "--serve-log-for", "0"],
            "acquire: publishing",
            130,
        ),
        "foxglove-wait": (  # waiting for a viewer that never comes: Ctrl-C ends the wait, not its 600 s
            ["reconstruct", "--source", str(files / "scan.mcap"), "--foxglove", "0", "--foxglove-wait", "600"],
            "waiting up to",
            130,
        ),
    }
    router_proc = subprocess.Popen(
        [LELSONAR, "router", "--listen", router],
        preexec_fn=_default_sigint,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert "listening" in router_proc.stdout.readline()
        for name, (argv, marker, _code) in midrun.items():
            jobs[f"mid-run {name}"] = lambda argv=argv, marker=marker: _run([LELSONAR, *argv], env=env, until=marker)
        # A closed stdout: the read end is closed before the command starts, so its first write fails.
        for argv in (["info", str(files / "scan.mcap")], ["schemas"], ["simulate"], ["calibrate"], ["version"]):

            def closed(argv=argv):
                r, w = os.pipe()
                os.close(r)
                try:
                    return _run([LELSONAR, *argv], env=env, stdout=w)
                finally:
                    os.close(w)

            jobs[f"closed stdout {argv[0]}"] = closed
        results = _side_by_side(jobs)
    finally:
        router_proc.send_signal(signal.SIGINT)
        router_proc.wait(timeout=30)
    failures = []
    for name, (code, lines) in sorted(results.items()):
        err = "".join(lines)
        if "Traceback" in err or "TIMEOUT" in err:
            failures.append(f"{name}: {err[-600:]}")
            continue
        if name.startswith(("startup", "parser")):
            said = [ln for ln in lines if ln.strip() not in ("fired", "not fired")]
            fired = "fired\n" in lines
            command = name.split()[-1]
            if not fired:
                ok = code == 0
            elif code == 0:  # a service whose own Ctrl-C handler was in place: stopped as it documents
                ok = command in SERVICES
            else:
                ok = code == 130 and len(said) == 1 and "interrupted" in said[0]
        elif name.startswith("mid-run"):
            ok = code == midrun[name.split()[-1]][2]
        else:
            ok = code == 141 and err == ""
        if not ok:
            failures.append(f"{name}: exit {code}, stderr {err[-600:]!r}")
    assert not failures, "\n".join(failures)
    assert results["parser imports"][0] == 130  # Ctrl-C while the parser imports the subcommands


def test_exit_stats_count_the_samples_of_a_scan_stopped_mid_way():
    """After Ctrl-C mid-scan, the totals count what was ingested, not only the finished scans'."""
    from lelsonar import codec as c
    from lelsonar.cli.reconstruct import count_open_scans
    from lelsonar.reconstruct.stream.config import ReconstructConfig
    from lelsonar.reconstruct.stream.service import ReconstructionService

    messages = [m for m in simulated_messages("paper-test1", seed=2, steps=120) if not isinstance(m, c.ScanEnd)]
    service = ReconstructionService(ReconstructConfig(provisional=False))
    for m in messages[:101]:  # the ScanStart and 100 samples
        service.handle(type(m).DESCRIPTOR.full_name, m.SerializeToString())
    stats = service.stats_dict()
    assert stats["samples"]["received_live"] == 0  # the service counts a scan at its final
    count_open_scans(stats, service)
    assert stats["samples"]["received_live"] == 100 and stats["samples"]["open_scans"] == 1


@pytest.mark.slow
def test_a_cold_kernel_cache_is_announced_and_compiled_in_a_child(monkeypatch, capsys):
    """Warm-up on a cold cache says it compiles before it starts, compiles in a child process, which Ctrl-C
    ends at once (Numba's compiler would hold it in this one), and says where the time went."""
    import lelsonar.cli.warm_up as warm_up

    calls = []
    real = warm_up.compile_in_child

    def counted(console, notice):
        calls.append(notice)
        return real(console, notice)

    monkeypatch.setattr(warm_up, "cache_is_cold", lambda: not calls)
    monkeypatch.setattr(warm_up, "compile_in_child", counted)
    assert main(["warm-up"]) == 0
    err = " ".join(capsys.readouterr().err.split())
    assert calls == [warm_up.WARM_UP_NOTICE] and warm_up.WARM_UP_NOTICE in err
    assert err.index(warm_up.WARM_UP_NOTICE) < err.index("warm-up:")
    assert "compiled in" in err and "in a child process" in err
