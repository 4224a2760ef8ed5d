"""The floor plan a planner uses: wall segments, the free space (shapely, GeoJSON), an occupancy grid shaped
like ROS 2's ``nav_msgs/OccupancyGrid``, wall markers, and a route (networkx) that keeps the robot's radius
from every wall.

Every wall is an obstacle here, flagged ones included: a wall the map cannot vouch for may still be there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import networkx as nx
import numpy as np
import shapely
from shapely.geometry import LineString, MultiLineString, Point, Polygon, mapping
from shapely.ops import unary_union

from lelsonar.errors import ConfigError
from lelsonar.map.lines import foot, segment, tangent
from lelsonar.map.result import FusedMap, FusedWall

#: Colours of the verdicts (RGBA, 0..1) for the wall markers.
QUALITY_COLOURS = {"good": (0.2, 0.8, 0.3, 1.0), "degraded": (1.0, 0.7, 0.1, 1.0), "unreliable": (0.9, 0.2, 0.2, 1.0)}

#: A corner or edge within this of a wall's observed piece, m, is not where the wall ends (see :func:`likely_walls`).
ON_PIECE = 0.1

#: A view ends on a wall when the middle of its far side is this near one of the wall's pieces, m.
VIEW_ON_WALL = 0.05

#: The space seen free crosses a wall's stretch when it reaches this far beyond it on both sides, m.
THROUGH = 0.1

#: OccupancyGrid cell values.
UNKNOWN, FREE, OCCUPIED = -1, 0, 100


@dataclass(frozen=True)
class PlanConfig:
    """The floor plan's geometry.

    Parameters
    ----------
    robot_radius : float
        The route keeps at least this from every wall, m.
    resolution : float
        Grid cell size, m.
    unknown_cost : float
        A move through space no scan saw free costs this many times a move through seen free space
        (the way out of a maze leads through space not yet seen; a wall not yet seen may stand there).
    margin : float
        The grid reaches this beyond the walls (room to leave the map), m.
    likely_wall_cost : float
        A move through unseen space where a wall likely runs (:func:`likely_walls`) costs this many times a
        move through seen free space: passable, where nothing else is, but never the easy way out.
    likely_wall_reach : float
        How far, m, a wall's end piece is taken to continue towards a corner or an edge on its line.
    likely_wall_span : float
        How far, m, it is taken to continue where no corner or edge is in reach.
    """

    robot_radius: float = 0.15
    resolution: float = 0.05
    unknown_cost: float = 10.0
    margin: float = 1.0
    likely_wall_cost: float = 100.0
    likely_wall_reach: float = 2.0
    likely_wall_span: float = 0.5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.unknown_cost) and self.unknown_cost >= 1):
            raise ConfigError(f"plan unknown_cost must be ≥ 1, got {self.unknown_cost!r}")
        if not (math.isfinite(self.likely_wall_cost) and self.likely_wall_cost >= self.unknown_cost):
            raise ConfigError(f"plan likely_wall_cost must be ≥ unknown_cost, got {self.likely_wall_cost!r}")
        for name in ("robot_radius", "margin", "likely_wall_reach", "likely_wall_span"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"plan {name} must be ≥ 0 m, got {v!r}")
        if not (math.isfinite(self.resolution) and 0.005 <= self.resolution <= 1.0):
            raise ConfigError(f"plan resolution must be 0.005–1 m, got {self.resolution!r}")


def wall_segments(m: FusedMap) -> list[LineString]:
    """Every observed piece of every wall, on the floor plane."""
    return [LineString(s) for w in m.walls for s in w.piece_segments]


def _segment_array(m: FusedMap) -> np.ndarray:
    return np.array([s for w in m.walls for s in w.piece_segments]).reshape(-1, 2, 2)


def trusted_views(m: FusedMap) -> list[np.ndarray]:
    """The views (echo paths) that end on a piece of a wall of good or degraded verdict.

    An unreliable wall may be no wall at all: an echo that came back off two walls (a corner) or round a
    wall's end reads as a wall farther than any, and its straight path from the scanner crosses the walls
    between.  Its view is no evidence of free space.
    """
    segments = np.array([s for w in m.walls if w.quality != "unreliable" for s in w.piece_segments]).reshape(-1, 2, 2)
    if not len(segments) or not m.views:
        return []
    keep = [v for v in m.views if len(v) >= 3]
    if not keep:
        return []
    ends = np.array([np.asarray(v)[1:].mean(axis=0) for v in keep])
    near = _distance_to_segments(ends[:, 0], ends[:, 1], segments) <= VIEW_ON_WALL
    return [v for v, ok in zip(keep, near.tolist()) if ok]


def _seen(m: FusedMap, cfg: PlanConfig):
    """The union of the trusted views and the robot's own way (see :func:`free_space`), walls not taken out."""
    parts = [Polygon(v) for v in trusted_views(m)]
    xy = [(p.x, p.y) for p in m.poses]
    if len(xy) == 1:
        parts.append(Point(xy[0]).buffer(cfg.robot_radius))
    elif xy:
        parts.append(LineString(xy).buffer(cfg.robot_radius))
    return unary_union([p.buffer(0) for p in parts]) if parts else Polygon()


