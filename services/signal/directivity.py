"""A capsule's beam: the directivity of a baffled circular piston, which the simulator sounds with and the
surfaces' beam-pattern tests read echoes through."""

from __future__ import annotations

import numpy as np
from scipy.special import j1

__all__ = ["PISTON_FIRST_NULL", "piston_directivity"]

#: ``ka·sinθ`` of the piston's first null (J1's first zero): past it the main lobe says nothing.
PISTON_FIRST_NULL = 3.8317


def piston_directivity(theta: np.ndarray, ka: float) -> np.ndarray:
    """One-way directivity of a baffled circular piston, ``D(θ) = 2·J1(x)/x``, ``x = ka·sinθ``.

    A transceiver sees ``D²`` (transmit and receive).  ``D(0) = 1``.

    Parameters
    ----------
    theta : array
        Off-axis angle, rad.
    ka : float
        Wavenumber times piston radius.
    """
    x = ka * np.sin(np.asarray(theta, dtype=float))
    small = np.abs(x) < 1e-6
    # 2·J1(x)/x → 1 as x → 0; avoid 0/0 without a warning.
    safe = np.where(small, 1.0, x)
    return np.where(small, 1.0, 2.0 * j1(safe) / safe)
