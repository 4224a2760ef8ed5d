"""``lelsonar bench ingest``'s two processes: a consumer and a publisher started on a private socket, their
result lines read on threads with bounded waits, and both always reaped."""

from __future__ import annotations

import argparse
import json
import queue
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

#: The line a child prints with its results (JSON after it), and the consumer's once it listens.
RESULT = "RESULT "
READY = "READY"


# --- the parent: run a phase with two processes ------------------------------------------------
def child_process(
    role: str, args: argparse.Namespace, sock: Path, phase: str, timeout: float, stderr_path: Path
) -> subprocess.Popen:
    """``python -m lelsonar.tools.bench_ingest --role ROLE`` with the run's options, its stderr to a file."""
    cmd = [
        sys.executable,
        "-m",
        "lelsonar.tools.bench_ingest",
        "--role",
        role,
        "--socket",
        str(sock),
        "--phase",
        phase,
        "--timeout",
        str(timeout),
        "--preset",
        args.preset,
        "--scans",
        str(args.scans),
        "--seconds",
        str(args.seconds),
        "--rate",
        str(args.rate),
        "--scanners",
        str(args.scanners),
        "--latency-scanners",
        str(args.latency_scanners),
        "--fifo",
        str(args.fifo),
    ]
    with open(stderr_path, "w") as err:
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True)


class LineReader:
    """Reads a child's stdout lines on a thread, so waits for a line are bounded."""

    def __init__(self, name: str, proc: subprocess.Popen) -> None:
        self.name = name
        self.proc = proc
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._thread = threading.Thread(target=self._read, name=f"{name}-stdout", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def wait_for(self, prefix: str, deadline: float) -> str:
        """The first line starting with ``prefix``; raises if the child ends or the deadline passes first."""
        while True:
            remaining = deadline - time.monotonic()
            try:
                line = self._lines.get(timeout=remaining) if remaining > 0 else None
            except queue.Empty:
                line = None
            if line is None:
                raise RuntimeError(f"no {prefix.strip()!r} line from the {self.name} (exit code {self.proc.poll()})")
            if line.startswith(prefix):
                return line[len(prefix) :]


def run_phase(args: argparse.Namespace, phase: str) -> tuple[dict, dict]:
    """Start a consumer and a publisher on a private socket; return their results."""
    budget = args.seconds + 40.0 if phase == "rate" else (args.scans + 1) * 256 / args.rate + 40.0
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory(prefix="lelsonar-bench-ingest-") as tmp:
        tmpdir = Path(tmp)
        sock = tmpdir / "z.sock"
        try:
            consumer = child_process("consumer", args, sock, phase, budget, tmpdir / "consumer.err")
            procs.append(consumer)
            consumer_out = LineReader("consumer", consumer)
            consumer_out.wait_for(READY, time.monotonic() + 60)
            publisher = child_process("publisher", args, sock, phase, budget, tmpdir / "publisher.err")
            procs.append(publisher)
            publisher_out = LineReader("publisher", publisher)
            end = time.monotonic() + budget + 20
            pub = json.loads(publisher_out.wait_for(RESULT, end))
            con = json.loads(consumer_out.wait_for(RESULT, end))
            for p, name in zip(procs, ("consumer", "publisher")):
                if p.wait(timeout=max(1.0, end - time.monotonic())) != 0:
                    raise RuntimeError(f"the {name} process exited with {p.returncode}")
            return pub, con
        except BaseException:
            for name in ("consumer.err", "publisher.err"):
                text = (tmpdir / name).read_text() if (tmpdir / name).exists() else ""
                if text.strip():
                    print(f"--- {name} ---\n{text[-3000:]}", file=sys.stderr)
            raise
        finally:
            for p in procs:
                if p.poll() is None:
                    p.kill()
                p.wait(timeout=10)
                if p.stdout:
                    p.stdout.close()
