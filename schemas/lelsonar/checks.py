"""Field checks every decoder of the contract shares: finite numbers and finite vectors, named in the error."""

from __future__ import annotations

import math

from lelsonar.errors import NonFiniteValueError


def finite(where: str, *values: float) -> None:
    """Raise :class:`~lelsonar.errors.NonFiniteValueError` naming ``where`` unless every value is finite."""
    if not all(math.isfinite(v) for v in values):
        raise NonFiniteValueError(f"{where} must be finite, got {values if len(values) > 1 else values[0]}")


def finite_vector(where: str, v) -> None:
    """:func:`finite` of a ``Vector3``'s ``x, y, z``."""
    finite(where, v.x, v.y, v.z)
