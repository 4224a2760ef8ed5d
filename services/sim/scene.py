"""What the simulated scanner looks at: finite planar panels and the corners they form.

World frame as in :mod:`lelsonar.geometry`: x is the rotation axis, the beams
point along +y at γ = 0 and along +z at γ = 90°.  Metres and radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from lelsonar.errors import ConfigError

_UNIT_TOL = 1e-6


def _vec3(value: object, name: str) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} must be three finite numbers, got {value!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class Panel:
    """A finite flat reflector (a rectangle).

    Parameters
    ----------
    center : (3,) floats
        Centre of the rectangle, m.
    normal : (3,) floats
        Unit normal pointing **away** from the scanner (the origin), so the
        panel's plane is ``n·p = offset`` with ``offset > 0``.
    u_axis : (3,) floats
        Unit in-plane direction of ``width``; ``v = normal × u`` is the
        direction of ``height``.
    width, height : float
        Extents along ``u`` and ``v``, m.
    reflectivity : float
        Amplitude reflection coefficient in (0, 1].
    label : str
        Name used in the ground truth ('a', 'b', ...).
    """

    center: tuple[float, float, float]
    normal: tuple[float, float, float]
    u_axis: tuple[float, float, float]
    width: float
    height: float
    reflectivity: float = 0.95
    label: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vec3(self.center, "Panel.center"))
        object.__setattr__(self, "normal", _vec3(self.normal, "Panel.normal"))
        object.__setattr__(self, "u_axis", _vec3(self.u_axis, "Panel.u_axis"))
        n, u = np.array(self.normal), np.array(self.u_axis)
        if abs(np.linalg.norm(n) - 1) > _UNIT_TOL or abs(np.linalg.norm(u) - 1) > _UNIT_TOL:
            raise ConfigError(f"panel {self.label!r}: normal and u_axis must be unit vectors")
        if abs(n @ u) > _UNIT_TOL:
            raise ConfigError(f"panel {self.label!r}: u_axis must lie in the panel (⊥ normal)")
        if not (math.isfinite(self.width) and math.isfinite(self.height) and self.width > 0 and self.height > 0):
            raise ConfigError(f"panel {self.label!r}: width and height must be > 0 m")
        if not (math.isfinite(self.reflectivity) and 0 < self.reflectivity <= 1):
            raise ConfigError(f"panel {self.label!r}: reflectivity must be in (0, 1], got {self.reflectivity}")
        if self.offset <= 0:
            raise ConfigError(
                f"panel {self.label!r}: the normal must point away from the scanner "
                f"(n·center = {self.offset:.3f} m ≤ 0); flip it or move the panel"
            )

    @property
    def offset(self) -> float:
        """``n·p`` of every point of the plane, m (> 0)."""
        return float(np.dot(self.normal, self.center))

    @property
    def v_axis(self) -> np.ndarray:
        """Unit in-plane direction of ``height``: ``normal × u``."""
        return np.cross(self.normal, self.u_axis)

    def corners(self) -> np.ndarray:
        """The four corners, shape (4, 3), in order around the rectangle."""
        c, u, v = np.array(self.center), np.array(self.u_axis), self.v_axis
        hu, hv = self.width / 2, self.height / 2
        return np.stack([c - hu * u - hv * v, c + hu * u - hv * v, c + hu * u + hv * v, c - hu * u + hv * v])

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether in-plane ``points`` (..., 3) lie on the rectangle (within ``tol`` m)."""
        rel = np.asarray(points, dtype=float) - np.array(self.center)
        cu = rel @ np.array(self.u_axis)
        cv = rel @ self.v_axis
        return (np.abs(cu) <= self.width / 2 + tol) & (np.abs(cv) <= self.height / 2 + tol)


@dataclass(frozen=True, eq=False)
class Edge:
    """Where two panels meet: a segment of the intersection of their planes.

    Attributes
    ----------
    panels : (int, int)
        Indices into :attr:`Scene.panels`.
    point : (3,) array
        The point of the edge line closest to the rotation axis' origin, m.
    direction : (3,) array
        Unit direction of the line (x component ≥ 0).
    t_min, t_max : float
        The segment is ``point + t·direction`` for ``t`` in [t_min, t_max].
    opening : float
        Interior angle of the dihedral seen from the scanner, rad (π/2 for a
        right corner).
    """

    panels: tuple[int, int]
    point: np.ndarray
    direction: np.ndarray
    t_min: float
    t_max: float
    opening: float


