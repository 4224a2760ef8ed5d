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


def test_unowned_is_the_array_it_is_given():
    """An array handed on without its reference count reads and writes the array itself, of any shape and type."""
    import numpy as np

    from lelsonar.signal.compiled import kernel, unowned

    @kernel
    def touch(payload, cube):
        buf = unowned(np.frombuffer(payload, dtype=np.uint8))
        view = unowned(cube)
        view[1, 2] = -1.0
        return int(buf[3]), buf.size, view.shape, view.sum()

    cube = np.arange(12, dtype=np.float64).reshape(3, 4)
    total = cube.sum() - cube[1, 2] - 1.0
    assert touch(bytes(range(10)), cube) == (3, 10, (3, 4), total)
    assert cube[1, 2] == -1.0


def test_array_at_is_the_array_whose_address_it_is_given():
    """An array handed over as its address is read and written as the array itself, of any shape and type."""
    import numpy as np

    from lelsonar.signal.compiled import array_at, kernel

    @kernel
    def touch(cube_at, flags_at, empty_at, rows):
        cube = array_at(cube_at, (2, rows, 4), np.float64)
        flags = array_at(flags_at, rows, np.bool_)
        empty = array_at(empty_at, (rows, 0), np.float32)
        cube[1, rows - 1, 3] = -1.0
        flags[rows - 1] = True
        return cube.sum(), flags.sum(), empty.shape, cube[0, 1, 2]

    cube = np.arange(2 * 3 * 4, dtype=np.float64).reshape(2, 3, 4)
    flags, empty = np.zeros(3, bool), np.zeros((3, 0), np.float32)
    total = cube.sum() - cube[1, 2, 3] - 1.0
    assert touch(cube.ctypes.data, flags.ctypes.data, empty.ctypes.data, 3) == (total, 1, (3, 0), cube[0, 1, 2])
    assert cube[1, 2, 3] == -1.0 and flags.tolist() == [False, False, True]


def test_wire_arrays_gives_each_arrays_address_and_refuses_one_it_cannot_read_so():
    """place_wire's arrays as their addresses: each one's, in order; an array of another type or shape, not
    contiguous or read-only, is refused (the kernel would read it as contiguous and write it)."""
    import numpy as np
    import pytest

    from lelsonar.errors import InternalError
    from lelsonar.reconstruct.stream.fastwire import wire_arrays

    k, rows = 4, 9
    arrays = [
        np.zeros(k, np.int64),
        np.zeros(6 * k + 5),
        np.zeros(k, np.int64),
        np.zeros(7),
        np.zeros((9, rows, k)),
        np.zeros((5, rows)),
        np.zeros(rows, np.int64),
        np.zeros(rows, bool),
        np.zeros(rows, bool),
        np.zeros((rows, k, 20), np.float32),
        np.zeros((rows, k, 0), np.float32),
    ]

    def call(replaced: dict[int, np.ndarray]) -> np.ndarray:
        given = [replaced.get(i, a) for i, a in enumerate(arrays)]
        return wire_arrays(rows, given[0], given[1], 35, *given[2:])

    assert call({}).tolist() == [rows, 35, k, rows, 20, 0, *(a.ctypes.data for a in arrays)]
    read_only = arrays[1].copy()
    read_only.flags.writeable = False
    strided = np.zeros((9, rows, 2 * k))[:, :, ::2]
    for replaced in ({1: read_only}, {4: strided}, {6: arrays[6].astype(np.int32)}, {7: np.zeros(rows + 1, bool)}):
        with pytest.raises(InternalError):
            call(replaced)


def test_an_entry_point_is_the_kernels_own_code_for_its_signature():
    """Called without the dispatcher, a kernel gives what a call through it gives (the dispatcher's own overload
    for its examples' types); a stand-in that is not a kernel is handed back as it is."""
    import numpy as np

    from lelsonar.signal.compiled import entry_point
    from lelsonar.signal.extrema import extent

    row = np.random.default_rng(3).standard_normal(50).astype(np.float32)
    direct = entry_point(extent, row, 0, 1)
    for a, b in ((0, 50), (7, 8), (13, 41)):
        assert direct(row, a, b) == extent(row, a, b)
    assert any(direct is compiled.entry_point for compiled in extent.overloads.values())

    def stand_in(*args):
        return args

    assert entry_point(stand_in, 1, 2) is stand_in
