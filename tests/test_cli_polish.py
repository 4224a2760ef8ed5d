"""One line, never a traceback, where scripts need one; the README's command table is complete."""

from __future__ import annotations

import builtins
import re
import subprocess
import sys
from pathlib import Path

import pytest

from lelsonar.cli.main import build_parser, main
from lelsonar.log import recording

from .conftest import simulated_messages

LELSONAR = str(Path(sys.executable).with_name("lelsonar"))
README = Path(__file__).parents[1] / "README.md"


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    path = tmp_path_factory.mktemp("polish") / "scan.mcap"
    with recording.McapRecorder(path) as rec:
        for m in simulated_messages("paper-test1", seed=1, steps=120):
            rec.write(m)
    return path


def test_a_closed_stdout_ends_quietly(scan):
    proc = subprocess.Popen(
        [LELSONAR, "reconstruct", "--source", str(scan), "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    proc.stdout.close()  # the reader is gone before the first line (as `| head` after its lines)
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141
    assert "Traceback" not in err and "BrokenPipe" not in err


@pytest.mark.parametrize("content", [b"ab", b"\x89MCAP0\r\nxxxxxxxxxxxxxxxx", b"plain text, not a recording\n" * 3])
def test_damaged_or_foreign_files_give_one_line(tmp_path, capsys, content):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    assert main(["reconstruct", "--source", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("lelsonar reconstruct: error: ") and str(bad) in err


def test_plot_without_matplotlib_names_the_extra(tmp_path, monkeypatch, capsys):
    real_import = builtins.__import__

    def no_matplotlib(name, *args, **kwargs):
        if name.startswith("matplotlib"):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    assert main(["simulate", "--plot", str(tmp_path / "x.png")]) == 2
    assert "pip install 'lelsonar[plot]'" in capsys.readouterr().err


def test_readme_command_table_lists_every_command():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    table = README.read_text().split("## Commands", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"^\| `lelsonar ([a-z0-9-]+)", table, re.M))
    listed |= set(re.findall(r"`lelsonar ([a-z0-9-]+)`", table))
    assert set(sub.choices) <= listed, f"missing from the README: {sorted(set(sub.choices) - listed)}"


def test_each_command_is_registered_by_the_module_the_registry_names():
    import importlib

    from lelsonar.cli.main import COMMANDS, OneLineParser

    for module, names in COMMANDS.items():
        sub = OneLineParser(prog="x").add_subparsers(dest="command")
        importlib.import_module(module).register(sub)
        assert tuple(sub.choices) == names, module
    every = next(a for a in build_parser()._actions if a.dest == "command").choices
    assert list(every) == [n for names in COMMANDS.values() for n in names]
    # A command line that names its command builds that module's commands only; help builds them all.
    only = next(a for a in build_parser(["info", "x.mcap"])._actions if a.dest == "command").choices
    assert list(only) == ["recover", "info"]
    assert list(next(a for a in build_parser(["--help"])._actions if a.dest == "command").choices) == list(every)


def test_bench_progress_yields_every_item():
    from lelsonar.tools.bench import progress

    assert list(progress(range(5), "x")) == [0, 1, 2, 3, 4]
    assert list(progress(iter("abc"), "y", total=3)) == ["a", "b", "c"]


def test_a_worker_thread_that_loses_stdout_stops_the_command_cleanly():
    # The main thread waits for SIGTERM itself (no handler, no lock taken in a handler).
    script = (
        "import signal, sys, threading\n"
        "from lelsonar.cli.main import _end_quietly_when_a_thread_loses_stdout\n"
        "signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})\n"
        "closed = _end_quietly_when_a_thread_loses_stdout()\n"
        "def worker():\n"
        "    raise BrokenPipeError(32, 'Broken pipe')\n"
        "threading.Thread(target=worker).start()\n"
        "got = signal.sigtimedwait({signal.SIGTERM}, 60)\n"
        "print('stopped' if got is not None and closed.is_set() else 'hung', file=sys.stderr)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.stderr.strip() == "stopped" and done.returncode == 0
