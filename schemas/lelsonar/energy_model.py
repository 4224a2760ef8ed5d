"""The rig's calibrated energy model ``E0(d)`` (paper eq. 12), shared by both services.

``acquire`` puts it in every ``ScanStart`` (``EnergyModel`` of the contract);
``reconstruct`` divides the measured energy by it (eq. 11–12).  It lives next
to the contract because it is part of what a scan says about its rig.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar, overload

import numpy as np

from lelsonar.errors import ConfigError

__all__ = ["EnergyModel"]

#: One range (a float) or many (an array): the quadratic keeps the kind it is given.
_D = TypeVar("_D", float, np.ndarray)


@dataclass(frozen=True)
class EnergyModel:
    """Expected face-on energy against range, the paper's eq. (12).

    ``E0(d) = 1 / (φ0·d² + φ1·d + φ2)`` with ``d`` in metres and ``E0`` in V²·s,
    so φ0 is in 1/(V²·s·m²), φ1 in 1/(V²·s·m) and φ2 in 1/(V²·s).  The paper's
    printed φ (eq. 13) use centimetres and its own amplifier; calibrate your own
    with :func:`fit_energy_model`.
    """

    phi0: float
    phi1: float
    phi2: float
    d_min: float = 0.9
    d_max: float = 1.8

    def __post_init__(self) -> None:
        values = (self.phi0, self.phi1, self.phi2, self.d_min, self.d_max)
        if not all(np.isfinite(values)):
            raise ConfigError(f"energy model parameters must be finite, got {values}")
        if not 0 < self.d_min < self.d_max:
            raise ConfigError(f"energy model range must satisfy 0 < d_min < d_max, got {self.d_min}, {self.d_max}")
        d = np.linspace(self.d_min, self.d_max, 32)
        if np.any(self._denominator(d) <= 0):
            raise ConfigError(
                "energy model gives a non-positive energy inside its range "
                f"[{self.d_min}, {self.d_max}] m; recalibrate with `lelsonar calibrate`"
            )

    def _denominator(self, d: _D) -> _D:
        return self.phi0 * d * d + self.phi1 * d + self.phi2

    @overload
    def expected_energy(self, distance: float) -> float: ...

    @overload
    def expected_energy(self, distance: np.ndarray) -> np.ndarray: ...

    def expected_energy(self, distance: np.ndarray | float) -> np.ndarray | float:
        """``E0(d)`` in V²·s, eq. (12).  Ranges are clipped to the calibrated interval,
        where the quadratic is known to stay positive.  A float in, a float out."""
        if isinstance(distance, float):
            # One step's range (the live service, per sample): plain min/max, not np.clip on a 0-d array.
            return 1.0 / self._denominator(min(max(distance, self.d_min), self.d_max))
        d = np.clip(np.asarray(distance, dtype=np.float64), self.d_min, self.d_max)
        return 1.0 / self._denominator(d)