@dataclass(frozen=True)
class Scene:
    """Panels and the concave corners between them.

    Parameters
    ----------
    panels : tuple of Panel
    corners : tuple of (int, int)
        Pairs of panels that meet at an edge and retro-reflect (double bounce).
        The edge segment is where the intersection line of the two planes lies
        on both rectangles (within 1 cm).
    """

    panels: tuple[Panel, ...]
    corners: tuple[tuple[int, int], ...] = field(default=())

    def __post_init__(self) -> None:
        object.__setattr__(self, "panels", tuple(self.panels))
        object.__setattr__(self, "corners", tuple(tuple(c) for c in self.corners))
        if not 1 <= len(self.panels) <= 32:
            raise ConfigError(f"a scene needs 1 to 32 panels, got {len(self.panels)}")
        if not all(isinstance(p, Panel) for p in self.panels):
            raise ConfigError("Scene.panels must all be Panel instances")
        for pair in self.corners:
            if len(pair) != 2 or not all(isinstance(i, (int, np.integer)) for i in pair):
                raise ConfigError(f"a corner is a pair of panel indices, got {pair!r}")
            i, j = pair
            if i == j or not (0 <= i < len(self.panels) and 0 <= j < len(self.panels)):
                raise ConfigError(f"corner {pair!r} must name two different panels out of {len(self.panels)}")
        _ = self.edges  # validates that every corner really has an edge segment

    @cached_property
    def edges(self) -> tuple[Edge, ...]:
        """Geometry of every corner in :attr:`corners` (same order)."""
        return tuple(_edge(self.panels, i, j) for i, j in self.corners)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def l_corner(
        cls,
        distance_a: float = 1.57,
        distance_b: float = 1.06,
        *,
        tilt_a_x: float = 0.0,
        tilt_a_z: float = 0.0,
        tilt_b_x: float = 0.0,
        tilt_b_y: float = 0.0,
        width: float = 1.2,
        height_a: float = 1.7,
        height_b: float = 2.2,
        reflectivity: tuple[float, float] = (0.95, 0.95),
    ) -> Scene:
        """The paper's L-shaped obstacle (§3), optionally tilted.

        Plane a is ``y = distance_a`` (face-on at γ = 0), plane b is
        ``z = distance_b`` (face-on at γ = 90°); they meet at the edge through
        ``(0, distance_a, distance_b)``, parallel to x when untilted.

        Each tilt turns one plane about an axis through that edge point (right-
        hand rule, rad), so the two panels always share their edge:

        * ``tilt_a_x`` / ``tilt_b_x``: about x.  Equal values roll the whole L
          (still 90°); ``tilt_a_x − tilt_b_x`` opens the corner to
          ``90° + tilt_a_x − tilt_b_x``.
        * ``tilt_a_z``: plane a about z; ``tilt_b_y``: plane b about y.  These
          skew the edge away from x, keeping 90° if the other plane is untilted.

        Plane a extends ``height_a`` from the edge towards −z, plane b
        ``height_b`` towards −y, both ``width`` along the edge, centred on x = 0.
        The defaults cover every beam of a [-10°, 110°] scan.
        """
        for name, value in (
            ("distance_a", distance_a),
            ("distance_b", distance_b),
            ("width", width),
            ("height_a", height_a),
            ("height_b", height_b),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"Scene.l_corner: {name} must be > 0 m, got {value!r}")
        for name, value in (
            ("tilt_a_x", tilt_a_x),
            ("tilt_a_z", tilt_a_z),
            ("tilt_b_x", tilt_b_x),
            ("tilt_b_y", tilt_b_y),
        ):
            if not (math.isfinite(value) and abs(value) <= math.radians(30)):
                raise ConfigError(f"Scene.l_corner: {name} must be within ±30° (rad), got {value!r}")
        apex = np.array([0.0, distance_a, distance_b])
        n_a = _rot_z(tilt_a_z) @ _rot_x(tilt_a_x) @ np.array([0.0, 1.0, 0.0])
        n_b = _rot_y(tilt_b_y) @ _rot_x(tilt_b_x) @ np.array([0.0, 0.0, 1.0])
        e = np.cross(n_a, n_b)
        e /= np.linalg.norm(e)
        if e[0] < 0:
            e = -e
        # Each panel runs from the shared edge away from the other plane.
        v_a = np.cross(n_a, e)
        v_a *= -np.sign(v_a @ n_b)
        v_b = np.cross(n_b, e)
        v_b *= -np.sign(v_b @ n_a)
        panels = []
        for label, n, v, h, refl in (
            ("a", n_a, v_a, height_a, reflectivity[0]),
            ("b", n_b, v_b, height_b, reflectivity[1]),
        ):
            center = apex + v * h / 2
            # Panel's own (u, v): u along the edge; Panel derives v = n × u, so pick u's sign to match.
            u = e if np.cross(n, e) @ v > 0 else -e
            panels.append(
                Panel(
                    center=_vec3(center, "center"),
                    normal=_vec3(n, "normal"),
                    u_axis=_vec3(u, "u_axis"),
                    width=width,
                    height=h,
                    reflectivity=float(refl),
                    label=label,
                )
            )
        return cls(panels=tuple(panels), corners=((0, 1),))

    @classmethod
    def wall(cls, distance: float, *, size: float = 3.0, reflectivity: float = 0.95, label: str = "a") -> Scene:
        """One square wall ``y = distance`` facing the array at γ = 0 (for calibration)."""
        if not (math.isfinite(distance) and distance > 0):
            raise ConfigError(f"Scene.wall: distance must be > 0 m, got {distance!r}")
        return cls(
            panels=(
                Panel(
                    center=(0.0, distance, 0.0),
                    normal=(0.0, 1.0, 0.0),
                    u_axis=(1.0, 0.0, 0.0),
                    width=size,
                    height=size,
                    reflectivity=reflectivity,
                    label=label,
                ),
            )
        )

    # ------------------------------------------------------------------ ground truth
    def critical_angle(self, corner: int = 0) -> float:
        """γ at which the boresight points at an edge: ``atan2(z, y)`` of its point nearest x = 0, rad.

        The capsules sit on the boresight line through the axis, so this holds
        for any radial offset.  NaN if the scene has no such corner.
        """
        if not 0 <= corner < len(self.edges):
            return math.nan
        edge = self.edges[corner]
        if abs(edge.direction[0]) > 1e-12:
            p = edge.point - edge.direction * (edge.point[0] / edge.direction[0])
        else:
            p = edge.point
        return math.atan2(p[2], p[1])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _edge(panels: tuple[Panel, ...], i: int, j: int, tol: float = 0.01) -> Edge:
    """Intersect the planes of panels ``i`` and ``j`` and clip the line to both rectangles."""
    pa, pb = panels[i], panels[j]
    na, nb = np.array(pa.normal), np.array(pb.normal)
    d = np.cross(na, nb)
    norm = np.linalg.norm(d)
    if norm < 1e-6:
        raise ConfigError(f"corner ({i}, {j}): panels {pa.label!r} and {pb.label!r} are parallel")
    d /= norm
    if d[0] < 0 or (d[0] == 0 and (d[1] < 0 or (d[1] == 0 and d[2] < 0))):
        d = -d
    # Point on both planes closest to the origin (minimum-norm solution).
    a = np.stack([na, nb])
    point, *_ = np.linalg.lstsq(a, np.array([pa.offset, pb.offset]), rcond=None)
    lo, hi = -np.inf, np.inf
    for p in (pa, pb):
        c, u, v = np.array(p.center), np.array(p.u_axis), p.v_axis
        for axis, half in ((u, p.width / 2 + tol), (v, p.height / 2 + tol)):
            # |(point + t·d − c)·axis| ≤ half is a slab in t.
            c0, c1 = (point - c) @ axis, d @ axis
            if abs(c1) < 1e-12:
                if abs(c0) > half:
                    lo, hi = np.inf, -np.inf
                continue
            t1, t2 = sorted(((-half - c0) / c1, (half - c0) / c1))
            lo, hi = max(lo, t1), min(hi, t2)
    if not lo < hi:
        raise ConfigError(
            f"corner ({i}, {j}): panels {pa.label!r} and {pb.label!r} do not meet "
            "(their planes' intersection misses one of the rectangles)"
        )
    # Interior angle of the wedge containing the scanner: both normals point out of it.
    opening = math.pi - math.acos(float(np.clip(na @ nb, -1.0, 1.0)))
    return Edge(panels=(i, j), point=point, direction=d, t_min=float(lo), t_max=float(hi), opening=opening)
