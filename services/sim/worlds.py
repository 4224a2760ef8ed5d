"""Seeded families of worlds for tests and benchmarks: rooms, L-rooms, corridors with doorways, mazes, boxes.

Each draw is a valid world file's content (it goes through :func:`parse_world`,
so every check a user's file gets applies) turned by a random angle and
shifted, so nothing downstream can lean on walls along the axes.  Drawn broadly:
the project is judged on worlds it never sees.

=============  =================================================================
family         what is drawn
=============  =================================================================
``room``       a rectangle 2.5–6 m × 2.5–5 m, ceiling 2.3–3 m; 2–4 poses
``l_room``     a rectangle with a corner notch (30–60 % of each side) cut out
``corridor``   a corridor 4–8 m long, 1–2 m wide, a doorway 0.7–1.1 m into a room
``maze``       a perfect maze of 3–5 × 3–5 cells of 1–1.6 m with one exit; the poses
               follow the way out, cell by cell
``boxes``      a room with 1–4 boxes (one 0.2–0.6 m in front of a wall)
=============  =================================================================

Every world has the fan mount at 0.2–0.5 m and the default odometry noise, seeded by the draw.
``draw_world(family, seed, mount="paper")`` is the same world seen by the paper's mount (a vertical
fan): each pose turns to face a wall whose foot of the perpendicular it sees, off square by up to
±12°, and the sweep reaches past straight down and straight up (the floor and the ceiling).
"""

from __future__ import annotations

import math
import zlib
from collections import deque

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.sim.world import MOUNTS, World, parse_world

#: World families, in the order benchmarks report them.
WORLD_FAMILIES: tuple[str, ...] = ("room", "l_room", "corridor", "maze", "boxes")
#: A drawn pose is at least this far from every wall and box, m.
POSE_CLEARANCE = 0.35
#: Paper mount: the most a pose's heading is off square to the wall it faces, rad.
PAPER_YAW = math.radians(12.0)
#: Paper mount: the farthest wall a pose may face, m (within the waveform window with room to spare).
PAPER_REACH = 3.0
#: Paper mount: the sweep's ends, drawn in these ranges, degrees: 35° to 60° past −90° and 90°, so a floor and a
#: ceiling close below and above (their regions as wide as the beam there) are whole in some sweeps, cut in others.
PAPER_SWEEP = ((-149.5, -125.0), (125.0, 149.5))
#: Paper mount: the shots' spacing, degrees (the paper mount's default sweep of 120° in 184 steps).
PAPER_STEP = 120.0 / 184


def world_rng(family: str, seed: int) -> np.random.Generator:
    """Independent streams per family and seed."""
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ConfigError(f"a world seed must be an int >= 0, got {seed!r}")
    return np.random.default_rng([int(seed), zlib.crc32(b"world:" + family.encode())])


def world_families(spec: str) -> tuple[str, ...]:
    """The families ``spec`` names: ``all``, or names separated by commas.

    Raises
    ------
    ConfigError
        A name that is no family.
    """
    families = WORLD_FAMILIES if spec == "all" else tuple(f.strip() for f in spec.split(","))
    unknown = [f for f in families if f not in WORLD_FAMILIES]
    if unknown:
        raise ConfigError(f"unknown world family {unknown[0]!r}; choose from {', '.join(WORLD_FAMILIES)} or all")
    return families


