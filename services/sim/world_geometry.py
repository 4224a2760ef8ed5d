"""What in a world can echo: its reflecting rectangles and the elements they form.

A :class:`World` becomes, once and independently of where the robot is:

* **surfaces**: finite rectangles (both sides of each wall, the outer faces of
  each box, the floor, the ceiling);
* **elements**, each a source of one kind of echo:

  - ``MIRROR``: the specular echo of one surface;
  - ``DIHEDRAL``: where two surfaces meet in a concave edge (wall and wall,
    wall and floor or ceiling, box side and floor): the double bounce;
  - ``TRIHEDRAL``: where two walls meet the floor or the ceiling: the triple
    bounce of a corner cube;
  - ``EDGE``: a convex or free edge (a wall's end at a doorway, a box's
    corner, a wall's top below the ceiling): diffraction.

Vertical junctions are found in plan view: at each point where wall or box
faces meet (within :data:`JOIN_TOLERANCE`), the faces leave as "arms"; between
two arms adjacent in angle lies a sector.  Seen from inside a sector narrower
than 180° the junction is a concave dihedral, from inside one wider it is a
convex edge, and a lone arm (a free wall end) is an edge seen from all round.
Faces of different heights split a junction into height bands, each with its
own sectors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from lelsonar.sim.world import World

#: Wall and box faces closer than this in plan view meet, m.
JOIN_TOLERANCE = 0.01
#: Sectors within this of 180° are a straight wall, not a corner or an edge, rad.
_STRAIGHT = math.radians(1.0)
#: The floor and ceiling rectangles reach this far past everything else in the world, m.
_FLOOR_MARGIN = 2.0


class ElementKind(IntEnum):
    """What kind of echo an element gives."""

    MIRROR = 1
    DIHEDRAL = 2
    TRIHEDRAL = 3
    EDGE = 4


@dataclass(frozen=True, eq=False)
class Surface:
    """A reflecting rectangle of the world.

    Attributes
    ----------
    label : str
        ``wall3``, ``box1.side2``, ``box1.top``, ``floor``, ``ceiling``.
    kind : str
        ``wall``, ``box``, ``floor`` or ``ceiling``.
    center, normal, u, v : (3,) arrays
        Centre, unit normal, unit in-plane axes (``v = normal × u``), world frame.
    half_u, half_v : float
        Half extents along ``u`` and ``v``, m.
    reflectivity : float
    two_sided : bool
        A wall reflects on both sides; a box face, the floor and the ceiling on the side ``normal`` points to.
    """

    label: str
    kind: str
    center: np.ndarray
    normal: np.ndarray
    u: np.ndarray
    v: np.ndarray
    half_u: float
    half_v: float
    reflectivity: float
    two_sided: bool

    def corners(self) -> np.ndarray:
        """The four corners, (4, 3)."""
        c, u, v = self.center, self.u * self.half_u, self.v * self.half_v
        return np.stack([c - u - v, c + u - v, c + u + v, c - u + v])


@dataclass(frozen=True, eq=False)
class Element:
    """One source of echoes.

    Attributes
    ----------
    kind : ElementKind
    label : str
        The surfaces' labels joined by ``|``.
    surfaces : tuple of int
        Indices into :attr:`WorldModel.surfaces` of the surfaces that form it.
    p0, p1 : (3,) arrays
        The edge segment (dihedral, edge) or the vertex twice (trihedral); unused for a mirror.
    opening : float
        Interior angle of the wedge the scanner must be in, rad (π/2 for a right corner, 3π/2 for a
        box's corner seen from outside, 2π for a free wall end; π for a horizontal edge of a wall, seen
        from either side).
    sector : (cx, cy, a0, span) or None
        Plan-view wedge the scanner must be in: at ``(cx, cy)``, from heading ``a0`` counter-clockwise
        over ``span`` (rad).  None: no such condition.
    side : (normal, offset) or None
        Half-space ``normal·p > offset`` the scanner must be in.  None: no such condition.
    gain : float
        Product of the reflectivities of the surfaces that bounce the sound.
    """

    kind: ElementKind
    label: str
    surfaces: tuple[int, ...]
    p0: np.ndarray
    p1: np.ndarray
    opening: float
    sector: tuple[float, float, float, float] | None
    side: tuple[np.ndarray, float] | None
    gain: float

    def describe(self) -> dict:
        """JSON-ready description (ground truth for readers of a recording)."""
        out: dict = {"kind": self.kind.name.lower(), "label": self.label}
        if self.kind != ElementKind.MIRROR:
            out["p0"] = [round(float(x), 6) for x in self.p0]
            out["p1"] = [round(float(x), 6) for x in self.p1]
            out["opening_deg"] = round(math.degrees(self.opening), 4)
        return out


@dataclass(frozen=True, eq=False)
class WorldModel:
    """The surfaces and elements of a world; mirrors come first, one per surface, in surface order."""

    world: World
    surfaces: tuple[Surface, ...]
    elements: tuple[Element, ...]

    def stacked(self) -> dict[str, np.ndarray]:
        """Surfaces as stacked arrays for vectorised ray tests: center, normal, u, v (B, 3); half_u, half_v (B,)."""
        s = self.surfaces
        return {
            "center": np.stack([x.center for x in s]),
            "normal": np.stack([x.normal for x in s]),
            "u": np.stack([x.u for x in s]),
            "v": np.stack([x.v for x in s]),
            "half_u": np.array([x.half_u for x in s]),
            "half_v": np.array([x.half_v for x in s]),
        }


def _vertical_rect(label, kind, a, b, z0, z1, refl, two_sided, outward=None) -> Surface:
    """The rectangle over the floor segment a→b between heights z0 and z1; normal horizontal."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    length = float(np.hypot(*d))
    u = np.array([d[0], d[1], 0.0]) / length
    normal = np.array([-u[1], u[0], 0.0]) if outward is None else np.asarray(outward, float)
    # v = normal × u must be +z or −z; keep u so that it is +z (heights along v).
    if np.cross(normal, u)[2] < 0:
        u = -u
    center = np.array([(a[0] + b[0]) / 2, (a[1] + b[1]) / 2, (z0 + z1) / 2])
    return Surface(label, kind, center, normal, u, np.cross(normal, u), length / 2, (z1 - z0) / 2, refl, two_sided)