def free_space(m: FusedMap, config: PlanConfig | None = None) -> Polygon | shapely.MultiPolygon:
    """The space the scans saw free: each echo's path from the scanner to the patch it came from on a wall
    that is not unreliable (:func:`trusted_views`), and the robot's own way between consecutive poses, less
    the walls.

    Nothing else is taken as free: a wall the scans never saw leaves unknown space, not free space.  Not
    shrunk by the robot: see :func:`reachable`.
    """
    cfg = config or PlanConfig()
    walls = unary_union(wall_segments(m)).buffer(cfg.resolution / 2) if m.walls else Polygon()
    return _seen(m, cfg).difference(walls)


def reachable(m: FusedMap, config: PlanConfig | None = None):
    """Where the robot's centre may go: the free space shrunk by its radius."""
    cfg = config or PlanConfig()
    return free_space(m, cfg).buffer(-cfg.robot_radius)


def to_geojson(m: FusedMap, config: PlanConfig | None = None) -> dict:
    """A GeoJSON FeatureCollection (metres in the map frame, not degrees): walls, free space, poses, route-free."""
    cfg = config or PlanConfig()
    features = [
        {
            "type": "Feature",
            "geometry": mapping(MultiLineString(w.piece_segments)),
            "properties": {
                "kind": "wall",
                "id": w.id,
                "quality": w.quality,
                "normal_stderr": w.normal_stderr,
                "offset_stderr": w.offset_stderr,
            },
        }
        for w in m.walls
    ]
    space = free_space(m, cfg)
    if not space.is_empty:
        features.append({"type": "Feature", "geometry": mapping(space), "properties": {"kind": "free_space"}})
    features += [
        {"type": "Feature", "geometry": mapping(Point(p.x, p.y)), "properties": {"kind": "pose", "scan_id": p.scan_id}}
        for p in m.poses
    ]
    return {"type": "FeatureCollection", "features": features}