def draw_world(family: str, seed: int, mount: str = "fan") -> World:
    """World ``seed`` of ``family``: the same pair always gives the same world.

    ``mount = "paper"``: the same walls, boxes and pose positions seen by a vertical fan (its
    headings and sweep drawn from their own stream, so the fan worlds stay as they are).
    """
    if family not in WORLD_FAMILIES:
        raise ConfigError(f"unknown world family {family!r}; choose from {', '.join(WORLD_FAMILIES)}")
    if mount not in MOUNTS:
        raise ConfigError(f"unknown scanner mount {mount!r}; choose from {', '.join(MOUNTS)}")
    rng = world_rng(family, seed)
    walls, boxes, poses, ceiling = _DRAW[family](rng)
    scanner: dict = {"mount": mount}
    if mount == "paper":
        prng = np.random.default_rng([int(seed), zlib.crc32(b"mount:paper:" + family.encode())])
        poses = _face_walls(prng, poses, walls)
        sweep = [float(prng.uniform(*PAPER_SWEEP[0])), float(prng.uniform(*PAPER_SWEEP[1]))]
        scanner |= {"sweep": sweep, "steps": round((sweep[1] - sweep[0]) / PAPER_STEP)}
    turn = float(rng.uniform(-math.pi, math.pi))
    shift = rng.uniform(-3.0, 3.0, size=2)
    c, s = math.cos(turn), math.sin(turn)

    def move(p) -> list[float]:
        return [c * p[0] - s * p[1] + shift[0], s * p[0] + c * p[1] + shift[1]]

    data = {
        "world": {"name": f"{family}-{seed}"},
        "room": {"floor": 0.0, "ceiling": ceiling},
        "wall": [{"from": move(a), "to": move(b)} for a, b in walls],
        "box": [{"center": move(b["center"]), "size": b["size"], "yaw": math.degrees(b["yaw"] + turn)} for b in boxes],
        "scanner": scanner | {"height": float(rng.uniform(0.2, 0.5))},
        "pose": [
            {"x": q[0], "y": q[1], "heading": math.degrees(h + turn)} for (x, y, h) in poses for q in [move((x, y))]
        ],
        "odometry": {"seed": int(seed)},
    }
    return parse_world(data, f"{family}-{seed}")


# ---------------------------------------------------------------------------- helpers
def _polygon_walls(points: list[tuple[float, float]]) -> list:
    return [(points[i], points[(i + 1) % len(points)]) for i in range(len(points))]


def _clear(p, walls, boxes, clearance=POSE_CLEARANCE) -> bool:
    for a, b in walls:
        a, b = np.asarray(a, float), np.asarray(b, float)
        d = b - a
        t = np.clip((np.asarray(p) - a) @ d / (d @ d), 0.0, 1.0)
        if np.hypot(*(np.asarray(p) - a - t * d)) < clearance:
            return False
    for bx in boxes:
        c, s = math.cos(-bx["yaw"]), math.sin(-bx["yaw"])
        dx, dy = p[0] - bx["center"][0], p[1] - bx["center"][1]
        u, v = c * dx - s * dy, s * dx + c * dy
        if abs(u) < bx["size"][0] / 2 + clearance and abs(v) < bx["size"][1] / 2 + clearance:
            return False
    return True


def _poses_in(rng, inside, walls, boxes, count, bounds) -> list:
    out = []
    for _ in range(2000):
        p = (float(rng.uniform(bounds[0], bounds[2])), float(rng.uniform(bounds[1], bounds[3])))
        if inside(p) and _clear(p, walls, boxes):
            out.append((p[0], p[1], float(rng.uniform(-math.pi, math.pi))))
            if len(out) == count:
                return out
    raise ConfigError("could not place the poses of a drawn world (a bug in the family's bounds)")


def _crosses(p, q, a, b) -> bool:
    """Segments p–q and a–b cross (strictly)."""

    def side(u, v, w) -> float:
        return (v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0])

    return side(p, q, a) * side(p, q, b) < 0 and side(a, b, p) * side(a, b, q) < 0


def _blocked(p, foot, walls, own) -> bool:
    """Another wall stands between p and the foot on its own wall."""
    own_a, own_b = tuple(own[0]), tuple(own[1])
    return any(
        _crosses(p, tuple(foot), a, b)
        for a, b in walls
        if (tuple(map(float, a)), tuple(map(float, b))) != (own_a, own_b)
    )