def _horizontal_rect(label, kind, center, size, yaw, z, up, refl) -> Surface:
    c, s = math.cos(yaw), math.sin(yaw)
    normal = np.array([0.0, 0.0, 1.0 if up else -1.0])
    u = np.array([c, s, 0.0])
    return Surface(
        label,
        kind,
        np.array([center[0], center[1], z]),
        normal,
        u,
        np.cross(normal, u),
        size[0] / 2,
        size[1] / 2,
        refl,
        False,
    )


def build_model(world: World) -> WorldModel:
    """Surfaces and elements of ``world`` (see the module docstring)."""
    floor, ceiling = world.room.floor, world.room.ceiling
    surfaces: list[Surface] = []
    # Plan-view faces that meet at vertical junctions: (surface index, a, b, z0, z1).
    faces: list[tuple[int, np.ndarray, np.ndarray, float, float]] = []
    elements: list[Element] = []
    for w in world.walls:
        z0 = floor + w.bottom
        z1 = z0 + w.height
        surfaces.append(_vertical_rect(w.name, "wall", w.start, w.end, z0, z1, w.reflectivity, True))
        faces.append((len(surfaces) - 1, np.array(w.start), np.array(w.end), z0, z1))
    box_sides: list[tuple[int, int, np.ndarray, np.ndarray, float]] = []  # (side, top, a, b, height)
    for box in world.boxes:
        fp = box.footprint()
        top_index = len(surfaces) + 4
        for k in range(4):
            a, e = np.array(fp[k]), np.array(fp[(k + 1) % 4])
            d = e - a
            outward = np.array([d[1], -d[0], 0.0]) / np.hypot(*d)  # footprint is counter-clockwise
            surfaces.append(
                _vertical_rect(
                    f"{box.name}.side{k + 1}", "box", a, e, floor, floor + box.size[2], box.reflectivity, False, outward
                )
            )
            faces.append((len(surfaces) - 1, a, e, floor, floor + box.size[2]))
            box_sides.append((len(surfaces) - 1, top_index, a, e, floor + box.size[2]))
        surfaces.append(
            _horizontal_rect(
                f"{box.name}.top", "box", box.center, box.size, box.yaw, floor + box.size[2], True, box.reflectivity
            )
        )
    x0, y0, x1, y1 = world.bounds()
    extent = (x1 - x0 + 2 * _FLOOR_MARGIN, y1 - y0 + 2 * _FLOOR_MARGIN)
    middle = ((x0 + x1) / 2, (y0 + y1) / 2)
    floor_index = len(surfaces)
    surfaces.append(_horizontal_rect("floor", "floor", middle, extent, 0.0, floor, True, world.room.floor_reflectivity))
    ceiling_index = -1
    if ceiling is not None:
        ceiling_index = len(surfaces)
        surfaces.append(
            _horizontal_rect("ceiling", "ceiling", middle, extent, 0.0, ceiling, False, world.room.ceiling_reflectivity)
        )

    for i, s in enumerate(surfaces):
        zero = np.zeros(3)
        elements.append(Element(ElementKind.MIRROR, s.label, (i,), zero, zero, math.pi, None, None, s.reflectivity))

    elements += _junction_elements(surfaces, faces, floor, ceiling, floor_index, ceiling_index)

    # Horizontal edges of the walls: the foot (with the floor), the top (with the ceiling or free), a raised bottom.
    for i, p0, p1, z0, z1 in faces[: len(world.walls)]:
        foot_other = floor_index if abs(z0 - floor) < 1e-6 else -1
        elements.append(_horizontal_edge(surfaces, i, foot_other, p0, p1, z0, None, "bottom"))
        top_other = ceiling_index if ceiling is not None and abs(z1 - ceiling) < 1e-6 else -1
        elements.append(_horizontal_edge(surfaces, i, top_other, p0, p1, z1, None, "top"))
    # Box sides: a concave foot with the floor, a convex top edge with the box's top.
    for side, top, p0, p1, z_top in box_sides:
        s = surfaces[side]
        half = (s.normal, float(s.normal @ s.center))
        elements.append(_horizontal_edge(surfaces, side, floor_index, p0, p1, floor, half, "bottom"))
        foot = _horizontal_edge(surfaces, side, -1, p0, p1, z_top, None, "top")
        elements.append(
            Element(
                ElementKind.EDGE,
                f"{s.label}|{surfaces[top].label}",
                (side, top),
                foot.p0,
                foot.p1,
                1.5 * math.pi,
                None,
                None,
                s.reflectivity,
            )
        )
    return WorldModel(world=world, surfaces=tuple(surfaces), elements=tuple(elements))


