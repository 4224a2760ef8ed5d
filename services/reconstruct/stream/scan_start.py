"""What a ``ScanStart`` states, read once a scan: the array geometry, the speed of sound, the energy model.

A scanner states the same array and model in every ScanStart, so both are cached by what describes them
(bounded): reading and checking them is paid once, not every scan.
"""

from __future__ import annotations

import functools
import math
from collections import OrderedDict

import numpy as np

from lelsonar import codec
from lelsonar.errors import ConfigError, InvalidMessageError
from lelsonar.geometry import ArrayGeometry
from lelsonar.signal.energy import EnergyModel

#: How far two statements of one length may differ (m): the radial offset in ScanStart.radial_offset and in
#: the capsules' array-frame positions.  A millimetre is far below the range noise and far above rounding.
_SAME_LENGTH = 1e-3


def geometry_from_start(start: codec.ScanStart) -> ArrayGeometry:
    """The array geometry a ``ScanStart`` describes (capsules on x at the radial offset).

    The radial offset is stated twice: ``radial_offset`` and the capsules' array-frame positions ``(x, r, 0)``.
    A writer may fill only one (proto3 leaves the other 0); both filled, they must agree.  An unset
    boresight (0, 0, 0) is the contract's +y, an unset rotation axis its x.

    Raises
    ------
    InvalidMessageError
        An array this build cannot describe (not a line along x facing +y, a rotation axis other than +x), or
        radial offsets that contradict each other; the message names the field to fix.
    """
    axis = start.rotation_axis
    if (axis.x, axis.y, axis.z) != (0.0, 0.0, 0.0):
        norm = math.sqrt(axis.x**2 + axis.y**2 + axis.z**2)
        if not (axis.x > 0 and math.hypot(axis.y, axis.z) <= 1e-3 * norm):
            raise InvalidMessageError(
                f"ScanStart.rotation_axis is ({axis.x:g}, {axis.y:g}, {axis.z:g}); this build supports rotation "
                "about +x only (γ right-handed about +x, beam along +y at γ = 0): state γ about +x"
            )
    ordered = sorted(start.capsules, key=lambda c: c.capsule_id)
    for c in ordered:
        b = c.boresight
        unset = (b.x, b.y, b.z) == (0.0, 0.0, 0.0)
        if abs(c.position.z) > 1e-9 or not (unset or (abs(b.x) + abs(b.z) <= 1e-9 and abs(b.y - 1.0) <= 1e-9)):
            raise InvalidMessageError(
                f"capsule {c.capsule_id} is not on the x axis line facing +y; this build supports only linear arrays"
            )
    radial = {round(c.position.y, 9) for c in ordered}
    if len(radial) > 1 and max(radial) - min(radial) > _SAME_LENGTH:
        raise InvalidMessageError(
            f"the capsules sit at different radial offsets {sorted(radial)} m (position.y); "
            "this build supports one line of capsules"
        )
    from_positions = float(np.mean([c.position.y for c in ordered]))
    offset = start.radial_offset
    if offset == 0.0:
        offset = from_positions
    elif from_positions != 0.0 and abs(from_positions - offset) > _SAME_LENGTH:
        raise InvalidMessageError(
            f"ScanStart.radial_offset {offset} m contradicts the capsules' position.y {from_positions} m: the "
            "positions are in the array frame, so y is the radial offset; state the same value in both"
        )
    return ArrayGeometry(capsule_x=tuple(c.position.x for c in ordered), radial_offset=offset)


#: Largest disagreement between ``ScanStart.sound_speed`` and c(air_temperature) that is still one air: 2 % is
#: 6 K, beyond what humidity (< 0.5 %) or a measured c explains.
SOUND_SPEED_TOLERANCE = 0.02


def air_sound_speed(start: codec.ScanStart) -> float | None:
    """c(T) = 331.3·√(T/273.15) m/s of ``ScanStart.air_temperature`` (K), None if unset."""
    t = start.air_temperature
    return 331.3 * math.sqrt(t / 273.15) if 200.0 < t < 350.0 else None


def speed_of_sound(start: codec.ScanStart) -> float | None:
    """The scan's speed of sound, m/s: ``ScanStart.sound_speed``, or from ``air_temperature`` (K) where the
    writer left it unset (0); None when neither is known."""
    if start.sound_speed > 0:
        return float(start.sound_speed)
    return air_sound_speed(start)


#: E0 for a ScanStart without a usable energy model: spherical spreading alone, E0 ∝ 1/d² (eq. 12 with
#: φ1 = φ2 = 0).  R is then uncalibrated but still relative, which is all the critical step and the energy
#: split use; the default method does not use R at all.
UNCALIBRATED_E0 = EnergyModel(1.0, 0.0, 0.0, d_min=0.01, d_max=100.0)


def energy_model_from_start(start: codec.ScanStart) -> tuple[EnergyModel, str | None]:
    """The scan's E0 (eq. 12), and why it is :data:`UNCALIBRATED_E0` instead (None if it is not).

    A scan is not thrown away for its calibration: the planes do not depend on it.
    """
    e = start.energy_model
    return energy_model_of(e.phi0, e.phi1, e.phi2, e.valid_min_range, e.valid_max_range)


@functools.lru_cache(maxsize=64)
def energy_model_of(
    phi0: float, phi1: float, phi2: float, d_min: float, d_max: float
) -> tuple[EnergyModel, str | None]:
    """The energy model (eq. 12) of these coefficients and calibrated interval, and why it is
    :data:`UNCALIBRATED_E0` instead (None if it is not); cached, as a scanner states the same model in every
    ScanStart."""
    try:
        return EnergyModel(phi0, phi1, phi2, d_min=d_min, d_max=d_max), None
    except ConfigError as exc:
        return UNCALIBRATED_E0, f"its energy model is unusable ({exc}); E0 taken as 1/d², uncalibrated"


#: Geometries of recent ScanStarts by what describes them (a scanner states the same array in every ScanStart);
#: bounded.
_GEOMETRIES: OrderedDict[tuple, ArrayGeometry] = OrderedDict()


def scan_geometry(start: codec.ScanStart) -> ArrayGeometry:
    """:func:`geometry_from_start`, of the same description once."""
    key = (
        start.rotation_axis.SerializeToString(),
        tuple([c.SerializeToString() for c in start.capsules]),
        start.radial_offset,
    )
    geometry = _GEOMETRIES.get(key)
    if geometry is None:
        geometry = _GEOMETRIES[key] = geometry_from_start(start)
        if len(_GEOMETRIES) > 64:
            _GEOMETRIES.popitem(last=False)
    return geometry
