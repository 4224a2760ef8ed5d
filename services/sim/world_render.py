"""A world's echoes at a robot pose, from first principles, and whole simulated scans of them.

The same acoustics as the L-corner simulator (:mod:`lelsonar.sim.scan`): the
piston beam ``D(ψ)²``, air absorption, ``1/(2r)`` spreading, the receiver
chain (amplitude noise, comparator, timing, waveforms) of
:func:`~lelsonar.sim.scan.shots_from_echoes`.  Per capsule and step, every
element of the world (:mod:`lelsonar.sim.world_geometry`) gives at most one echo:

* **mirror** of a surface: the image of the capsule in the surface's plane.
  Range = the perpendicular distance; present when the foot of the
  perpendicular lies on the rectangle (on its reflecting side) and the
  direction to it is in the main lobe.  Amplitude
  ``ρ·D(ψ)²·10^(−α·2r/20)/(2r)``.
* **dihedral** (two surfaces at a concave, right edge): the double image is
  the capsule turned by twice the opening about the edge, so the one-way range
  is ``ρ_e·sin(opening)`` (``ρ_e`` = distance to the edge line; ``= ρ_e`` at
  90°).  Present when the foot on the edge lies on the segment, the capsule is
  inside the wedge and the opening is within ``corner_max_error`` of 90°.
  Amplitude as a mirror at that range times ``corner_gain`` and both
  reflectivities.
* **trihedral** (two walls and the floor or ceiling): the triple image is the
  capsule mirrored through the vertex, range = distance to the vertex.
  Amplitude times ``trihedral_gain`` and the three reflectivities.
* **edge** (convex or free): diffraction from the foot on the edge, range =
  distance to it, amplitude times ``edge_gain`` (weak).  A concave edge far
  from 90° does not retro-reflect and diffracts the same way.
* **diffuse**: from the first surface the boresight meets, as the L simulator.

Every path is checked for **occlusion**: the segment from the capsule to the
reflection point (mirror foot, edge foot, vertex) must cross no other surface
(a segment–rectangle intersection test against every rectangle of the world,
stopping 1 mm short of both ends).  Gaps between walls (doorways) are simply
where no surface is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lelsonar.errors import ConfigError
from lelsonar.geometry import ArrayGeometry, array_pose, boresight
from lelsonar.signal.directivity import piston_directivity
from lelsonar.sim.acoustics import (
    Acoustics,
    Receiver,
    absorption_factor,
    capsule_radius_for_beam_width,
    sound_speed,
)
from lelsonar.sim.config import Servo
from lelsonar.sim.scan import EchoSource, EchoTable, shots_from_echoes
from lelsonar.sim.world import Pose2, World
from lelsonar.sim.world_geometry import Element, ElementKind, WorldModel, build_model

#: Receiver envelope span (rise times) the window holds after the farthest echo.
_ENVELOPE_SPAN = 8.0
#: Occlusion tests stop this far short of both ends of a path, m.
_END_MARGIN = 1e-3

_SOURCE = {
    ElementKind.MIRROR: EchoSource.PLANE_OTHER,
    ElementKind.DIHEDRAL: EchoSource.CORNER,
    ElementKind.TRIHEDRAL: EchoSource.TRIHEDRAL,
    ElementKind.EDGE: EchoSource.EDGE,
}


@dataclass(frozen=True)
class WorldRig:
    """The simulated scanner of a world: array, sweep, air, receiver and servo.

    Attributes
    ----------
    mount : {"fan", "paper"}
    height : float
        Rotation axis above the floor, m.
    geometry : ArrayGeometry
    gamma_start, gamma_stop : float
        The sweep, rad.
    steps : int
    temperature : float
        K.
    sample_rate : float
        Hz.
    window_samples : int
    window_start : float
        s.
    acoustics : Acoustics
    receiver : Receiver
    servo : Servo
    edge_gain : float
        Diffraction echo relative to a mirror at the same range.
    trihedral_gain : float
        Triple bounce relative to a mirror at the same range.
    tilt : float
        rad, the mount turned about the robot's lateral axis (:func:`lelsonar.geometry.tilt_rotation`).
    """

    mount: str
    height: float
    geometry: ArrayGeometry
    gamma_start: float
    gamma_stop: float
    steps: int
    temperature: float
    sample_rate: float
    window_samples: int
    window_start: float
    acoustics: Acoustics
    receiver: Receiver
    servo: Servo = field(default_factory=Servo)
    edge_gain: float = 0.2
    trihedral_gain: float = 1.5
    tilt: float = 0.0

    @property
    def sound_speed(self) -> float:
        """c at :attr:`temperature`, m/s."""
        return float(sound_speed(self.temperature))

    def gamma_commanded(self) -> np.ndarray:
        """Commanded γ of every step, rad."""
        return np.linspace(self.gamma_start, self.gamma_stop, int(self.steps))


def world_rig(world: World, *, receiver: Receiver | None = None, steps: int | None = None) -> WorldRig:
    """The rig a world file describes (``[scanner]``, ``[acoustics]``); the receiver is the simulator's default."""
    sc, wa = world.scanner, world.acoustics
    base = Acoustics()
    c = float(sound_speed(wa.temperature))
    acoustics = Acoustics(
        capsule_radius=base.capsule_radius
        if sc.beam_width is None
        else capsule_radius_for_beam_width(sc.beam_width, c, base.frequency),
        absorption_db_per_m=base.absorption_db_per_m if wa.absorption_db_per_m is None else wa.absorption_db_per_m,
        corner_gain=base.corner_gain if wa.corner_gain is None else wa.corner_gain,
        diffuse_coefficient=base.diffuse_coefficient if wa.diffuse_coefficient is None else wa.diffuse_coefficient,
    )
    receiver = receiver or Receiver()
    fs = 200_000.0
    t_end = 2.0 * sc.max_range / c + _ENVELOPE_SPAN * receiver.envelope_time
    window = int(math.ceil(t_end * fs / 100.0) * 100)
    return WorldRig(
        mount=sc.mount,
        height=world.room.floor + sc.height,
        geometry=ArrayGeometry(radial_offset=sc.radial_offset),
        gamma_start=sc.sweep_start,
        gamma_stop=sc.sweep_stop,
        steps=int(steps or sc.steps),
        temperature=wa.temperature,
        sample_rate=fs,
        window_samples=window,
        window_start=0.0,
        acoustics=acoustics,
        receiver=receiver,
        edge_gain=wa.edge_gain,
        trihedral_gain=acoustics.corner_gain if wa.trihedral_gain is None else wa.trihedral_gain,
        tilt=sc.tilt,
    )


