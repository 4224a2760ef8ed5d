"""Which of the echoes a model of the walls leaves unexplained speak against those walls.

A model that took the corner cluster (or anything else) for a wall leaves the
real wall's echoes unexplained, so a large share of unexplained echoes has
been read as "the walls explain the wrong echoes".  But a third surface (a
floor, a table, a pillar) also returns echoes that neither wall nor their
edge explains, and those say nothing against the walls.  The two differ in
where the echoes are, against what the model's walls have already shown:

* an echo **behind** a wall (later than the wall's mirror echo along that
  beam) from a beam no further off the wall's normal than beams the wall did
  answer: the wall, were it where the model puts it, would have answered
  first (its mirror echo is strongest face-on, paper §3) — against;
* an echo **in front of** a wall from a beam closer to face-on than the
  wall's own echoes: it may be the real wall's mirror echo, the model's wall
  being something farther (the corner cluster) — against;
* an echo in front of a wall from a beam further off its normal than several
  echoes the wall did return: a mirror plane there, near parallel to the
  wall, would have answered those more face-on beams first, and they heard
  the wall — a third surface (diffuse, along the beam), not evidence against;
* an echo behind a wall from a beam further off its normal than any it
  answered, or from a beam that faces no wall at all: outside what the walls
  return — not evidence against.
"""

from __future__ import annotations

import numpy as np

__all__ = ["echoes_against_walls"]


def echoes_against_walls(
    residuals: np.ndarray, cosines: np.ndarray, own: np.ndarray, unexplained: np.ndarray, min_face_on: int
) -> np.ndarray:
    """Mask of the ``unexplained`` echoes that a wall of the model should have returned instead.

    Parameters
    ----------
    residuals : (K, N) array
        Each wall's mirror-echo residual ``n·p_c + d − h`` of every echo, m
        (:func:`~lelsonar.reconstruct.estimate.corner.model.echo_residuals`):
        positive behind the wall, negative in front of it; ``inf`` where the
        wall's normal lies outside the beam (the wall cannot have returned it).
    cosines : (K, N) array
        Cosine of each echo's boresight to each wall's normal.
    own : (K, N) bool array
        The echoes the model gives to each wall.
    unexplained : (N,) bool array
        The echoes the model leaves unexplained (its outliers).
    min_face_on : int
        How many of a wall's own echoes must come from beams at least as
        close to face-on as an echo in front of it for that echo to be a
        third surface's (one stray echo given to the wall must not clear a
        competing mirror plane).

    Returns
    -------
    (N,) bool array
        True for an unexplained echo that some wall, where the model puts it,
        contradicts: behind the wall from a beam within the angle the wall
        answered at, or in front of it from a beam closer to face-on than the
        wall's ``min_face_on`` most face-on echoes.
    """
    r = np.asarray(residuals, dtype=np.float64)
    cos = np.asarray(cosines, dtype=np.float64)
    own = np.asarray(own, dtype=bool)
    against = np.zeros(r.shape[1], dtype=bool)
    for k in range(r.shape[0]):
        c_own = cos[k, own[k]]
        # Behind: the wall answered beams down to its echoes' lowest cosine (none: nothing clears the echo).
        widest = float(c_own.min()) if c_own.size else -np.inf
        # In front: the cosine of its min_face_on-th most face-on echo (too few: nothing clears the echo).
        m = int(min_face_on)
        nearest = float(np.partition(c_own, c_own.size - m)[c_own.size - m]) if c_own.size >= m >= 1 else -np.inf
        faces = unexplained & np.isfinite(r[k])
        behind = faces & (r[k] > 0) & (cos[k] >= widest)
        in_front = faces & (r[k] < 0) & (cos[k] > nearest)
        against |= behind | in_front
    return against
