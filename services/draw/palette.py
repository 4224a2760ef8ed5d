"""What every viewer shows of an estimate (Rerun, Foxglove, ROS 2 markers, the console): one colour per
method, and one name and colour per trust verdict.

RGB in 0–255; viewers that take 0–1 divide by 255.
"""

from __future__ import annotations

import zlib

from lelsonar.codec import QUALITY, QUALITY_NAME

__all__ = [
    "CONCAVE_CORNER_COLOR",
    "CONVEX_EDGE_COLOR",
    "HORIZONTAL_CORNER_COLOR",
    "METHOD_COLORS",
    "QUALITY",
    "QUALITY_NAME",
    "QUALITY_COLORS",
    "UNASSESSED_COLOR",
    "method_color",
    "quality_color",
    "unit_rgb",
]

METHOD_COLORS: dict[str, tuple[int, int, int]] = {
    "corner": (30, 120, 255),  # blue: the method of record
    "ls": (255, 140, 0),  # orange
    "lel": (40, 190, 70),  # green
    "paper": (0, 180, 210),  # cyan
    "fcm-ransac": (220, 60, 200),  # magenta
}
_PALETTE = ((230, 200, 40), (120, 120, 255), (255, 110, 110), (140, 220, 220), (200, 160, 100))

#: The trust verdict: green good, amber degraded, red unreliable.
QUALITY_COLORS: dict[str, tuple[int, int, int]] = {
    "good": (40, 200, 80),
    "degraded": (255, 170, 0),
    "unreliable": (230, 30, 30),
}
UNASSESSED_COLOR = (150, 150, 150)
#: A concave corner (pink) and a convex edge (cyan), in a scan and in a map.
CONCAVE_CORNER_COLOR = (255, 80, 200)
CONVEX_EDGE_COLOR = (0, 220, 255)
#: A map's line where a wall meets the floor or the ceiling (violet: apart from the plan's corners and edges).
HORIZONTAL_CORNER_COLOR = (170, 110, 255)


def method_color(method: str) -> tuple[int, int, int]:
    """The colour of an estimator's planes: fixed for known methods, stable for others."""
    return METHOD_COLORS.get(method, _PALETTE[zlib.crc32(method.encode()) % len(_PALETTE)])


def quality_color(quality: str | int) -> tuple[int, int, int]:
    """The colour of a verdict, by name (``"good"``, …) or wire value; grey when not assessed or unknown."""
    name = QUALITY_NAME.get(quality, "") if isinstance(quality, int) else quality
    return QUALITY_COLORS.get(name, UNASSESSED_COLOR)


def unit_rgb(rgb: tuple[int, int, int]) -> tuple[float, float, float]:
    """A palette colour for viewers that take RGB in 0–1."""
    return rgb[0] / 255, rgb[1] / 255, rgb[2] / 255
