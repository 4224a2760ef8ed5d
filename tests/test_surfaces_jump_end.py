"""A face whose mirror echo hands over, at one range, to its own end's weak diffraction: the face placed by one
beam pattern across the amplitude jump.

The face's foot lies where it ends, so its region of constant depth holds the face's rising flank, cut where the
foot leaves the face, then the end's weak echo at the same range: each piece alone leaves the face's bearing
open (a flank cut by an echo at a like range, an edge's echo), the two together place it within the angle an
end at the face's depth can lie off its foot.
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.estimate.surfaces import extract_surfaces
from lelsonar.reconstruct.estimate.surfaces.flank_bearing import FLANK_SOURCE, across_jump_bearing
from lelsonar.reconstruct.estimate.surfaces.piston_beam import SweepBeam
from lelsonar.signal.directivity import piston_directivity
from tests.piston_sweep import GAMMA, GEOMETRY, PistonSweep

#: The face: its foot and depth; its end just past the foot, at the face's depth within 0.1 mm.
FOOT, DEPTH = math.radians(20.0), 1.5
END = FOOT + math.radians(0.5)
#: Where the foot leaves the face: the mirror answers before it, the end after it.
HANDOVER = FOOT - math.radians(1.0)
#: A wall seen whole elsewhere: the sweep's beam and strongest echo.
REFERENCE = (math.radians(-90.0), 1.2)


def _sweep(seed: int) -> tuple[np.ndarray, np.ndarray]:
    face, end = PistonSweep(seed), PistonSweep(seed + 100)
    for s in (face, end):
        s.wall(*REFERENCE)
    face.wall(FOOT, DEPTH)
    end.corner(END, DEPTH / math.cos(END - FOOT), gain=0.4)
    (d_face, a_face), (d_end, a_end) = face.readings(), end.readings()
    past = (GAMMA >= HANDOVER)[:, None] & (GAMMA > 0.0)[:, None]
    return np.where(past, d_end, d_face), np.where(past, a_end, a_face)


def test_the_premise_the_end_is_weak_and_the_face_piece_is_its_flank_alone():
    d, a = _sweep(21)
    near = np.abs(d - DEPTH) < 0.05
    steps = np.flatnonzero(near.any(axis=1))
    assert GAMMA[steps].min() < HANDOVER < GAMMA[steps].max()
    face = a[near & (GAMMA < HANDOVER)[:, None]]
    edge = a[near & (GAMMA >= HANDOVER)[:, None]]
    assert np.nanmax(edge) < 0.35 * np.nanmax(face)


def test_a_face_handing_over_to_its_end_at_one_range_is_placed_across_the_jump():
    for seed in (21, 22, 23):
        d, a = _sweep(seed)
        result = extract_surfaces(GAMMA, d, GEOMETRY, amplitude=a)
        faces = [w for w in result.surfaces if abs(w.offset - DEPTH) < 0.02]
        assert len(faces) == 1, [(w.label, w.bearing_source, w.reasons) for w in result.surfaces]
        (face,) = faces
        assert face.bearing_source == FLANK_SOURCE, face.reasons
        assert any("across the amplitude jump" in r for r in face.reasons), face.reasons
        sigma = math.sqrt(face.covariance[0, 0])
        assert abs(face.bearing - FOOT) <= 3 * sigma, (math.degrees(face.bearing), math.degrees(sigma))
        # The end lies off the foot by at most acos(h/ρ) of the depths' σ: a few degrees, not the reach past a cut.
        assert sigma < math.radians(5.0)
        assert face.quality != "good"


def _profile(g: np.ndarray, bearing: float, level: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    la = level + 2.0 * np.log(np.abs(piston_directivity(g - bearing, BEAM.ka))) + 0.01 * rng.normal(size=g.size)
    return g, la


BEAM = SweepBeam(ka=5.13, ka_stderr=0.02, n_regions=2)


def test_two_echoes_about_one_bearing_give_it_and_two_about_bearings_apart_give_none():
    rng = np.random.default_rng(7)
    flank = np.radians(np.arange(-14.0, 19.0, 1.0))
    end = np.radians(np.arange(19.0, 44.0, 1.0))
    lo, hi = float(flank[0]), float(end[-1])
    one = across_jump_bearing([_profile(flank, FOOT, 0.0, rng), _profile(end, FOOT, -1.8, rng)], BEAM, lo, hi)
    assert one is not None
    assert abs(one[0] - FOOT) <= 3 * one[1] and one[1] < math.radians(1.0)
    apart = across_jump_bearing(
        [_profile(flank, FOOT + math.radians(12.0), 0.0, rng), _profile(end, FOOT, -1.8, rng)], BEAM, lo, hi
    )
    assert apart is None