@dataclass(frozen=True)
class Grid:
    """An occupancy grid shaped like ``nav_msgs/OccupancyGrid``: row-major from ``origin``, x along rows."""

    resolution: float
    width: int
    height: int
    origin: tuple[float, float]
    data: np.ndarray  # (height, width) int8: −1 unknown, 0 free, 100 occupied

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """The x and y of every cell's centre, each (height, width)."""
        xs = self.origin[0] + (np.arange(self.width) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(self.height) + 0.5) * self.resolution
        return np.meshgrid(xs, ys)

    def cell(self, x: float, y: float) -> tuple[int, int]:
        """``(row, column)`` of a point."""
        return int((y - self.origin[1]) // self.resolution), int((x - self.origin[0]) // self.resolution)

    def to_message(self, frame_id: str = "map") -> dict:
        """The fields of ``nav_msgs/OccupancyGrid`` (for the ROS 2 bridge and the bag export)."""
        return {
            "header": {"frame_id": frame_id},
            "info": {
                "resolution": self.resolution,
                "width": self.width,
                "height": self.height,
                "origin": {
                    "position": {"x": self.origin[0], "y": self.origin[1], "z": 0.0},
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                },
            },
            "data": self.data.astype(np.int8).ravel().tolist(),
        }


def _unseen_through(m: FusedMap, cfg: PlanConfig, stretches: list[np.ndarray], *, views: bool) -> np.ndarray:
    """The stretches (n, 2, 2) that the space seen free (``views`` False: the robot's own way alone) does not
    cross.

    Crossing means reaching :data:`THROUGH` beyond the stretch on both sides: an echo's path that ends on the
    wall itself touches its line but saw nothing beyond it.
    """
    if not stretches:
        return np.zeros((0, 2, 2))
    space = _seen(m, cfg) if views else _seen(replace(m, views=(), view_scans=()), cfg)
    out = []
    for s in stretches:
        d = s[1] - s[0]
        n = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-12)
        if not all(space.intersects(LineString(s + side * THROUGH * n)) for side in (1.0, -1.0)):
            out.append(s)
    return np.array(out).reshape(-1, 2, 2)


def closed_gaps(m: FusedMap, config: PlanConfig | None = None) -> np.ndarray:
    """Stretches (n, 2, 2) of a wall's line that no scan saw but a route never crosses.

    * A gap between two observed pieces of one wall: scans saw the wall on both sides and its hull (the
      wall's ``extent``) spans it; an opening there was never seen open.
    * The stretch from an end piece to the corner or edge of the map that ends the wall on its line
      (:func:`likely_walls`): the corner says the wall runs on to it.

    A gap that the space seen free crosses (an echo's path through it to a wall beyond, or the robot's own
    way) is an opening the scans saw: not closed, though no more than that is seen free.  A stretch on to a
    corner is opened by the robot's own way alone: an echo's path is drawn from the scanner to the ends of the
    patch it came from, and a patch read longer than its wall reaches past the corner.  Only walls of good
    evidence close anything: a flagged wall's line may be degrees off, or be no wall at all.
    """
    cfg = config or PlanConfig()
    gaps: list[np.ndarray] = []
    for w in m.walls:
        if w.quality == "unreliable" or w.good_observations == 0:
            continue
        pieces = sorted(w.pieces)
        gaps += [segment(w.line, (hi, lo)) for (_, hi), (lo, _) in zip(pieces, pieces[1:]) if lo > hi]
    ends = [s for s, ended, w in _continuations(m, cfg) if ended and w.good_observations > 0]
    return np.concatenate(
        [_unseen_through(m, cfg, gaps, views=True), _unseen_through(m, cfg, ends, views=False)]
    ).reshape(-1, 2, 2)


def likely_walls(m: FusedMap, config: PlanConfig | None = None) -> np.ndarray:
    """Unseen stretches (n, 2, 2) where a wall likely runs on beyond its observed pieces.

    Sonar sees a wall only near the foot of its perpendicular: a wall's pieces are centimetres long, and the
    space up to where the wall ends stays unseen.  A wall usually goes on there (a doorway may not), so for
    each wall of good or degraded verdict (an unreliable one may be no wall at all): from each end piece
    along its line to the nearest corner or edge of the map on that line (where it meets another wall, or
    ends), at most ``likely_wall_reach`` away; without one, ``likely_wall_span``.  The gaps between its
    pieces, and the stretches that reach a corner or an edge, are also :func:`closed_gaps`.
    """
    return np.array([s for s, _, _ in _continuations(m, config or PlanConfig())]).reshape(-1, 2, 2)


