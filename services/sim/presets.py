"""Named simulator configurations: the paper's two tests and a tilted L for benchmarks."""

from __future__ import annotations

import math

from lelsonar.errors import ConfigError
from lelsonar.sim.config import SimConfig
from lelsonar.sim.scene import Scene


def _paper_test1() -> SimConfig:
    # Paper §3, Test 1: 184 steps over [-10°, 110°].
    return SimConfig(steps=184)


def _paper_test2() -> SimConfig:
    # Paper §3, Test 2: the same setting with 220 steps.
    return SimConfig(steps=220)


def _tilted() -> SimConfig:
    # Plane a yawed 3° about z (the edge leaves the x axis) and plane b pitched
    # 2° about x (the corner opens to 92°): what a real, imperfect rig looks like.
    scene = Scene.l_corner(tilt_a_z=math.radians(3.0), tilt_b_x=math.radians(-2.0))
    return SimConfig(scene=scene, steps=220)


_PRESETS = {
    "paper-test1": _paper_test1,
    "paper-test2": _paper_test2,
    "tilted": _tilted,
}


def preset_names() -> tuple[str, ...]:
    """Names accepted by :func:`preset`."""
    return tuple(_PRESETS)


def preset(name: str) -> SimConfig:
    """A named :class:`SimConfig`.

    ``paper-test1``: the paper's L (planes y = 1.57 m, z = 1.06 m), 184 steps over [-10°, 110°].
    ``paper-test2``: the same with 220 steps.
    ``tilted``: plane a yawed 3° about z, plane b pitched −2° about x (a 92° corner), 220 steps.

    Raises
    ------
    ConfigError
        For an unknown name.
    """
    try:
        return _PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown simulator preset {name!r}; choose one of {', '.join(_PRESETS)}") from None
