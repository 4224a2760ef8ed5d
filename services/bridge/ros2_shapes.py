"""The shapes of lelsonar's ROS 2 messages that need no message definitions: the point clouds' row types
(``sensor_msgs/PointField`` datatypes), their rows, and the rotations of the frames."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.reconstruct.estimate.results import PlaneFit

# sensor_msgs/PointField datatypes
POINTFIELD_TYPES = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
RAW_POINT = np.dtype(
    {
        "names": ["x", "y", "z", "step", "capsule"],
        "formats": ["<f4", "<f4", "<f4", "<u4", "<u4"],
        "offsets": [0, 4, 8, 12, 16],
        "itemsize": 20,
    }
)
CORRECTED_POINT = np.dtype(
    {
        "names": ["x", "y", "z", "step", "subset", "inlier"],
        "formats": ["<f4", "<f4", "<f4", "<u4", "u1", "u1"],
        "offsets": [0, 4, 8, 12, 16, 17],
        "itemsize": 20,
    }
)


def quat_x(angle: float) -> tuple[float, float, float, float]:
    return (math.sin(angle / 2), 0.0, 0.0, math.cos(angle / 2))


def quat_from_x_to(v) -> tuple[float, float, float, float]:
    """The shortest rotation taking +x onto the unit vector ``v`` (x, y, z, w)."""
    v = np.asarray(v, dtype=float)
    n = np.linalg.norm(v)
    if not n > 0:
        raise ConfigError("a frame axis must be a non-zero vector")
    v = v / n
    if v[0] < -1 + 1e-12:
        return (0.0, 0.0, 1.0, 0.0)  # 180° about z
    q = np.array([0.0, -v[2], v[1], 1.0 + v[0]])  # axis x × v, w = 1 + cos
    q /= np.linalg.norm(q)
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def corrected_rows(subsets) -> np.ndarray:
    parts = []
    for data, plane in subsets:
        if data is None or data.n == 0:
            continue
        rows = np.zeros(data.n, dtype=CORRECTED_POINT)
        rows["x"], rows["y"], rows["z"] = np.asarray(data.points).T
        rows["step"] = data.step
        rows["subset"] = 0 if data.label == "a" else 1
        mask = plane.inlier_mask if isinstance(plane, PlaneFit) and plane.n_points == data.n else np.ones(data.n, bool)
        rows["inlier"] = np.asarray(mask, dtype=np.uint8)
        parts.append(rows)
    return stack_rows(parts, CORRECTED_POINT)


def stack_rows(parts: Sequence[np.ndarray], dtype: np.dtype) -> np.ndarray:
    """Concatenate structured rows keeping ``dtype``'s padding (np.concatenate would pack it)."""
    out = np.zeros(sum(len(p) for p in parts), dtype=dtype)
    i = 0
    for p in parts:
        out[i : i + len(p)] = p
        i += len(p)
    return out