def _continuations(m: FusedMap, cfg: PlanConfig) -> list[tuple[np.ndarray, bool, FusedWall]]:
    """:func:`likely_walls`' stretches, each with whether a corner or an edge ends it, and its wall."""
    out: list[tuple[np.ndarray, bool, FusedWall]] = []
    # Vertical ones only: a wall's foot on the floor is a corner too, but it ends nothing along the wall.
    features = [f for f in (*m.corners, *m.edges) if abs(float(f.direction[2])) >= math.cos(math.radians(30.0))]
    for w in m.walls:
        if w.quality == "unreliable":
            continue
        pieces = sorted(w.pieces)
        n, t = w.normal[:2], tangent(float(w.line[0]))
        lo, hi = pieces[0][0], pieces[-1][1]
        ahead, behind = [], []
        for f in features:
            across = abs(float(n @ f.point[:2]) - w.offset)
            if across > 0.05 + 3.0 * math.hypot(f.point_stderr, w.offset_stderr):
                continue
            s_f = float((f.point[:2] - foot(w.line)) @ t)
            # A feature on the observed piece itself is the piece's own echo read as a corner: it ends nothing.
            if hi + ON_PIECE < s_f <= hi + cfg.likely_wall_reach:
                ahead.append(s_f)
            elif lo - cfg.likely_wall_reach <= s_f < lo - ON_PIECE:
                behind.append(s_f)
        end = min(ahead) if ahead else hi + cfg.likely_wall_span
        start = max(behind) if behind else lo - cfg.likely_wall_span
        out.append((segment(w.line, (hi, end)), bool(ahead), w))
        out.append((segment(w.line, (start, lo)), bool(behind), w))
    return out