def _face_walls(rng, poses, walls) -> list:
    """Each pose turned to face a wall: the foot of its perpendicular on the wall and within reach.

    The heading is off square by up to ±PAPER_YAW (a robot is never exactly square), so the wall's
    normal leaves the fan by that much and the capsules along the axis see it as a tilt.
    """
    out = []
    for x, y, h in poses:
        feet = []
        for a, b in walls:
            a, b = np.asarray(a, float), np.asarray(b, float)
            d = b - a
            t = float((np.array([x, y]) - a) @ d / (d @ d))
            foot = a + t * d
            dist = float(np.hypot(*(foot - (x, y))))
            # Not at the wall's very end (its edge would answer with the wall) and within reach.
            margin = 0.3 / float(np.sqrt(d @ d))
            if margin < t < 1 - margin and dist <= PAPER_REACH and not _blocked((x, y), foot, walls, (a, b)):
                feet.append((dist, math.atan2(foot[1] - y, foot[0] - x)))
        if not feet:
            out.append((x, y, h))
            continue
        _, toward = feet[int(rng.integers(len(feet)))]
        out.append((x, y, math.remainder(toward + float(rng.uniform(-PAPER_YAW, PAPER_YAW)), 2 * math.pi)))
    return out


# ---------------------------------------------------------------------------- families
def _room(rng):
    w, d = rng.uniform(2.5, 6.0), rng.uniform(2.5, 5.0)
    walls = _polygon_walls([(0, 0), (w, 0), (w, d), (0, d)])
    poses = _poses_in(rng, lambda p: True, walls, [], int(rng.integers(2, 5)), (0, 0, w, d))
    return walls, [], poses, float(rng.uniform(2.3, 3.0))


def _l_room(rng):
    w, d = rng.uniform(3.5, 6.5), rng.uniform(3.5, 6.0)
    nw, nd = w * rng.uniform(0.3, 0.6), d * rng.uniform(0.3, 0.6)
    pts = [(0, 0), (w, 0), (w, d - nd), (w - nw, d - nd), (w - nw, d), (0, d)]
    walls = _polygon_walls(pts)

    def inside(p):
        return not (p[0] > w - nw and p[1] > d - nd)

    poses = _poses_in(rng, inside, walls, [], int(rng.integers(2, 5)), (0, 0, w, d))
    return walls, [], poses, float(rng.uniform(2.3, 3.0))


def _corridor(rng):
    length, width = rng.uniform(4.0, 8.0), rng.uniform(1.0, 2.0)
    door = rng.uniform(0.7, 1.1)
    x_door = rng.uniform(1.0, length - 1.0 - door)
    room_w = rng.uniform(max(2.0, door + 1.0), min(4.0, length))
    room_x0 = float(np.clip(x_door + door / 2 - room_w / 2, 0.0, length - room_w))
    room_d = rng.uniform(2.0, 3.5)
    walls = [
        ((0, 0), (length, 0)),
        ((0, 0), (0, width)),
        ((length, 0), (length, width)),
        ((0, width), (x_door, width)),
        ((x_door + door, width), (length, width)),
        ((room_x0, width), (room_x0, width + room_d)),
        ((room_x0, width + room_d), (room_x0 + room_w, width + room_d)),
        ((room_x0 + room_w, width + room_d), (room_x0 + room_w, width)),
    ]
    mid = x_door + door / 2
    poses = [
        (float(rng.uniform(0.5, max(0.6, x_door - 0.2))), width / 2, 0.0),
        (mid, width / 2, math.pi / 2),
        (mid, width + room_d / 2, math.pi / 2),
    ]
    poses = [p for p in poses if _clear(p[:2], walls, [])]
    if not poses:
        raise ConfigError("could not place the poses of a drawn corridor")
    return walls, [], poses, float(rng.uniform(2.3, 3.0))