def _horizontal_edge(
    surfaces: list[Surface], face: int, other: int, a: np.ndarray, b: np.ndarray, z: float, side, which: str
) -> Element:
    """The edge along a→b at height z: a right dihedral with surface ``other``, or a free edge (other = −1)."""
    p0, p1 = np.array([a[0], a[1], z]), np.array([b[0], b[1], z])
    s = surfaces[face]
    if other >= 0:
        return Element(
            ElementKind.DIHEDRAL,
            f"{s.label}|{surfaces[other].label}",
            (face, other),
            p0,
            p1,
            math.pi / 2,
            None,
            side,
            s.reflectivity * surfaces[other].reflectivity,
        )
    return Element(ElementKind.EDGE, f"{s.label}.{which}", (face,), p0, p1, 2 * math.pi, None, side, s.reflectivity)


def _junction_elements(
    surfaces: list[Surface],
    faces: list[tuple[int, np.ndarray, np.ndarray, float, float]],
    floor: float,
    ceiling: float | None,
    floor_index: int,
    ceiling_index: int,
) -> list[Element]:
    """Dihedrals, trihedrals and edges where plan-view faces meet or end (see the module docstring)."""
    # Arms: (point, heading of the arm, face, z0, z1).
    arms: list[tuple[np.ndarray, float, int, float, float]] = []
    for f, a, b, z0, z1 in faces:
        d = b - a
        arms.append((a, math.atan2(d[1], d[0]), f, z0, z1))
        arms.append((b, math.atan2(-d[1], -d[0]), f, z0, z1))
    # A face's end on another face's middle (a T): the other face leaves that point both ways.
    for f, a, b, _z0, _z1 in faces:
        for end in (a, b):
            for g, ga, gb, gz0, gz1 in faces:
                if g == f:
                    continue
                d = gb - ga
                length = float(np.hypot(*d))
                t = float((end - ga) @ d) / length
                if JOIN_TOLERANCE < t < length - JOIN_TOLERANCE:
                    foot = ga + d * (t / length)
                    if float(np.hypot(*(end - foot))) < JOIN_TOLERANCE:
                        arms.append((foot, math.atan2(d[1], d[0]), g, gz0, gz1))
                        arms.append((foot, math.atan2(-d[1], -d[0]), g, gz0, gz1))
    # Group arms by junction point.
    junctions: list[tuple[np.ndarray, list]] = []
    for arm in arms:
        for point, members in junctions:
            if float(np.hypot(*(arm[0] - point))) < JOIN_TOLERANCE:
                members.append(arm)
                break
        else:
            junctions.append((arm[0], [arm]))
    out: list[Element] = []
    for _point, members in junctions:
        c = np.mean([m[0] for m in members], axis=0)
        levels = sorted({m[3] for m in members} | {m[4] for m in members})
        for lo, hi in zip(levels[:-1], levels[1:], strict=True):
            if hi - lo < 1e-3:
                continue
            present: dict[tuple[int, int], tuple[float, int]] = {}
            for _p, heading, f, z0, z1 in members:
                if z0 <= lo + 1e-9 and z1 >= hi - 1e-9:
                    present[(f, round(math.degrees(heading) * 100))] = (heading % (2 * math.pi), f)
            ordered = sorted(present.values())
            if not ordered:
                continue
            for k, (a0, fa) in enumerate(ordered):
                a1, fb = ordered[(k + 1) % len(ordered)]
                span = (a1 - a0) % (2 * math.pi) if len(ordered) > 1 else 2 * math.pi
                if abs(span - math.pi) < _STRAIGHT or span < 1e-6:
                    continue
                p0, p1 = np.array([c[0], c[1], lo]), np.array([c[0], c[1], hi])
                sector = (float(c[0]), float(c[1]), float(a0), float(span))
                pair = (fa,) if fa == fb else (min(fa, fb), max(fa, fb))
                # Where, and towards which side: the junction's point and the heading of the sector's bisector.
                at = f"@{c[0]:g},{c[1]:g}:{math.degrees((a0 + span / 2) % (2 * math.pi)):.0f}"
                label = "|".join(surfaces[i].label for i in pair)
                gain = float(np.prod([surfaces[i].reflectivity for i in pair]))
                if span < math.pi - _STRAIGHT:
                    out.append(Element(ElementKind.DIHEDRAL, label + at, pair, p0, p1, span, sector, None, gain))
                    for z, h in ((lo, floor_index), (hi, ceiling_index)):
                        at_plane = (
                            abs(z - floor) < 1e-6
                            if h == floor_index
                            else (ceiling is not None and abs(z - ceiling) < 1e-6)
                        )
                        if h >= 0 and at_plane:
                            vertex = np.array([c[0], c[1], z])
                            out.append(
                                Element(
                                    ElementKind.TRIHEDRAL,
                                    f"{label}|{surfaces[h].label}{at}",
                                    (*pair, h),
                                    vertex,
                                    vertex,
                                    span,
                                    sector,
                                    None,
                                    gain * surfaces[h].reflectivity,
                                )
                            )
                else:
                    gain_edge = max(surfaces[i].reflectivity for i in pair)
                    out.append(Element(ElementKind.EDGE, label + at, pair, p0, p1, span, sector, None, gain_edge))
    return out