def _distance_to_segments(x: np.ndarray, y: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """The distance from each point to the nearest segment ``(n, 2, 2)``."""
    best = np.full(x.shape, np.inf)
    for (ax, ay), (bx, by) in segments:
        dx, dy = bx - ax, by - ay
        length2 = dx * dx + dy * dy or 1e-18
        t = np.clip(((x - ax) * dx + (y - ay) * dy) / length2, 0.0, 1.0)
        np.minimum(best, np.hypot(x - (ax + t * dx), y - (ay + t * dy)), out=best)
    return best


def occupancy_grid(m: FusedMap, config: PlanConfig | None = None) -> Grid:
    """Occupied where a wall runs (within half a cell), free inside :func:`free_space`, unknown elsewhere."""
    cfg = config or PlanConfig()
    segments = _segment_array(m)
    pts = np.concatenate([segments.reshape(-1, 2), np.array([[p.x, p.y] for p in m.poses]).reshape(-1, 2)])
    if len(pts) == 0:
        pts = np.zeros((1, 2))
    lo = pts.min(axis=0) - cfg.margin
    hi = pts.max(axis=0) + cfg.margin
    width, height = (int(math.ceil(v)) for v in (hi - lo) / cfg.resolution)
    grid = Grid(cfg.resolution, width, height, (float(lo[0]), float(lo[1])), np.full((height, width), UNKNOWN, np.int8))
    x, y = grid.centres()
    space = free_space(m, cfg)
    if not space.is_empty:
        grid.data[shapely.contains_xy(space, x, y)] = FREE
    if len(segments):
        grid.data[_distance_to_segments(x, y, segments) <= cfg.resolution / 2] = OCCUPIED
    return grid


def wall_markers(m: FusedMap, frame_id: str = "map", thickness_sigmas: float = 2.0) -> list[dict]:
    """Each observed piece of each wall as the fields of a ``visualization_msgs/Marker`` CUBE: its stretch,
    its height, a thickness of ``thickness_sigmas`` × its offset σ (at least 1 cm), coloured by verdict;
    the marker's text names the wall."""
    out: list[dict] = []
    for w in m.walls:
        z0, z1 = w.z_range
        r, g, bl, alpha = QUALITY_COLOURS[w.quality]
        for a, b in w.piece_segments:
            mid = 0.5 * (a + b)
            yaw = math.atan2(b[1] - a[1], b[0] - a[0])
            out.append(
                {
                    "header": {"frame_id": frame_id},
                    "ns": "walls",
                    "id": len(out),
                    "type": 1,  # CUBE
                    "action": 0,  # ADD
                    "pose": {
                        "position": {"x": float(mid[0]), "y": float(mid[1]), "z": 0.5 * (z0 + z1)},
                        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
                    },
                    "scale": {
                        "x": max(0.01, float(np.hypot(*(b - a)))),
                        "y": max(0.01, thickness_sigmas * w.offset_stderr),
                        "z": max(0.01, z1 - z0),
                    },
                    "color": {"r": r, "g": g, "b": bl, "a": alpha},
                    "text": f"wall {w.id}: {w.quality}",
                }
            )
    return out


def route(
    m: FusedMap,
    start: tuple[float, float],
    goal: tuple[float, float] | None = None,
    config: PlanConfig | None = None,
    *,
    through_closed_gaps: bool = False,
) -> list[tuple[float, float]] | None:
    """The shortest route over the grid from ``start`` to ``goal``, or out of the map when ``goal`` is None.

    A move costs its length, times ``unknown_cost`` through space no scan saw free, and times
    ``likely_wall_cost`` across where a wall likely runs on unseen (:func:`likely_walls`).
    A cell is open when its centre is farther than the robot's radius plus half a cell's diagonal from
    every observed piece of every wall, whatever its verdict, and from every gap between the pieces of one
    wall that no scan saw through (:func:`closed_gaps`; ``through_closed_gaps`` opens them, to tell why
    there is no route), so the straight moves between open cells keep the radius.  Moves go to the 8
    neighbours.  "Out of the map" is any open cell on the grid's border (the grid reaches ``margin`` beyond
    the walls).

    Returns
    -------
    list of (x, y) or None
        The route's turning points from ``start`` to the end, m; None when there is none.
    """
    cfg = config or PlanConfig()
    grid = occupancy_grid(m, cfg)
    x, y = grid.centres()
    segments = _segment_array(m)
    if not through_closed_gaps:
        segments = np.concatenate([segments, closed_gaps(m, cfg)])
    clearance = cfg.robot_radius + cfg.resolution * math.sqrt(2) / 2
    open_ = _distance_to_segments(x, y, segments) > clearance if len(segments) else np.ones(x.shape, bool)
    rows, cols = open_.shape
    cost = np.where(grid.data == FREE, 1.0, cfg.unknown_cost)
    likely = likely_walls(m, cfg)
    if len(likely):
        near = _distance_to_segments(x, y, likely) <= clearance
        cost = np.where(near & (grid.data != FREE), cfg.likely_wall_cost, cost)

    def index(r: int, c: int) -> int:
        return r * cols + c

    g = nx.Graph()
    rr, cc = np.nonzero(open_)
    g.add_nodes_from(index(r, c) for r, c in zip(rr.tolist(), cc.tolist()))
    for dr, dc, w in ((0, 1, 1.0), (1, 0, 1.0), (1, 1, math.sqrt(2)), (1, -1, math.sqrt(2))):
        r2, c2 = rr + dr, cc + dc
        ok = (r2 >= 0) & (r2 < rows) & (c2 >= 0) & (c2 < cols)
        ok[ok] &= open_[r2[ok], c2[ok]]
        a, b, c, d = rr[ok], cc[ok], r2[ok], c2[ok]
        weight = w * 0.5 * (cost[a, b] + cost[c, d])
        g.add_weighted_edges_from(zip((a * cols + b).tolist(), (c * cols + d).tolist(), weight.tolist()))
    s = grid.cell(*start)
    if not (0 <= s[0] < rows and 0 <= s[1] < cols) or not open_[s]:
        return None
    if goal is None:
        target = -1
        border = [index(r, c) for r, c in zip(rr.tolist(), cc.tolist()) if r in (0, rows - 1) or c in (0, cols - 1)]
        g.add_weighted_edges_from((b, target, 0.0) for b in border)
    else:
        t = grid.cell(*goal)
        if not (0 <= t[0] < rows and 0 <= t[1] < cols) or not open_[t]:
            return None
        target = index(*t)
    try:
        path = nx.shortest_path(g, index(*s), target, weight="weight")
    except nx.NetworkXNoPath:
        return None
    cells = [divmod(n, cols) for n in path if n != -1]
    points = [(float(x[r, c]), float(y[r, c])) for r, c in cells]
    # The exact start and goal replace their cells' centres: each lies within half a cell's diagonal of
    # its open centre, so the last and first moves keep the radius too.
    end = points[1:] if goal is None else points[1:-1] + [(float(goal[0]), float(goal[1]))]
    return _turning_points([(float(start[0]), float(start[1]))] + end)


def unseen_length(m: FusedMap, path: list[tuple[float, float]], config: PlanConfig | None = None) -> float:
    """How much of a route (m) runs through space no scan saw free: there a wall the scans missed may stand."""
    if len(path) < 2:
        return 0.0
    return float(LineString(path).difference(free_space(m, config)).length)


def frontier(
    m: FusedMap, path: list[tuple[float, float]], config: PlanConfig | None = None
) -> tuple[float, float] | None:
    """Where a route leaves the free space the scans saw for the last time (the frontier to explore), or None
    when it ends inside it.

    Shorter stretches outside it before that (a corner cut between two echo paths) are in :func:`unseen_length`.
    """
    if len(path) < 2:
        return None
    line = LineString(path)
    outside = line.difference(free_space(m, config))
    if outside.is_empty or outside.length <= 1e-9:
        return None
    pieces = [g for g in getattr(outside, "geoms", [outside]) if g.length > 1e-9]
    last = max(pieces, key=lambda g: line.project(Point(g.coords[0])))
    if line.length - line.project(Point(last.coords[-1])) > 1e-6:
        return None  # back inside the space seen free at its end
    x, y = last.coords[0]
    return float(x), float(y)


def _turning_points(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The route without the points where it goes straight on."""
    if len(points) < 3:
        return points
    out = [points[0]]
    for a, b, c in zip(points, points[1:], points[2:]):
        if abs((b[0] - a[0]) * (c[1] - b[1]) - (b[1] - a[1]) * (c[0] - b[0])) > 1e-12:
            out.append(b)
    out.append(points[-1])
    return out


@dataclass(frozen=True)
class RouteSummary:
    """What a route runs through and what it relies on.

    Attributes
    ----------
    length : float
        m.
    unseen : float
        How much of it (m) runs through space no scan saw free (:func:`unseen_length`).
    frontier : (float, float) or None
        Where it first leaves the space seen free (:func:`frontier`).
    clearance : float
        Its closest approach to an observed wall piece, m (infinite with no wall).
    nearest_wall : int
        The id of that wall (−1 with none).
    beside : dict of str to int
        The walls with a piece within ``reach`` of it, by verdict: the walls it relies on.
    """

    length: float
    unseen: float
    frontier: tuple[float, float] | None
    clearance: float
    nearest_wall: int
    beside: dict[str, int]


def summarise_route(
    m: FusedMap, path: list[tuple[float, float]], config: PlanConfig | None = None, reach: float = 0.5
) -> RouteSummary:
    """The route's length, how much of it runs through unseen space, and the walls beside it (see
    :class:`RouteSummary`)."""
    cfg = config or PlanConfig()
    line = LineString(path) if len(path) >= 2 else Point(path[0])
    clearance, nearest = math.inf, -1
    beside = {q: 0 for q in QUALITY_COLOURS}
    for w in m.walls:
        d = min(line.distance(LineString(s)) for s in w.piece_segments)
        if d < clearance:
            clearance, nearest = d, w.id
        if d <= reach:
            beside[w.quality] += 1
    return RouteSummary(
        length=float(line.length),
        unseen=unseen_length(m, path, cfg),
        frontier=frontier(m, path, cfg),
        clearance=float(clearance),
        nearest_wall=nearest,
        beside=beside,
    )