def _maze(rng):
    nx, ny = int(rng.integers(3, 6)), int(rng.integers(3, 6))
    cell = float(rng.uniform(1.0, 1.6))
    # Randomised depth-first search: a perfect maze (one way between any two cells).
    open_edges: set[tuple[tuple[int, int], tuple[int, int]]] = set()
    seen = {(0, 0)}
    stack = [(0, 0)]
    while stack:
        cx, cy = stack[-1]
        nexts = [
            (cx + dx, cy + dy)
            for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= cx + dx < nx and 0 <= cy + dy < ny and (cx + dx, cy + dy) not in seen
        ]
        if not nexts:
            stack.pop()
            continue
        nxt = nexts[int(rng.integers(len(nexts)))]
        open_edges.add(tuple(sorted(((cx, cy), nxt))))
        seen.add(nxt)
        stack.append(nxt)
    exit_cell = (nx - 1, int(rng.integers(ny)))
    walls = []
    # Inner walls: vertical between (i, j) and (i + 1, j), horizontal between (i, j) and (i, j + 1).
    for i in range(nx):
        for j in range(ny):
            if i + 1 < nx and ((i, j), (i + 1, j)) not in open_edges:
                walls.append((((i + 1) * cell, j * cell), ((i + 1) * cell, (j + 1) * cell)))
            if j + 1 < ny and ((i, j), (i, j + 1)) not in open_edges:
                walls.append(((i * cell, (j + 1) * cell), ((i + 1) * cell, (j + 1) * cell)))
    w, d = nx * cell, ny * cell
    walls += [((0, 0), (w, 0)), ((0, 0), (0, d)), ((0, d), (w, d))]
    ey = exit_cell[1]
    if ey > 0:
        walls.append(((w, 0), (w, ey * cell)))
    if ey < ny - 1:
        walls.append(((w, (ey + 1) * cell), (w, d)))
    # The way out: breadth-first from the start cell.
    prev: dict[tuple[int, int], tuple[int, int] | None] = {(0, 0): None}
    queue = deque([(0, 0)])
    while queue:
        c = queue.popleft()
        for e in open_edges:
            if c in e:
                o = e[1] if e[0] == c else e[0]
                if o not in prev:
                    prev[o] = c
                    queue.append(o)
    path: list[tuple[int, int]] = []
    node: tuple[int, int] | None = exit_cell
    while node is not None:
        path.append(node)
        node = prev[node]
    path.reverse()
    poses = []
    for k, (i, j) in enumerate(path):
        ni, nj = path[k + 1] if k + 1 < len(path) else (i + 1, j)  # out through the exit
        poses.append(((i + 0.5) * cell, (j + 0.5) * cell, math.atan2(nj - j, ni - i)))
    return walls, [], poses, float(rng.uniform(2.3, 3.0))


def _boxes(rng):
    w, d = rng.uniform(3.5, 6.0), rng.uniform(3.0, 5.0)
    walls = _polygon_walls([(0, 0), (w, 0), (w, d), (0, d)])
    boxes: list[dict] = []
    for k in range(int(rng.integers(1, 5))):
        for _ in range(200):
            size = [float(rng.uniform(0.3, 1.0)), float(rng.uniform(0.3, 1.0)), float(rng.uniform(0.4, 1.2))]
            if k == 0:  # one box in front of a wall (it shadows part of it)
                gap = rng.uniform(0.2, 0.6)
                center = (float(rng.uniform(1.0, w - 1.0)), float(d - gap - size[1] / 2))
                yaw = 0.0
            else:
                center = (float(rng.uniform(0.8, w - 0.8)), float(rng.uniform(0.8, d - 0.8)))
                yaw = float(rng.uniform(-math.pi, math.pi))
            box = {"center": center, "size": size, "yaw": yaw}
            r = math.hypot(size[0], size[1]) / 2
            if _clear(center, walls, boxes, clearance=r + 0.2 if k else 0.0):
                boxes.append(box)
                break
    poses = _poses_in(rng, lambda p: True, walls, boxes, int(rng.integers(2, 4)), (0, 0, w, d))
    return walls, boxes, poses, float(rng.uniform(2.3, 3.0))


_DRAW = {"room": _room, "l_room": _l_room, "corridor": _corridor, "maze": _maze, "boxes": _boxes}
