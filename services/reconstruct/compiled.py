"""The one module that imports Numba: :func:`kernel` compiles a hot numeric loop to machine code.

Why: the estimators and the ingest path make thousands of small NumPy calls a scan, and each costs
~1 µs of interpreter overhead whatever its size (issue 12's default-fit and ingest targets).  A
kernel runs such a loop as one call.  Kernels are ordinary Python functions over NumPy arrays and
scalars; the math stays in the module it belongs to (``corner_model``, ``assembly``…), decorated
with :func:`kernel` — one implementation per idea, this module only holds the compiler's settings.

Settings, and why:
- ``cache=True``: compiled code is kept next to the sources (``__pycache__``, or the user's cache
  directory if that is read-only), so only the first process after an install pays the compile;
  a later one pays ~0.4 s to load the machine code on its first call.
- ``nogil=True``: a kernel releases the GIL, so the live source's threads keep receiving.
- ``error_model="numpy"``: division by zero gives inf/NaN as NumPy does, not an exception.
- no ``fastmath``: results stay IEEE, so a kernel agrees with the NumPy it replaced to rounding.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

import numba

F = TypeVar("F", bound=Callable[..., object])


def kernel(func: F) -> F:
    """Compile ``func`` with the project's Numba settings (see the module docstring)."""
    return numba.njit(cache=True, nogil=True, error_model="numpy")(func)  # type: ignore[return-value]
