"""The map as fusion leaves it: walls with their σ and verdict, corners, edges and corrected poses (world frame).

:func:`map_to_dict` turns it into the public JSON of ``lelsonar map --json``: the keys ``walls`` (``normal``,
``offset``, ``extent``, ``quality``, ``normal_stderr``, ``offset_stderr``), ``corners`` (``point``,
``direction``, ``kind``), ``edges`` (``point``, ``direction``) and ``poses`` (``scan_id``, ``x``, ``y``,
``z``, ``heading``) are an interface: keep them.  SI units (m, rad).

``corners`` and ``edges`` are those of the floor plan (vertical lines: where walls meet, or a wall ends);
where a wall meets the floor or the ceiling is a line across the plan, listed apart (``horizontal_corners``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lelsonar.map.lines import segment


@dataclass(frozen=True, eq=False)
class FusedWall:
    """One wall of the map.

    Attributes
    ----------
    id : int
        Stable over the map's life.
    line : array of 2
        ``(θ, ρ)``, world frame: the vertical plane ``cos θ x + sin θ y = ρ``.
    covariance : (2, 2) array
        Covariance of ``(θ, ρ)`` (GTSAM marginal, or first order for a flagged wall outside the graph).
    interval : (float, float)
        The observed stretch along the line's tangent ``(−sin θ, cos θ)``, from its foot ``ρ n``, m: from the
        first observed point to the last.
    pieces : tuple of (float, float)
        The stretches actually observed, in the same coordinate, in order; between them the scans saw no
        wall (and no opening either).
    z_range : (float, float)
        The observed heights, m.
    quality : str
        ``good``, ``degraded`` or ``unreliable``.
    reasons : tuple of str
        Why it is not ``good``.
    scans : tuple of int
        The scans that saw it (good observations first).
    good_observations, flagged_observations : int
        How many observations of each kind it holds.
    piece_scans : tuple of tuple of int
        The scans that saw each piece (empty when not known, as for a map received without them).
    """

    id: int
    line: np.ndarray
    covariance: np.ndarray
    interval: tuple[float, float]
    pieces: tuple[tuple[float, float], ...]
    z_range: tuple[float, float]
    quality: str
    reasons: tuple[str, ...]
    scans: tuple[int, ...]
    good_observations: int
    flagged_observations: int
    piece_scans: tuple[tuple[int, ...], ...] = ()

    @property
    def normal(self) -> np.ndarray:
        return np.array([math.cos(self.line[0]), math.sin(self.line[0]), 0.0])

    @property
    def offset(self) -> float:
        return float(self.line[1])

    @property
    def normal_stderr(self) -> float:
        return math.sqrt(max(float(self.covariance[0, 0]), 0.0))

    @property
    def offset_stderr(self) -> float:
        return math.sqrt(max(float(self.covariance[1, 1]), 0.0))

    @property
    def segment(self) -> np.ndarray:
        """End points (2, 2) of the observed stretch on the floor plane."""
        return segment(self.line, self.interval)

    @property
    def piece_segments(self) -> list[np.ndarray]:
        """End points (2, 2) of each observed piece on the floor plane."""
        return [segment(self.line, p) for p in self.pieces]

    def extent(self, piece: int | None = None) -> np.ndarray:
        """The observed patch's corners (k, 3): a rectangle, or the two end points when no height was seen; of
        the whole observed stretch, or of one of its ``pieces``."""
        (x0, y0), (x1, y1) = self.segment if piece is None else self.piece_segments[piece]
        lo, hi = self.z_range
        if hi - lo < 1e-9:
            return np.array([[x0, y0, lo], [x1, y1, lo]])
        return np.array([[x0, y0, lo], [x1, y1, lo], [x1, y1, hi], [x0, y0, hi]])


@dataclass(frozen=True, eq=False)
class FusedFeature:
    """A corner or an edge of the map: a line (a vertical line for a corner of two walls), world frame."""

    point: np.ndarray
    direction: np.ndarray
    kind: str  # "concave", "convex" or "edge"
    point_stderr: float
    source: str  # "walls" (where two fused walls meet) or "observed" (from the scans' own corners and edges)
    observations: int
    walls: tuple[int, ...] = ()
    scans: tuple[int, ...] = ()  # the scans whose own corners or edges it holds


@dataclass(frozen=True, eq=False)
class FusedPose:
    """A scan's pose after fusion, with its marginal σ and the odometry it started from."""

    scan_id: int
    x: float
    y: float
    z: float
    heading: float
    covariance: np.ndarray  # (3, 3) over (x, y, heading), body-frame tangent of GTSAM's Pose2
    odometry: tuple[float, float, float]