def pose_frame(rig: WorldRig, pose: Pose2) -> tuple[np.ndarray, np.ndarray]:
    """world ← array (γ = 0) rotation and translation of the scanner at ``pose``."""
    return array_pose(pose.x, pose.y, pose.heading, rig.mount, rig.height, rig.tilt)


# ---------------------------------------------------------------------------- geometry helpers
def _angle_between(bore: np.ndarray, direction: np.ndarray, length: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.einsum("nk,nk->n", bore, direction) / length
    return np.arccos(np.clip(cos, -1.0, 1.0))


def _in_sector(points: np.ndarray, sector: tuple[float, float, float, float] | None) -> np.ndarray:
    if sector is None:
        return np.ones(points.shape[0], dtype=bool)
    cx, cy, a0, span = sector
    beta = np.arctan2(points[:, 1] - cy, points[:, 0] - cx)
    rel = np.mod(beta - a0, 2.0 * math.pi)
    return (rel > 1e-9) & (rel < span - 1e-9)


def _on_side(points: np.ndarray, side: tuple[np.ndarray, float] | None) -> np.ndarray:
    if side is None:
        return np.ones(points.shape[0], dtype=bool)
    return points @ side[0] > side[1]


def segment_blocked(
    start: np.ndarray, end: np.ndarray, surfaces: dict[str, np.ndarray], exclude: tuple[int, ...] = ()
) -> np.ndarray:
    """Whether each segment ``start → end`` crosses one of the rectangles ``surfaces`` (:meth:`WorldModel.stacked`).

    A segment–rectangle test: the segment meets the rectangle's plane at
    ``t = n·(c − p)/n·d`` and the crossing lies on the rectangle.  Crossings
    within 1 mm of either end do not count (a path ends on the surfaces that
    reflect it), nor do the rectangles in ``exclude``.

    Parameters
    ----------
    start, end : (N, 3) arrays
    surfaces : dict of arrays
        ``center``, ``normal``, ``u``, ``v`` (B, 3) and ``half_u``, ``half_v`` (B,).
    exclude : tuple of int

    Returns
    -------
    (N,) bool array
    """
    d = end - start
    length = np.linalg.norm(d, axis=1)
    normal = surfaces["normal"]
    denom = d @ normal.T
    num = np.einsum("bk,bk->b", surfaces["center"], normal)[None, :] - start @ normal.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / denom
        margin = (_END_MARGIN / length)[:, None]
    valid = (np.abs(denom) > 1e-12) & (t > margin) & (t < 1.0 - margin)
    t = np.where(valid, t, 0.0)
    rel = start[:, None, :] + t[..., None] * d[:, None, :] - surfaces["center"][None]
    hit = (
        valid
        & (np.abs(np.einsum("nbk,bk->nb", rel, surfaces["u"])) <= surfaces["half_u"][None])
        & (np.abs(np.einsum("nbk,bk->nb", rel, surfaces["v"])) <= surfaces["half_v"][None])
    )
    if exclude:
        hit[:, list(exclude)] = False
    return hit.any(axis=1)


def _element_echo(
    model: WorldModel, el: Element, pos: np.ndarray, bore: np.ndarray, rig: WorldRig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range, amplitude and reflection point of one element's echo for flat capsules ``pos`` (N, 3)."""
    ac = rig.acoustics
    c = rig.sound_speed
    ka = ac.wavenumber(c) * ac.capsule_radius
    lobe = ac.main_lobe(c)
    n = pos.shape[0]
    if el.kind == ElementKind.MIRROR:
        s = model.surfaces[el.surfaces[0]]
        signed = (pos - s.center) @ s.normal
        dist = np.abs(signed)
        target = pos - signed[:, None] * s.normal
        rel = target - s.center
        ok = (np.abs(rel @ s.u) <= s.half_u) & (np.abs(rel @ s.v) <= s.half_v) & (dist > 1e-6)
        if not s.two_sided:
            ok &= signed > 0
        r, gain = dist, el.gain
    elif el.kind == ElementKind.TRIHEDRAL:
        target = np.broadcast_to(el.p0, (n, 3))
        r = np.linalg.norm(target - pos, axis=1)
        right = abs(el.opening - math.pi / 2) <= ac.corner_max_error
        ok = _in_sector(pos, el.sector) & _on_side(pos, el.side) & (r > 1e-6) & right
        gain = rig.trihedral_gain * el.gain
    else:
        d = el.p1 - el.p0
        length = float(np.linalg.norm(d))
        e = d / length
        t = (pos - el.p0) @ e
        target = el.p0 + t[:, None] * e
        rho = np.linalg.norm(target - pos, axis=1)
        ok = (t >= 0) & (t <= length) & _in_sector(pos, el.sector) & _on_side(pos, el.side) & (rho > 1e-6)
        if el.kind == ElementKind.DIHEDRAL and abs(el.opening - math.pi / 2) <= ac.corner_max_error:
            r, gain = rho * math.sin(el.opening), ac.corner_gain * el.gain
        else:
            r, gain = rho, rig.edge_gain * el.gain
    psi = _angle_between(bore, target - pos, np.linalg.norm(target - pos, axis=1))
    ok &= psi < lobe
    with np.errstate(divide="ignore", invalid="ignore"):
        amp = gain * piston_directivity(psi, ka) ** 2 * absorption_factor(2 * r, ac.absorption_db_per_m) / (2 * r)
    return np.where(ok, r, np.nan), np.where(ok, amp, 0.0), target


def world_echo_table(
    model: WorldModel, rig: WorldRig, rotation: np.ndarray, translation: np.ndarray, gamma: np.ndarray
) -> EchoTable:
    """Every echo of every capsule with the array at ``gamma`` (rad), the array frame at (rotation, translation).

    Slots: one per element of ``model`` (in order, so ``index`` is the element's) and one diffuse echo.
    """
    gamma = np.atleast_1d(np.asarray(gamma, dtype=float))
    pos = rig.geometry.capsule_positions(gamma) @ rotation.T + translation  # (n, m, 3)
    bore_n = boresight(gamma) @ rotation.T  # (n, 3)
    n, m = pos.shape[:2]
    flat = pos.reshape(-1, 3)
    bore = np.repeat(bore_n, m, axis=0)
    stacked = model.stacked()
    k_slots = len(model.elements) + 1
    out_range = np.full((n * m, k_slots), np.nan)
    out_amp = np.zeros((n * m, k_slots))
    out_src = np.zeros((n * m, k_slots), dtype=np.int8)
    out_idx = np.full((n * m, k_slots), -1, dtype=np.int16)
    for k, el in enumerate(model.elements):
        r, a, target = _element_echo(model, el, flat, bore, rig)
        live = np.flatnonzero(a > 0)
        if live.size:
            hidden = segment_blocked(flat[live], np.asarray(target)[live], stacked, el.surfaces)
            r[live[hidden]] = np.nan
            a[live[hidden]] = 0.0
        out_range[:, k], out_amp[:, k] = r, a
        out_src[:, k] = _SOURCE[el.kind]
        out_idx[:, k] = k
    # Diffuse: the first surface along the boresight.
    ac = rig.acoustics
    normal = stacked["normal"]
    denom = bore @ normal.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.einsum("bk,bk->b", stacked["center"], normal)[None, :] - flat @ normal.T) / denom
    valid = (np.abs(denom) > 1e-9) & (t > 1e-6)
    t = np.where(valid, t, np.inf)
    rel = flat[:, None, :] + np.where(valid, t, 0.0)[..., None] * bore[:, None, :] - stacked["center"][None]
    on = (
        valid
        & (np.abs(np.einsum("nbk,bk->nb", rel, stacked["u"])) <= stacked["half_u"][None])
        & (np.abs(np.einsum("nbk,bk->nb", rel, stacked["v"])) <= stacked["half_v"][None])
    )
    t = np.where(on, t, np.inf)
    first = np.argmin(t, axis=1)
    along = t[np.arange(n * m), first]
    hit = np.isfinite(along) & (ac.diffuse_coefficient > 0)
    refl = np.array([s.reflectivity for s in model.surfaces])[first]
    cos_i = np.abs(denom[np.arange(n * m), first])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        a_d = ac.diffuse_coefficient * refl * cos_i * absorption_factor(2 * along, ac.absorption_db_per_m) / (2 * along)
    out_range[:, -1] = np.where(hit, along, np.nan)
    out_amp[:, -1] = np.where(hit, a_d, 0.0)
    out_src[:, -1] = EchoSource.DIFFUSE
    out_idx[:, -1] = np.where(hit, first, -1)  # mirrors come first: surface i is element i
    shape = (n, m, k_slots)
    return EchoTable(
        range=out_range.reshape(shape),
        amplitude=out_amp.reshape(shape),
        source=out_src.reshape(shape),
        index=out_idx.reshape(shape),
    )


# ---------------------------------------------------------------------------- whole scans
@dataclass(frozen=True, eq=False)
class WorldScan:
    """One simulated sweep at one pose, shaped like :class:`~lelsonar.sim.scan.SimulatedScan`, plus its truth.

    Attributes
    ----------
    gamma_commanded, gamma_measured : (n,) arrays, rad
    gamma_raw : (n,) int array, AX-12 units
    gamma_true : (n,) array, rad
    tof : (n, m) array, s (NaN: no echo)
    distance : (n, m) array, m
    waveforms : (n, m, samples) float32 array, V
    sample_rate, t0, sound_speed, temperature : float
    geometry : ArrayGeometry
    rig : WorldRig
    pose : Pose2
        Where the robot truly was.
    pose_index : int
    echo_source, echo_index, echo_range : (n, m) arrays
        Which element set each time of flight (:class:`EchoSource`, index into ``model.elements``), and its
        noise-free range.
    model : WorldModel
    """

    gamma_commanded: np.ndarray
    gamma_measured: np.ndarray
    gamma_raw: np.ndarray
    gamma_true: np.ndarray
    tof: np.ndarray
    distance: np.ndarray
    waveforms: np.ndarray
    sample_rate: float
    t0: float
    sound_speed: float
    temperature: float
    geometry: ArrayGeometry
    rig: WorldRig
    pose: Pose2
    pose_index: int
    echo_source: np.ndarray
    echo_index: np.ndarray
    echo_range: np.ndarray
    model: WorldModel

    @property
    def n_steps(self) -> int:
        return int(self.gamma_measured.shape[0])


def simulate_world_scan(
    model: WorldModel | World,
    pose_index: int,
    *,
    rig: WorldRig | None = None,
    seed: int | np.random.Generator = 0,
    with_waveforms: bool = True,
) -> WorldScan:
    """One sweep of the world's scanner at pose ``pose_index``: servo, echoes, times of flight, waveforms.

    The same seed gives the same bytes.
    """
    if isinstance(model, World):
        model = build_model(model)
    world = model.world
    if not 0 <= pose_index < len(world.poses):
        raise ConfigError(f"pose {pose_index} does not exist; the world has {len(world.poses)} poses")
    rig = rig or world_rig(world)
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    commanded = rig.gamma_commanded()
    goal = rig.servo.to_raw(commanded)
    settle = rng.standard_normal(commanded.shape) * rig.servo.position_error
    gamma_true = rig.servo.to_gamma(goal) + settle
    raw = np.clip(rig.servo.to_raw(gamma_true), 0, 1023)
    gamma_measured = rig.servo.to_gamma(raw)
    pose = world.poses[pose_index]
    rotation, translation = pose_frame(rig, pose)
    echoes = world_echo_table(model, rig, rotation, translation, gamma_true)
    echo_range, source, index, tof, waveforms = shots_from_echoes(rig, echoes, rng, with_waveforms=with_waveforms)
    c = rig.sound_speed
    return WorldScan(
        gamma_commanded=commanded,
        gamma_measured=gamma_measured,
        gamma_raw=raw,
        gamma_true=gamma_true,
        tof=tof,
        distance=c * tof / 2.0,
        waveforms=waveforms,
        sample_rate=float(rig.sample_rate),
        t0=float(rig.window_start),
        sound_speed=c,
        temperature=float(rig.temperature),
        geometry=rig.geometry,
        rig=rig,
        pose=pose,
        pose_index=int(pose_index),
        echo_source=source,
        echo_index=index,
        echo_range=echo_range,
        model=model,
    )
