"""Kinds the simulator's truth holds in vertical-fan worlds: a box face ending between the capsules is a plane, a
trihedral corner above the fan is no settled edge."""

from __future__ import annotations

import pytest

from lelsonar.sim.world_geometry import ElementKind
from lelsonar.tools.surface_scores import majority, world_sweep


def _claims(family: str, seed: int, pose: int, element: int):
    model, scan, _, result = world_sweep(family, seed, pose, "paper")
    planes = [s for s in result.surfaces if majority(scan, s.steps, s)[0] == element]
    features = [f for f in (*result.corners, *result.edges) if majority(scan, f.steps, f)[0] == element]
    return model, planes, features


def test_a_box_face_that_ends_between_the_capsules_is_a_plane_not_a_line_across_the_stack():
    # Boxes world 21, pose 1: the face 0.73 m away ends between the stack's middle capsules; the two past its end
    # hear its vertical edge.  Its plane is found, and its verdict says its tilt mixes the face with its end.
    model, planes, features = _claims("boxes", 21, 1, 9)
    assert model.elements[9].kind == ElementKind.MIRROR
    assert planes and not features
    assert all(p.plane.quality != "good" for p in planes)
    assert any("bend along the capsule stack" in r for p in planes for r in p.plane.quality_reasons)


@pytest.mark.parametrize(("family", "seed", "pose", "element"), [("corridor", 21, 2, 47)])
def test_a_trihedral_corner_off_the_fan_is_no_settled_edge(family, seed, pose, element):
    # Its ranges slope along the stack 24° off the fan: the beam's flank hears its retro-reflection weakly.
    model, _, features = _claims(family, seed, pose, element)
    assert model.elements[element].kind == ElementKind.TRIHEDRAL
    assert features
    assert not [f for f in features if f.kind == "edge" and f.settled]
