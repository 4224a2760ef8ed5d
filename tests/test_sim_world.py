"""The world renderer's echoes against geometry worked out by hand.

Every expected range below is written from the scene's numbers (mirror images,
distances to edge lines and vertices), with the capsule positions written out
for each mount, never taken from the renderer's own helpers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lelsonar.errors import ConfigError
from lelsonar.signal.directivity import piston_directivity
from lelsonar.sim import Scene, SimConfig, echo_table
from lelsonar.sim.acoustics import Receiver
from lelsonar.sim.scan import EchoSource
from lelsonar.sim.world import parse_world
from lelsonar.sim.world_geometry import ElementKind, build_model
from lelsonar.sim.world_render import pose_frame, simulate_world_scan, world_echo_table, world_rig

R = 0.03  # radial offset
XS = (-0.12, -0.04, 0.04, 0.12)  # capsules along the rotation axis
H = 0.3  # axis height


def _world(walls, boxes=(), *, mount="fan", ceiling=None, pose=(0.0, 0.0, 0.0), scanner=None):
    data: dict = {"room": {"floor": 0.0}, "scanner": {"mount": mount, "height": H} | (scanner or {})}
    if ceiling is not None:
        data["room"]["ceiling"] = ceiling
    data["wall"] = [{"from": list(a), "to": list(b)} for a, b in walls]
    data["box"] = [{"center": list(c), "size": list(s), "yaw": y} for c, s, y in boxes]
    data["pose"] = [{"x": pose[0], "y": pose[1], "heading": pose[2]}]
    return parse_world(data, "test.toml")


def _fan_capsules(gamma: float) -> np.ndarray:
    """Fan mount, robot at the origin heading +x: the axis is vertical, γ turns the beam from +x towards +y."""
    return np.array([[R * math.cos(gamma), R * math.sin(gamma), H + x] for x in XS])


def _table(world, gamma_deg):
    model = build_model(world)
    rig = world_rig(world)
    rot, trans = pose_frame(rig, world.poses[0])
    table = world_echo_table(model, rig, rot, trans, np.radians([gamma_deg]))
    return model, rig, table


def _slot(model, kind, label):
    hits = [i for i, e in enumerate(model.elements) if e.kind == kind and e.label == label]
    assert len(hits) == 1, (kind, label, [e.label for e in model.elements if e.kind == kind])
    return hits[0]


def _mirror_amplitude(rig, r, psi, refl=0.95):
    c = rig.sound_speed
    ka = 2 * math.pi * rig.acoustics.frequency / c * rig.acoustics.capsule_radius
    return refl * piston_directivity(psi, ka) ** 2 * 10 ** (-rig.acoustics.absorption_db_per_m * 2 * r / 20) / (2 * r)


def test_a_wall_echoes_from_the_mirror_image_of_each_capsule():
    world = _world([((2.0, -5.0), (2.0, 5.0))])
    for gamma in (0.0, 20.0, -35.0):
        model, rig, table = _table(world, gamma)
        k = _slot(model, ElementKind.MIRROR, "wall1")
        g = math.radians(gamma)
        caps = _fan_capsules(g)
        expected = 2.0 - caps[:, 0]  # perpendicular distance to x = 2
        np.testing.assert_allclose(table.range[0, :, k], expected, atol=1e-12)
        # The normal is off the boresight by γ: amplitude D(γ)²·absorption/(2r).
        np.testing.assert_allclose(table.amplitude[0, :, k], _mirror_amplitude(rig, expected, abs(g)), rtol=1e-12)
        assert (table.source[0, :, k] == EchoSource.PLANE_OTHER).all()


@pytest.mark.parametrize("tilt_deg", [15.0, -25.0])
def test_a_tilted_scanner_s_capsules_see_a_wall_at_their_own_leaned_ranges(tilt_deg, tmp_path):
    # The mount turned by τ about the robot's lateral axis: the vertical axis leans to (−sin τ, 0, cos τ) and the
    # γ beam runs along (cos γ cos τ, sin γ, cos γ sin τ).  Capsule i sits at H·z + x_i·axis + R·beam, so its
    # perpendicular distance to the wall x = D is D + x_i sin τ − R cos γ cos τ, seen cos ψ = cos γ cos τ off
    # the wall's normal.
    d = 2.0
    tau = math.radians(tilt_deg)
    world = _world([((d, -5.0), (d, 5.0))], scanner={"tilt": tilt_deg})
    for gamma in (0.0, 25.0):
        model, rig, table = _table(world, gamma)
        k = _slot(model, ElementKind.MIRROR, "wall1")
        g = math.radians(gamma)
        expected = np.array([d + x * math.sin(tau) - R * math.cos(g) * math.cos(tau) for x in XS])
        np.testing.assert_allclose(table.range[0, :, k], expected, atol=1e-12)
        psi = math.acos(math.cos(g) * math.cos(tau))
        np.testing.assert_allclose(table.amplitude[0, :, k], _mirror_amplitude(rig, expected, psi), rtol=1e-12)
    # The pose a scan announces is the tilted array's: its γ = 0 beam raised by τ.
    path = tmp_path / "tilted.toml"
    path.write_text(
        f"[scanner]\nheight = {H}\ntilt = {tilt_deg}\n[[wall]]\nfrom = [{d}, -5.0]\nto = [{d}, 5.0]\n"
        "[[pose]]\nx = 0.0\ny = 0.0\n[odometry]\ntranslation_noise = 0.0\nrotation_noise = 0.0\n"
        "heading_noise = 0.0\n"
    )
    from lelsonar.acquire.world_scans import prepare_world
    from lelsonar.geometry import matrix_from_quaternion

    o = prepare_world(path).pose_message(0).orientation
    beam = matrix_from_quaternion((o.x, o.y, o.z, o.w)) @ np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(beam, [math.cos(tau), 0.0, math.sin(tau)], atol=1e-12)


@pytest.mark.parametrize("width_deg", [20.0, 60.0])
def test_the_capsules_beam_width_is_where_a_wall_s_echo_halves(width_deg):
    from scipy.optimize import brentq
    from scipy.special import j1, jn_zeros

    # A level fan facing the wall x = 2: at γ the beam is γ off the normal and the mirror range is 2 − R cos γ.
    # With the beam width W, the echo at γ = W/2 is half the face-on one once its longer path is undone; past
    # the piston's first null (ka sin γ = j₁,₁ with ka from W) there is no mirror echo.
    world = _world([((2.0, -5.0), (2.0, 5.0))], scanner={"beam_width": width_deg})
    half = math.radians(width_deg) / 2
    alpha = world_rig(world).acoustics.absorption_db_per_m

    def echo(gamma):
        model, _rig, table = _table(world, math.degrees(gamma))
        k = _slot(model, ElementKind.MIRROR, "wall1")
        return table.range[0, 0, k], table.amplitude[0, 0, k]

    r0, a0 = echo(0.0)
    r1, a1 = echo(half)
    assert (r0, r1) == pytest.approx((2.0 - R, 2.0 - R * math.cos(half)), abs=1e-12)
    path = (r1 / r0) * 10 ** (alpha * 2 * (r1 - r0) / 20)  # spreading 1/(2r) and absorption over 2r
    assert a1 * path / a0 == pytest.approx(0.5, rel=1e-9)
    x_half = brentq(lambda x: 2 * j1(x) / x - 1 / math.sqrt(2), 0.5, 3.0, xtol=1e-15)
    ka = x_half / math.sin(half)
    if ka > jn_zeros(1, 1)[0]:
        null = math.asin(jn_zeros(1, 1)[0] / ka)
        assert np.isfinite(echo(null - math.radians(0.5))[0])
        assert np.isnan(echo(null + math.radians(0.5))[0])
    # Without the key, the simulator's own capsule.
    level = world_rig(_world([((2.0, -5.0), (2.0, 5.0))]))
    assert level.acoustics.capsule_radius == 0.007 and level.tilt == 0.0


def test_a_wall_outside_the_main_lobe_gives_no_mirror_echo():
    world = _world([((2.0, -5.0), (2.0, 5.0))])
    model, _rig, table = _table(world, 60.0)  # first null of a 7 mm piston at 40 kHz: 48°
    assert np.isnan(table.range[0, :, _slot(model, ElementKind.MIRROR, "wall1")]).all()


def test_a_right_corner_returns_the_double_bounce_from_the_edge_and_the_triple_from_its_foot():
    # Walls x = 2 (y ≤ 2) and y = 2 (x ≤ 2) meet at (2, 2); the beam points at the edge at γ = 45°.
    world = _world([((2.0, -3.0), (2.0, 2.0)), ((2.0, 2.0), (-3.0, 2.0))])
    model, _rig, table = _table(world, 45.0)
    caps = _fan_capsules(math.radians(45.0))
    horizontal = np.hypot(2.0 - caps[:, 0], 2.0 - caps[:, 1])  # = 2√2 − r
    np.testing.assert_allclose(horizontal, 2 * math.sqrt(2) - R, atol=1e-12)
    dihedral = _slot(model, ElementKind.DIHEDRAL, "wall1|wall2@2,2:225")
    np.testing.assert_allclose(table.range[0, :, dihedral], horizontal, atol=1e-12)
    assert (table.source[0, :, dihedral] == EchoSource.CORNER).all()
    trihedral = _slot(model, ElementKind.TRIHEDRAL, "wall1|wall2|floor@2,2:225")
    np.testing.assert_allclose(table.range[0, :, trihedral], np.hypot(horizontal, caps[:, 2]), atol=1e-12)
    assert (table.source[0, :, trihedral] == EchoSource.TRIHEDRAL).all()


def test_the_foot_of_a_wall_is_a_dihedral_with_the_floor():
    world = _world([((2.0, -5.0), (2.0, 5.0))])
    model, _rig, table = _table(world, 0.0)
    caps = _fan_capsules(0.0)
    k = _slot(model, ElementKind.DIHEDRAL, "wall1|floor")
    np.testing.assert_allclose(table.range[0, :, k], np.hypot(2.0 - caps[:, 0], caps[:, 2]), atol=1e-12)


def test_the_first_echo_over_the_threshold_sets_the_range():
    # At γ = 45° in the corner, the mirrors are 45° off their normals (near the null): the corner answers first
    # over the threshold, though the mirror of wall 1 is nearer.
    world = _world([((2.0, -3.0), (2.0, 2.0)), ((2.0, 2.0), (-3.0, 2.0))])
    quiet = Receiver(tof_jitter=0.0, cycle_slip_probability=0.0)
    rig = world_rig(world, receiver=quiet)
    rig = type(rig)(**{**rig.__dict__, "gamma_start": math.radians(45.0), "gamma_stop": math.radians(46.0), "steps": 2})
    scan = simulate_world_scan(world, 0, rig=rig, seed=1)
    gamma = scan.gamma_true[0]
    caps = _fan_capsules(gamma)
    np.testing.assert_allclose(scan.distance[0], np.hypot(2.0 - caps[:, 0], 2.0 - caps[:, 1]), atol=1e-9)
    assert (scan.echo_source[0] == EchoSource.CORNER).all()
    # The wall's mirror image is nearer, but 45° off its normal it is under the threshold.
    assert np.all(2.0 - caps[:, 0] < scan.distance[0])


def test_a_free_wall_end_diffracts_from_its_edge():
    # Wall x = 1.2 from y = 0.4 upwards: its end (1.2, 0.4) is a free vertical edge.
    world = _world([((1.2, 0.4), (1.2, 5.0))])
    gamma = math.degrees(math.atan2(0.4, 1.2))
    model, rig, table = _table(world, gamma)
    caps = _fan_capsules(math.radians(gamma))
    k = _slot(model, ElementKind.EDGE, "wall1@1.2,0.4:270")
    expected = np.hypot(1.2 - caps[:, 0], 0.4 - caps[:, 1])
    np.testing.assert_allclose(table.range[0, :, k], expected, atol=1e-12)
    # Weak: the edge gain times a mirror at that range, on the boresight.
    weak = rig.edge_gain * _mirror_amplitude(rig, expected, 0.0)
    np.testing.assert_allclose(table.amplitude[0, :, k], weak, rtol=1e-6)
    assert (table.source[0, :, k] == EchoSource.EDGE).all()
    # The foot of the perpendicular on the wall's plane (y ≈ 0.007) is off the wall: no mirror echo.
    assert np.isnan(table.range[0, :, _slot(model, ElementKind.MIRROR, "wall1")]).all()


def test_a_box_shadows_the_wall_behind_it_and_a_low_box_does_not():
    wall = ((3.0, -3.0), (3.0, 3.0))
    tall = _world([wall], [((1.5, 0.0), (0.4, 0.6, 0.5), 0.0)])
    model, _rig, table = _table(tall, 0.0)
    caps = _fan_capsules(0.0)
    assert np.isnan(table.range[0, :, _slot(model, ElementKind.MIRROR, "wall1")]).all()
    # The box's face x = 1.3 answers instead.
    np.testing.assert_allclose(table.range[0, :, _slot(model, ElementKind.MIRROR, "box1.side4")], 1.3 - caps[:, 0])
    # A box 10 cm high is below every capsule (the lowest is 18 cm up): the wall is seen over it.
    low = _world([wall], [((1.5, 0.0), (0.4, 0.6, 0.1), 0.0)])
    model, _rig, table = _table(low, 0.0)
    np.testing.assert_allclose(table.range[0, :, _slot(model, ElementKind.MIRROR, "wall1")], 3.0 - caps[:, 0])
    # Pointed at the box's corner (1.3, 0.3), the nearest vertical edge echo is that corner's diffraction.
    model, _rig, table = _table(tall, math.degrees(math.atan2(0.3, 1.3)))
    caps = _fan_capsules(math.atan2(0.3, 1.3))
    corner = [i for i, e in enumerate(model.elements) if e.kind == ElementKind.EDGE and e.sector is not None]
    ranges = table.range[0][:, corner]
    np.testing.assert_allclose(np.nanmin(ranges, axis=1), np.hypot(1.3 - caps[:, 0], 0.3 - caps[:, 1]), atol=1e-12)


def test_a_doorway_lets_the_sound_through_to_the_wall_beyond():
    # Wall y = 1 with a gap for x in [-0.5, 0.5]; wall y = 3 behind it.  At γ = 90° the beam looks along +y.
    world = _world([((-3.0, 1.0), (-0.5, 1.0)), ((0.5, 1.0), (3.0, 1.0)), ((-3.0, 3.0), (3.0, 3.0))])
    model, _rig, table = _table(world, 90.0)
    caps = _fan_capsules(math.pi / 2)
    np.testing.assert_allclose(table.range[0, :, _slot(model, ElementKind.MIRROR, "wall3")], 3.0 - caps[:, 1])
    assert np.isnan(table.range[0, :, _slot(model, ElementKind.MIRROR, "wall1")]).all()
    assert np.isnan(table.range[0, :, _slot(model, ElementKind.MIRROR, "wall2")]).all()


def test_the_paper_mount_in_a_world_gives_the_l_corner_simulator_s_echoes():
    # The paper's L: a wall 1.57 m ahead, a ceiling 1.06 m above the axis.  The L simulator's panels are finite;
    # where both have an echo, the two renderers agree to rounding.
    ceiling = H + 1.06
    world = _world([((1.57, -5.0), (1.57, 5.0))], mount="paper", ceiling=ceiling)
    model = build_model(world)
    rig = world_rig(world)
    rot, trans = pose_frame(rig, world.poses[0])
    gamma = np.radians(np.linspace(-10, 110, 61))
    got = world_echo_table(model, rig, rot, trans, gamma)
    cfg = SimConfig(scene=Scene.l_corner(1.57, 1.06, width=3.0, height_a=3.0, height_b=3.0))
    ref = echo_table(cfg, gamma)
    pairs = (
        (_slot(model, ElementKind.MIRROR, "wall1"), 0),
        (_slot(model, ElementKind.MIRROR, "ceiling"), 1),
        (_slot(model, ElementKind.DIHEDRAL, "wall1|ceiling"), 2),
    )
    for mine, theirs in pairs:
        both = np.isfinite(got.range[..., mine]) & np.isfinite(ref.range[..., theirs])
        assert both.sum() > 20
        np.testing.assert_allclose(got.range[..., mine][both], ref.range[..., theirs][both], atol=1e-9)
        np.testing.assert_allclose(got.amplitude[..., mine][both], ref.amplitude[..., theirs][both], rtol=1e-9)


def test_a_world_file_error_names_the_key_and_the_fix():
    with pytest.raises(ConfigError, match=r"\[\[wall\]\] #1 needs 'to'; write to = \[4.0, 0.0\]"):
        parse_world({"wall": [{"from": [0, 0]}], "pose": [{"x": 1, "y": 1}]}, "w.toml")
    with pytest.raises(ConfigError, match=r"unknown key 'hieght' in \[\[wall\]\] #1"):
        parse_world({"wall": [{"from": [0, 0], "to": [1, 0], "hieght": 2}], "pose": [{"x": 1, "y": 1}]}, "w.toml")
    with pytest.raises(ConfigError, match=r"'mount' must be one of fan, paper"):
        parse_world(
            {"wall": [{"from": [0, 0], "to": [1, 0]}], "scanner": {"mount": "side"}, "pose": [{"x": 1, "y": 1}]}
        )
    with pytest.raises(ConfigError, match=r"'sweep' must rise within ±149.7°"):
        parse_world(
            {"wall": [{"from": [0, 0], "to": [1, 0]}], "scanner": {"sweep": [-180, 180]}, "pose": [{"x": 1, "y": 1}]}
        )
    with pytest.raises(ConfigError, match=r"within 0.08 m of wall"):
        parse_world({"wall": [{"from": [0, 0], "to": [4, 0]}], "pose": [{"x": 1, "y": 0.02}]})
    with pytest.raises(ConfigError, match=r"no \[\[pose\]\]"):
        parse_world({"wall": [{"from": [0, 0], "to": [4, 0]}]})
    with pytest.raises(ConfigError, match=r"\[scanner\] 'tilt' must be in \[-45, 45\], got 60; write tilt = -10.0"):
        _world([((2.0, -5.0), (2.0, 5.0))], scanner={"tilt": 60})
    with pytest.raises(
        ConfigError, match=r"\[scanner\] 'beam_width' must be in \[6, 170\], got 2; write beam_width = 40"
    ):
        _world([((2.0, -5.0), (2.0, 5.0))], scanner={"beam_width": 2})
    with pytest.raises(ConfigError, match=r"'beam_width' must be a finite number"):
        _world([((2.0, -5.0), (2.0, 5.0))], scanner={"beam_width": "wide"})


def test_the_example_worlds_load_and_scan(tmp_path):
    from pathlib import Path

    from lelsonar.sim.world import load_world

    root = Path(__file__).resolve().parents[1] / "examples" / "worlds"
    names = sorted(p.stem for p in root.glob("*.toml"))
    assert {"room", "l_room", "corridor", "maze", "boxes"} <= set(names)
    for name in names:
        world = load_world(root / f"{name}.toml")
        scan = simulate_world_scan(world, 0, seed=0, with_waveforms=False)
        # Most beams of a closed world find a surface.
        assert np.isfinite(scan.distance).mean() > 0.5, name


def test_a_wall_ending_on_another_makes_two_right_corners_and_no_edge():
    # Wall 2 runs from (0, -1) up to wall 1 (y = 2) and ends on its middle: a T with two concave corners.
    world = _world([((-3.0, 2.0), (3.0, 2.0)), ((0.0, -1.0), (0.0, 2.0))], pose=(1.0, 0.0, 0.0))
    model = build_model(world)
    at_t = [e for e in model.elements if "@0,2:" in e.label]
    assert sorted(e.kind.name for e in at_t) == ["DIHEDRAL", "DIHEDRAL", "TRIHEDRAL", "TRIHEDRAL"]
    # From (1, 0), the beam towards the junction (heading atan2(2, −1)) sees the corner on its side.
    gamma = math.degrees(math.atan2(2.0, -1.0))
    rig = world_rig(world)
    rot, trans = pose_frame(rig, world.poses[0])
    table = world_echo_table(model, rig, rot, trans, np.radians([gamma]))
    caps = _fan_capsules(math.radians(gamma)) + np.array([1.0, 0.0, 0.0])
    k = _slot(model, ElementKind.DIHEDRAL, "wall1|wall2@0,2:315")  # the sector x > 0, y < 2
    np.testing.assert_allclose(table.range[0, :, k], np.hypot(0.0 - caps[:, 0], 2.0 - caps[:, 1]), atol=1e-12)
    tri = _slot(model, ElementKind.TRIHEDRAL, "wall1|wall2|floor@0,2:315")
    horizontal = np.hypot(0.0 - caps[:, 0], 2.0 - caps[:, 1])
    np.testing.assert_allclose(table.range[0, :, tri], np.hypot(horizontal, caps[:, 2]), atol=1e-12)
    # The other corner of the T (x < 0, its bisector at 225°) is behind wall 2 from here: no echo.
    others = [i for i, e in enumerate(model.elements) if "@0,2:225" in e.label]
    assert len(others) == 2 and np.isnan(table.range[0][:, others]).all()


def test_the_diffuse_echo_comes_from_where_the_boresight_meets_the_first_surface():
    # At γ = 60° the wall x = 2 is outside the main lobe for a mirror echo; the boresight still meets it.
    world = _world([((2.0, -5.0), (2.0, 5.0))])
    g = math.radians(60.0)
    _model, _rig, table = _table(world, 60.0)
    caps = _fan_capsules(g)
    np.testing.assert_allclose(table.range[0, :, -1], (2.0 - caps[:, 0]) / math.cos(g), atol=1e-12)
    assert (table.source[0, :, -1] == EchoSource.DIFFUSE).all()
    # A box in the way is met first.
    boxed = _world([((2.0, -5.0), (2.0, 5.0))], [((1.0, 1.4), (0.4, 0.4, 0.6), 0.0)])
    _model, _rig, table = _table(boxed, 60.0)
    # The box's face x = 0.8 (y 1.2…1.6): the boresight from each capsule reaches it at t = (0.8 − x_c)/cos γ.
    t = (0.8 - caps[:, 0]) / math.cos(g)
    assert np.all(np.abs(caps[:, 1] + t * math.sin(g) - 1.4) <= 0.2)
    np.testing.assert_allclose(table.range[0, :, -1], t, atol=1e-12)


def test_simulate_world_draws_the_world_and_reports_each_pose(tmp_path, capsys):
    from pathlib import Path

    from lelsonar.cli.main import main as lelsonar_main

    root = Path(__file__).resolve().parents[1] / "examples" / "worlds"
    out = tmp_path / "boxes.png"
    assert lelsonar_main(["simulate", "--world", str(root / "boxes.toml"), "--plot", str(out)]) == 0
    text = capsys.readouterr().out
    assert "world boxes: 4 walls, 2 boxes" in text and text.count("pose ") == 2
    assert out.stat().st_size > 10_000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
