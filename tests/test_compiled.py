"""The compiled kernels' cache: complete, keyed to the sources, and reused by a new process."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from lelsonar.signal.compiled import KERNEL_MODULES, module_source

SERVICES = Path(__file__).parents[1] / "services"


def test_every_module_with_a_kernel_is_in_the_cache_key():
    """A kernel calling another module's kernel keeps that module's machine code: if the module is left out of
    the key, editing it leaves stale code in the cache."""
    with_kernels = {
        p.resolve() for p in SERVICES.rglob("*.py") if re.search(r"^@kernel\b", p.read_text(), re.MULTILINE)
    }
    assert with_kernels == {module_source(name).resolve() for name in KERNEL_MODULES}


def _warm_up() -> str:
    done = subprocess.run([sys.executable, "-m", "lelsonar", "warm-up"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return " ".join(done.stderr.split())


def test_a_new_process_loads_the_kernels_the_warm_up_compiled():
    _warm_up()  # compiles only if nothing has since the sources last changed (`make` warms up after installing)
    second = _warm_up()
    found = re.search(r"(\d+) kernels ready: (\d+) variants compiled now and (\d+) loaded from the cache", second)
    assert found, second
    n_kernels, compiled, loaded = map(int, found.groups())
    assert n_kernels > 0 and compiled == 0 and loaded > 0, second


def test_float32_at_reads_the_samples_at_every_byte_offset():
    """A protobuf field's bytes lie at any address: the unaligned view reads them as NumPy does."""
    import numpy as np

    from lelsonar.signal.compiled import float32_at, kernel

    @kernel
    def read(payload, start, n):
        row = float32_at(np.frombuffer(payload, dtype=np.uint8), start, n)
        return row.copy()

    values = np.random.default_rng(3).standard_normal(37).astype(np.float32)
    for offset in range(4):
        payload = bytes(offset) + values.tobytes() + bytes(3)
        np.testing.assert_array_equal(read(payload, offset, values.size), values)
