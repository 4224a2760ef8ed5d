"""Estimates → ``lelsonar.v1.Reconstruction``: every field maps from its own source, in SI units.

Each source value is distinct, so a field filled from the wrong attribute (or left unset) shows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.results import EdgeLine, FailureReason, FitFailure, PlaneFit
from lelsonar.v1 import reconstruction_pb2 as pb


def tilted_fit(label: str = "a", method: str = "lel") -> PlaneFit:
    normal = np.array([0.1, 0.98, 0.2])
    normal /= np.linalg.norm(normal)
    mask = np.array([True, True, False, True, False, True, True])  # 5 inliers of 7
    cov = np.array([[4e-6, 1e-7, 2e-7], [1e-7, 5e-6, 3e-7], [2e-7, 3e-7, 6e-6]])  # symmetric, not diagonal
    patch = np.array([[-0.3, 1.5, 0.1], [0.3, 1.49, 0.12], [0.31, 1.45, 0.6], [-0.29, 1.46, 0.58]])
    return PlaneFit(
        label=label,
        method=method,
        normal=normal,
        offset=1.57,
        entropy=0.42,
        sigma_relative=0.0021,
        sigma=0.0033,
        inlier_mask=mask,
        sorted_residuals=np.linspace(-0.01, 0.02, 7),
        theta_covariance=cov,
        normal_stderr=0.0044,
        offset_stderr=0.0055,
        patch=patch,
    )


def xyz(v) -> list[float]:
    return [v.x, v.y, v.z]


def test_plane_message_maps_every_field() -> None:
    fit = tilted_fit()
    msg = wire.plane_message(fit)
    assert (msg.label, msg.method) == ("a", "lel")
    np.testing.assert_allclose(xyz(msg.normal), fit.normal, rtol=0, atol=1e-15)
    assert msg.offset == 1.57
    np.testing.assert_allclose(xyz(msg.theta), fit.normal / 1.57, rtol=1e-15)  # θ = n / h (eq. 1)
    assert (msg.sigma_relative, msg.sigma) == (0.0021, 0.0033)
    assert (msg.inlier_count, msg.point_count) == (5, 7)
    assert msg.lel_cost == 0.42
    np.testing.assert_array_equal(np.reshape(msg.theta_covariance, (3, 3)), fit.theta_covariance)  # row-major
    assert (msg.normal_stderr, msg.offset_stderr) == (0.0044, 0.0055)
    np.testing.assert_array_equal([xyz(c) for c in msg.patch], fit.patch)  # corners in order
    codec.validate(pb.Reconstruction(schema_version=1, scanner_id="s1", planes=[msg]))


def test_reconstruction_message_maps_every_field() -> None:
    a, b = tilted_fit("a"), tilted_fit("b", "ls")
    edge = EdgeLine(point=np.array([0.0, 1.57, 1.06]), direction=np.array([1.0, 0.0, 0.0]), angle=math.pi / 2)
    failure = FitFailure(FailureReason.TOO_FEW_POINTS, "3 < 8 points", "b", 3)
    for status, code in (
        ("provisional", pb.ESTIMATE_STATUS_PROVISIONAL),
        ("final", pb.ESTIMATE_STATUS_FINAL),
        ("final_timeout", pb.ESTIMATE_STATUS_FINAL_TIMEOUT),
    ):
        msg = wire.reconstruction_message(
            "s1",
            77,
            status=status,
            last_step=183,
            samples_used=180,
            critical_step=67,
            critical_angle=0.5939,
            planes=[a, failure, b],
            edge=edge,
            timings=(0.011, 0.022, 0.033),
            stamp_ns=1_700_000_000_123,
        )
        codec.validate(msg)
        assert (msg.scanner_id, msg.scan_id, msg.status) == ("s1", 77, code)
        assert (msg.last_step, msg.samples_used, msg.stamp_ns) == (183, 180, 1_700_000_000_123)
        assert msg.HasField("critical_step") and (msg.critical_step, msg.critical_angle) == (67, 0.5939)
        assert [p for p in msg.planes] == [wire.plane_message(a), wire.plane_message(b)]  # failures are not planes
        assert list(msg.failures) == [str(failure)] and "3 < 8 points" in msg.failures[0]
        assert xyz(msg.corner_edge.point) == [0.0, 1.57, 1.06] and xyz(msg.corner_edge.direction) == [1.0, 0.0, 0.0]
        assert (msg.timings.segmentation, msg.timings.fit, msg.timings.total) == (0.011, 0.022, 0.033)


def test_no_corner_yet_leaves_the_critical_step_unset_and_an_edge_failure_is_reported() -> None:
    edge_failure = FitFailure(FailureReason.DEGENERATE_GEOMETRY, "parallel planes", "edge", 0)
    msg = wire.reconstruction_message(
        "s1",
        1,
        status="provisional",
        last_step=10,
        samples_used=11,
        critical_step=None,
        critical_angle=0.3,
        planes=[],
        edge=edge_failure,
        timings=(0.0, 0.0, 0.0),
    )
    assert not msg.HasField("critical_step") and msg.critical_angle == 0.0
    assert not msg.HasField("corner_edge") and list(msg.failures) == [str(edge_failure)]
    with pytest.raises(KeyError):
        wire.reconstruction_message(
            "s1",
            1,
            status="finished",
            last_step=0,
            samples_used=0,
            critical_step=None,
            critical_angle=0.0,
            planes=[],
            edge=None,
            timings=(0.0, 0.0, 0.0),
        )


def test_plane_messages_reuse_a_plane_objects_message_and_make_a_new_planes() -> None:
    cache = wire.PlaneMessages()
    a, b = tilted_fit("a"), tilted_fit("b")
    first = cache.message(a)
    assert cache.message(a) is first  # the same plane object: its message, made once
    assert first == wire.plane_message(a)
    other = tilted_fit("a", method="adaptive")  # a new plane of the same label: its own message
    assert cache.message(other).method == "adaptive"
    assert cache.message(b).label == "b"
    estimate = dict(
        status="provisional",
        last_step=9,
        samples_used=10,
        critical_step=4,
        critical_angle=0.5,
        planes=[other, b],
        edge=None,
        timings=(0.0, 0.0, 0.0),
    )
    msg = wire.reconstruction_message("s1", 3, plane_messages=cache, **estimate)
    plain = wire.reconstruction_message("s1", 3, stamp_ns=msg.stamp_ns, **estimate)
    assert msg == plain