@dataclass(frozen=True, eq=False)
class FusedMap:
    """Everything the map holds, world frame."""

    walls: tuple[FusedWall, ...]
    features: tuple[FusedFeature, ...]
    poses: tuple[FusedPose, ...]
    notes: tuple[str, ...] = field(default=())
    #: Where the scans saw free space: for each wall observation, the polygon (k, 2) from its scanner to
    #: the patch the echoes came from, world frame.
    views: tuple[np.ndarray, ...] = field(default=())
    #: The scan of each view.
    view_scans: tuple[int, ...] = field(default=())
    #: Corners that are lines across the floor plan, not corners of it: where a wall meets the floor or the
    #: ceiling (seen by two scans).
    horizontal: tuple[FusedFeature, ...] = field(default=())

    @property
    def corners(self) -> tuple[FusedFeature, ...]:
        return tuple(f for f in self.features if f.kind != "edge")

    @property
    def edges(self) -> tuple[FusedFeature, ...]:
        return tuple(f for f in self.features if f.kind == "edge")


def _xyz(v) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _wall_entries(w: FusedWall, first_id: int) -> list[dict]:
    """One JSON wall for each observed piece of ``w``: its ``extent`` covers that piece only (never the opening
    or the unseen stretch between two pieces); the pieces of one line share ``wall_id``, the line, its σ and
    its verdict."""
    pieces = [[_xyz((*p, w.z_range[0])) for p in seg] for seg in w.piece_segments]
    out = []
    for k in range(len(w.pieces)):
        scans = w.piece_scans[k] if len(w.piece_scans) == len(w.pieces) else w.scans
        out.append(
            {
                "id": first_id + k,
                "wall_id": w.id,
                "piece": k,
                "normal": _xyz(w.normal),
                "offset": w.offset,
                "extent": [_xyz(p) for p in w.extent(k)],
                "quality": w.quality,
                "normal_stderr": w.normal_stderr,
                "offset_stderr": w.offset_stderr,
                "reasons": list(w.reasons),
                "scans": list(scans),
                "wall_scans": list(w.scans),
                "observations": {"good": w.good_observations, "flagged": w.flagged_observations},
                "pieces": pieces,
            }
        )
    return out


def map_to_dict(m: FusedMap) -> dict:
    """The public JSON object of the map (see the module docstring for the keys that are an interface).

    A wall whose observed stretch has gaps (:attr:`FusedWall.pieces`) is one entry a piece: a planner takes each
    entry's ``extent`` as an obstacle, and a wall's extent spanning an opening would close it.  The entries of
    one fused wall share ``wall_id`` (and list every piece of the line in ``pieces``); ``id`` is unique in the
    map; ``scans`` are the scans that saw that piece, ``wall_scans`` those that saw the line.
    """
    walls: list[dict] = []
    for w in m.walls:
        walls.extend(_wall_entries(w, len(walls)))

    def feature(f: FusedFeature, with_kind: bool) -> dict:
        out: dict = {"point": _xyz(f.point), "direction": _xyz(f.direction)}
        if with_kind:
            out["kind"] = f.kind
        out.update(point_stderr=f.point_stderr, source=f.source, observations=f.observations, walls=list(f.walls))
        return out

    poses = [
        {
            "scan_id": p.scan_id,
            "x": p.x,
            "y": p.y,
            "z": p.z,
            "heading": p.heading,
            "x_stderr": math.sqrt(max(float(p.covariance[0, 0]), 0.0)),
            "y_stderr": math.sqrt(max(float(p.covariance[1, 1]), 0.0)),
            "heading_stderr": math.sqrt(max(float(p.covariance[2, 2]), 0.0)),
            "odometry": {"x": p.odometry[0], "y": p.odometry[1], "heading": p.odometry[2]},
        }
        for p in m.poses
    ]
    return {
        "walls": walls,
        "corners": [feature(f, True) for f in m.corners],
        "edges": [feature(f, False) for f in m.edges],
        "horizontal_corners": [feature(f, True) for f in m.horizontal],
        "poses": poses,
        "notes": list(m.notes),
    }
