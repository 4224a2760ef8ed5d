"""Scans from another writer of the contract: every field reconstruction reads, filled otherwise.

The scans come from :mod:`tests.foreign_scenes`, a simulator independent of
``lelsonar.sim`` (its own beam, burst, comparator, noise and floor),
written with its own conventions, recorded with the project's recorder and
reconstructed through ``reconstruct --source --json``.  Each plane is judged
against the scene's truth as the stress sweep judges it: a failure (patch
error > 2 cm and > 3× the oracle's) must never claim ``good``; a convention
the contract allows must give the same planes as our own writer's.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.errors import InvalidMessageError, SchemaVersionError
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.scan_start import geometry_from_start
from lelsonar.signal.energy import echo_amplitude, waveform_energy

from . import foreign_scenes as fs
from .conftest import make_sample, make_scan_start


# ----------------------------------------------------------------------------- the foreign scan, once
@pytest.fixture(scope="module")
def scan() -> fs.ForeignScan:
    rig = fs.ForeignRig(seed=3, steps=150)
    s = fs.simulate(rig)
    s.energy_model = fs.energy_model(rig)
    return s


def _run(tmp_path, scan: fs.ForeignScan, conv: fs.Conventions, name: str = "f"):
    path = fs.write_scan(tmp_path / f"{name}.mcap", scan, conv)
    code, lines, err = fs.run_cli(path)
    planes = [p for msg in lines for p in msg.get("planes", [])]
    return code, lines, err, fs.judge(scan, planes)


def _accurate(verdicts: dict) -> None:
    for label, row in verdicts.items():
        assert row["verdict"] == "accurate", (label, row)
        assert row["quality"] == "good", (label, row)


@pytest.fixture(scope="module")
def baseline(scan, tmp_path_factory):
    """Our own writer's conventions: both walls accurate and good (the simulator is sound)."""
    code, lines, _, verdicts = _run(tmp_path_factory.mktemp("base"), scan, fs.Conventions())
    assert code == 0
    _accurate(verdicts)
    return lines[0]


def _same_planes(lines: list[dict], baseline: dict) -> None:
    """The same planes as the baseline's, to float noise (only γ from the commanded angles may differ)."""
    got = {p["label"]: p for p in lines[0]["planes"]}
    for p in baseline["planes"]:
        q = got[p["label"]]
        n0, n1 = (np.array([x["normal"].get(a, 0.0) for a in "xyz"]) for x in (p, q))
        assert math.degrees(math.acos(min(1.0, float(n0 @ n1)))) < 0.5
        assert abs(p["offset"] - q["offset"]) < 0.003


# ----------------------------------------------------------------------------- allowed conventions
#: Everything another writer may do within the contract (or leave at proto3's default) at once:
#: capsule ids from 1, the radial offset only in the capsules' positions, "no echo" as NaN, the range
#: as a time of flight only, γ measured unset, the ScanStart's sample rate and speed of sound unset
#: (the air temperature is there), no acquisition times, no rotation axis, int16 waveforms without a scale.
EVERYTHING_FOREIGN = fs.Conventions(
    capsule_id_base=1,
    radial_offset_in="position",
    no_echo="nan",
    fill="tof",
    gamma="commanded",
    start_sample_rate=False,
    start_sound_speed=False,
    acquisition_time=False,
    rotation_axis=(0.0, 0.0, 0.0),
    int16_scale=False,
)


def test_every_allowed_convention_at_once_gives_our_writers_planes(scan, baseline, tmp_path):
    # Before: every Sample refused (capsule ids, tof unset, NaN), or with a 0 radial offset no plane at all.
    code, lines, _, verdicts = _run(tmp_path, scan, EVERYTHING_FOREIGN)
    assert code == 0
    _accurate(verdicts)
    _same_planes(lines, baseline)


@pytest.mark.parametrize(
    "conv",
    [
        fs.Conventions(radial_offset_in="position"),  # before: radial offset 0, no plane (exit 1)
        fs.Conventions(fill="distance", ids_reversed=True, gamma_wrap=True, encoding="float32"),  # before: all refused
    ],
)
def test_single_conventions_give_our_writers_planes(scan, baseline, tmp_path, conv):
    code, lines, _, verdicts = _run(tmp_path, scan, conv)
    assert code == 0
    _accurate(verdicts)
    _same_planes(lines, baseline)


def test_a_scan_without_waveforms_is_reconstructed_from_its_ranges(scan, tmp_path):
    # Before: no waveform energy, no energy peak, so "no step with an echo yet" and no plane (exit 1).
    code, _, _, verdicts = _run(tmp_path, scan, fs.Conventions(waveforms=False))
    assert code == 0
    _accurate(verdicts)


# ----------------------------------------------------------------------------- against the contract
@pytest.mark.parametrize(
    ("conv", "why"),
    [
        # Before: 77 cm and 51 cm off, both planes "good" (the ranges came out half the truth).
        (fs.Conventions(fill="tof", tof_scale=0.5), "no echo starting at the readings' time of flight"),
        # Before: 1.5 m off, only "degraded".
        (fs.Conventions(fill="distance", distance_scale=2.0), "no echo starting at the readings' time of flight"),
        (fs.Conventions(distance_scale=2.0), "off c·time_of_flight/2"),
        # Before: 50 cm off, flagged only by chance of the fit.
        (fs.Conventions(gamma_unit="deg"), "beyond a turn"),
    ],
)
def test_ranges_or_angles_in_another_convention_are_never_good(scan, tmp_path, conv, why):
    code, lines, _, verdicts = _run(tmp_path, scan, conv)
    assert code in (0, 1)
    for label, row in verdicts.items():
        assert row["verdict"] != "claims_good", (label, row)
        assert row["quality"] == "unreliable", (label, row)
        assert any(why in r for r in row["reasons"]), row["reasons"]


def test_waveforms_whose_start_time_was_left_unset_are_not_trusted(tmp_path):
    # The window starts 1 ms after firing but Waveform.t0 says 0: every echo sits 1 ms earlier in the samples
    # than its time of flight says, and the amplitudes read there are not the echoes'.
    scan = fs.simulate(fs.ForeignRig(seed=3, steps=100, t0=1.0e-3))
    code, _, _, verdicts = _run(tmp_path, scan, fs.Conventions(energy_model=False, t0=False))
    assert code == 0
    for row in verdicts.values():
        assert row["quality"] == "unreliable" and row["verdict"] != "claims_good", row
        assert any("waveform.t0" in r for r in row["reasons"])


def test_a_stated_speed_of_sound_that_contradicts_the_readings_degrades(scan, tmp_path):
    # 335 m/s stated, 343 m/s in the air: distance and time of flight disagree by 2.5 %.
    code, _, _, verdicts = _run(tmp_path, scan, fs.Conventions(stated_sound_speed=335.0))
    assert code == 0
    for row in verdicts.values():
        assert row["verdict"] == "accurate" and row["quality"] == "degraded"
        assert any("speed of sound 335.0" in r for r in row["reasons"])


def test_echo_valid_never_set_is_named_as_the_failure(scan, tmp_path):
    # Before: "too few points (no step with an echo yet)", nothing said why.
    code, lines, _, verdicts = _run(tmp_path, scan, fs.Conventions(echo_valid=False))
    assert code == 1
    assert all(v["verdict"] == "missing" for v in verdicts.values())
    assert any("set echo_valid = true" in f for f in lines[0]["failures"])


def test_a_rotation_axis_other_than_x_is_refused_by_name(scan, tmp_path):
    code, lines, err, _ = _run(tmp_path, scan, fs.Conventions(rotation_axis=(-1.0, 0.0, 0.0)))
    assert code == 1 and not lines
    assert "rotation_axis" in err or "InvalidMessageError" in err


# ----------------------------------------------------------------------------- the physics
def _assembled(scan: fs.ForeignScan, conv: fs.Conventions = fs.Conventions()) -> ScanAssembly:
    msgs = fs.messages(scan, conv)
    assembly = ScanAssembly(_decoded(msgs[0]))
    for m in msgs[1:-1]:
        assembly.add(_decoded(m))
    return assembly


def test_a_comparator_whose_crossing_walks_with_amplitude_is_re_timed(scan, tmp_path):
    """The foreign board times the first threshold crossing of the rectified waveform, so weaker echoes read
    farther (by up to 12 mm here).  Reconstruction re-times them from the waveforms and says so; against the
    scene's truth the ranges it uses no longer follow the echoes' amplitude."""
    code, _, _, verdicts = _run(tmp_path, scan, fs.Conventions())
    assert code == 0
    for row in verdicts.values():
        assert row["verdict"] == "accurate" and row["quality"] == "good", row
        assert any("re-timed" in r for r in row["reasons"]), row["reasons"]
    assembly = _assembled(scan)
    steps, _, writer, _ = assembly.arrays()
    used = assembly.walk_free(writer)
    pos = fs._positions(scan.rig, scan.gamma)
    truth = np.full(writer.shape, np.nan)
    for src, panel in enumerate(scan.scene.panels[:2], start=1):
        mine = scan.source == src
        truth[mine] = panel.offset - pos[mine] @ np.asarray(panel.normal)
    amplitude = np.log(assembly.echo_amplitude[steps])
    ok = np.isfinite(truth) & np.isfinite(used) & np.isfinite(amplitude)
    assert ok.sum() > 300

    def slope(r):  # m of range error per e-fold of amplitude
        return np.polyfit(amplitude[ok], (r - truth)[ok], 1)[0]

    # Before: -5.8 mm per e-fold (the board's 1.5 mm jitter over ~430 echoes makes a slope's σ ~0.1 mm).  What
    # is left (-0.4 mm) is the envelope's noise floor (4 mV, coloured) pulling the weakest echoes' fraction
    # earlier: under a tenth of the walk.
    assert slope(writer) < -0.004
    assert abs(slope(used)) < 0.1 * abs(slope(writer))


#: Rigs of the random foreign sweep whose re-timed walls claimed ``good`` 11–13° off: the L rolled by ±8–11°,
#: long bursts, echoes strong enough to clip near the walls' normals (the amplitude peak lost), the re-timed
#: echoes of each wall on one side of its normal.
_ROLLED_CLIPPING_RIGS = {
    "seed 11": fs.ForeignRig(
        distance_a=1.7481946561002875,
        distance_b=2.003745894058394,
        roll=-0.19742228651397592,
        radial_offset=0.021012352630445173,
        gamma_start=-0.28174664965048796,
        gamma_stop=1.392321566162817,
        steps=116,
        reverse=True,
        beam_sigma=0.13642951292433952,
        burst=0.0007689970719750652,
        echo_scale=3.222852886142999,
        corner_gain=1.1165903732217073,
        noise=0.006965586572651194,
        threshold=0.04579730152622839,
        seed=11,
    ),
    "seed 43": fs.ForeignRig(
        distance_a=0.6094383090974915,
        distance_b=0.5500739671855421,
        roll=0.1420890342962498,
        radial_offset=0.021141371911175027,
        gamma_start=-0.007522755124996004,
        gamma_stop=1.9731767460941156,
        steps=195,
        beam_sigma=0.16915191392909396,
        burst=0.00045198674582976083,
        echo_scale=2.4198475189052115,
        corner_gain=1.9374404109097325,
        noise=0.003507697229670492,
        threshold=0.07243311684281299,
        seed=43,
    ),
}


@pytest.mark.parametrize("name", sorted(_ROLLED_CLIPPING_RIGS))
def test_a_roll_read_from_re_timed_ranges_is_good_only_within_its_standard_error(tmp_path, name):
    """Re-timed ranges still walk by a millimetre or so on the weakest echoes (the noise lifts a weak echo's
    envelope peak, so its constant fraction comes late), and through the capsules' 2 cm radial lever arm a
    tenth of a millimetre across a wall's echoes is a degree of roll.  Where the amplitude peak is lost the
    wall's direction rests on those ranges: before, both walls were "good" 7–14° off at σ 1.5–2.3° (|z| 5–9).
    A good plane's normal must lie within 3 of its own standard errors of the truth (the verdict's σ is the
    plane's claim; 3σ of a 2-D tilt is passed by chance ~1 % of the time), and no failure may claim good."""
    scan = fs.simulate(_ROLLED_CLIPPING_RIGS[name])
    code, lines, _, verdicts = _run(tmp_path, scan, fs.Conventions())
    assert code == 0
    final = [m for m in lines if m.get("status") == "final"]
    assert len(final) == 1
    sigma = {p["label"]: p["normal_stderr"] for p in final[0]["planes"]}
    for label, row in verdicts.items():
        assert any("re-timed" in r for r in row["reasons"]), row
        assert row["verdict"] != "claims_good", (label, row)
        if row["quality"] == "good":
            assert row["angle_deg"] <= 3.0 * np.rad2deg(sigma[label]), (label, row, np.rad2deg(sigma[label]))


@pytest.mark.xfail(
    strict=True,
    reason="known gap: a one-sided sweep whose wall echoes all clip leaves the direction to "
    "the ranges, which a late-firing comparator turns. Re-timing (echo_timing) cannot help: 236 of "
    "the 256 echoes clip (a clipped peak has no constant fraction), and the 20 that do not, all weak, "
    "show the walk at only 1.3 standard errors. Degrading every one-sided wall cost 36 of 343 "
    "accurate good planes of `bench estimators --families all --seeds 20`; degrading only clipped "
    "one-sided walls still degraded accurate planes of our simulator's partial sweeps (3 of 571 in "
    "`--stress all --seeds 20`, and a hard scene of test_reconstruct_corner). Neither is done",
)
def test_a_wall_seen_from_one_side_of_its_normal_is_not_good(tmp_path):
    """The L rolled 11°, the sweep (0°..51°, reversed) starting 11° past wall a's normal; a receiver that clips
    every wall echo (no amplitude peak to find) and a comparator whose threshold crossing comes later on weaker,
    off-axis echoes.  Wall a's direction rests on the ranges' lever arm seen from one side, which that range
    bias turns: before, 10° and 3.2 cm off (oracle 0.9 cm) and "good"."""
    rig = fs.ForeignRig(
        distance_a=1.7830363310095811,
        distance_b=1.6938356931615588,
        roll=-0.1903572544171102,
        gamma_start=-0.0033389079129613197,
        gamma_stop=0.8934311199550851,
        steps=64,
        reverse=True,
        beam_sigma=0.3254629289661583,
        burst=0.0006705769242689202,
        echo_scale=4.997552377766458,
        corner_gain=1.3571584212937797,
        crosstalk=0.807290582161242,
        dc=0.15,
        full_scale=0.5,
        gains=(0.5708356164525817, 1.1886958726238408, 0.7073260841899358, 1.584129877091351),
        floor_depth=0.6337890015727393,
        floor_scale=0.37580473655153046,
        seed=45,
    )
    code, _, _, verdicts = _run(tmp_path, fs.simulate(rig), fs.Conventions(energy_model=False))
    assert code == 0
    a = verdicts["a"]
    assert a["patch_cm"] > 2 and a["verdict"] == "flagged", a
    assert any("extrapolated" in r for r in a["reasons"])
    assert all(v["verdict"] != "claims_good" for v in verdicts.values())


#: Rigs of the random foreign sweep (seeds 19 and 15): the L rolled by 10.6° and 10.9°, wall a's amplitude peak
#: not found, so its direction rests on the joint fit, checked against the paper-corrected points.
_ROLLED_NO_PEAK_RIGS = {
    "seed 19": fs.ForeignRig(
        distance_a=2.814673362041759,
        distance_b=1.1846749697457053,
        roll=-0.18428640976336602,
        radial_offset=0.034529809033116296,
        gamma_start=-0.12895602766753753,
        gamma_stop=1.6586405318511017,
        steps=64,
        beam_sigma=0.23634895659325672,
        burst=0.0003869992506942923,
        echo_scale=4.606843728129003,
        corner_gain=1.8993057161275204,
        noise=0.0046872334217392154,
        threshold=0.04055646829943126,
        seed=19,
    ),
    "seed 15": fs.ForeignRig(
        distance_a=2.539542778340144,
        distance_b=1.3610168944821417,
        roll=-0.1906577391260678,
        radial_offset=0.04766485450343573,
        gamma_start=0.01365372887152969,
        gamma_stop=1.9835002208907033,
        steps=195,
        beam_sigma=0.18910626836986846,
        burst=0.00047420580536532283,
        echo_scale=4.886908070733824,
        corner_gain=1.694052438880843,
        noise=0.005996029456673743,
        threshold=0.06906530316847832,
        seed=15,
    ),
}


def _final_sigma(lines: list[dict]) -> dict[str, float]:
    final = [m for m in lines if m.get("status") == "final"]
    assert len(final) == 1
    return {p["label"]: p["normal_stderr"] for p in final[0]["planes"]}


@pytest.mark.parametrize("name", sorted(_ROLLED_NO_PEAK_RIGS))
def test_a_roll_the_joint_fit_measured_does_not_make_the_wall_ambiguous(tmp_path, name):
    """The corrected points (§4) assume the wall's direction in the rotation plane, so on an L rolled by ~11°
    they sit ~11° from the joint fit whatever the data; only the tilt out of that plane is measured by both.
    Before, wall a was within 0.5° of the truth yet unreliable: "its direction is ambiguous: the corrected
    points and the joint fit differ by" the roll."""
    scan = fs.simulate(_ROLLED_NO_PEAK_RIGS[name])
    code, lines, _, verdicts = _run(tmp_path, scan, fs.Conventions())
    assert code == 0
    sigma = _final_sigma(lines)
    a = verdicts["a"]
    # The scene is what it claims: the joint fit found the roll (within 3 of its standard errors of the truth).
    assert a["verdict"] == "accurate" and a["angle_deg"] <= 3.0 * np.rad2deg(sigma["a"]), (a, sigma)
    assert not any("ambiguous" in r for r in a["reasons"]), a["reasons"]
    assert a["quality"] != "unreliable", a
    assert all(v["verdict"] != "claims_good" for v in verdicts.values())


#: Rigs of the random foreign sweep (seeds 13, 53, 64, 4, 44; the L rolled 4–11°) with a wall whose amplitude
#: peak was not found: its joint-fit normal 0.1–2° off the truth, reported ±10–39° (the covariance of its own
#: echoes, whose direction rests on the capsules' few-cm radial lever, not the joint fit's that the edge ties).
_JOINT_WALL_RIGS = [
    fs.ForeignRig(
        distance_a=2.6382562873301474,
        distance_b=2.5275584969608555,
        roll=-0.09992511446148157,
        radial_offset=0.027531201892136856,
        gamma_start=0.10374110730338212,
        gamma_stop=1.7284328228159027,
        steps=171,
        beam_sigma=0.10536256949588771,
        burst=0.0007462443068395029,
        echo_scale=4.92857633361651,
        corner_gain=1.0008152458326385,
        noise=0.0017416714949317741,
        threshold=0.06695627861272857,
        seed=13,
    ),
    fs.ForeignRig(
        distance_a=2.2972766344192523,
        distance_b=1.327817977877488,
        roll=0.1814117551975595,
        radial_offset=0.03518059396258964,
        gamma_start=-0.34323976966892716,
        gamma_stop=1.3007380550835232,
        steps=78,
        beam_sigma=0.2737014291880676,
        burst=0.0007989771408133268,
        echo_scale=3.9133184970277535,
        corner_gain=1.008558364426894,
        noise=0.006398592543437524,
        threshold=0.031092137605588287,
        seed=53,
    ),
    fs.ForeignRig(
        distance_a=1.8083490728518568,
        distance_b=0.6642773435726099,
        roll=-0.07600192128039981,
        radial_offset=0.011889666461423153,
        gamma_start=0.14494616624102083,
        gamma_stop=2.315030912358148,
        steps=188,
        beam_sigma=0.2575292709125941,
        burst=0.0002903242872320636,
        echo_scale=0.45891974798112506,
        corner_gain=1.1853752848711854,
        noise=0.007244160795525226,
        threshold=0.04889240865702877,
        seed=64,
    ),
    fs.ForeignRig(
        distance_a=1.778318882035904,
        distance_b=2.9406092642692605,
        roll=-0.17557899573054184,
        radial_offset=0.04155786870177318,
        gamma_start=0.14471717179932586,
        gamma_stop=2.1395278585743336,
        steps=99,
        beam_sigma=0.14736494551206034,
        burst=0.0007229811645125939,
        echo_scale=2.8565245835884414,
        corner_gain=1.8631011116023837,
        noise=0.004874466499564719,
        threshold=0.043400746668744446,
        seed=4,
    ),
    fs.ForeignRig(
        distance_a=1.1452826869319326,
        distance_b=1.5144268195528277,
        roll=0.1965313126230361,
        radial_offset=0.04706994771014241,
        gamma_start=-0.28489069960304525,
        gamma_stop=1.3992243575869967,
        steps=199,
        reverse=True,
        beam_sigma=0.18729943770243201,
        burst=0.000606633690428322,
        echo_scale=3.1977106063503715,
        corner_gain=1.936910629695899,
        noise=0.009456776307805552,
        threshold=0.038798054660716175,
        seed=44,
    ),
]


def test_a_joint_walls_standard_error_is_the_joint_fits(tmp_path):
    """z = angle error / σ over the ten walls of five rolled Ls, against the scene's truth: a Gaussian's median
    |z| is 0.67, and σ 20× too large gives ~0.03 (before: 0.05); 0.25 leaves room for ten walls' scatter and
    for σ that count a walk the ranges may hide.  No good plane lies beyond 3 of its standard errors."""
    z = []
    for k, rig in enumerate(_JOINT_WALL_RIGS):
        code, lines, _, verdicts = _run(tmp_path, fs.simulate(rig), fs.Conventions(), name=f"r{k}")
        assert code == 0
        sigma = _final_sigma(lines)
        for label, row in verdicts.items():
            assert row["verdict"] == "accurate", (rig.seed, label, row)
            z.append(np.deg2rad(row["angle_deg"]) / sigma[label])
            if row["quality"] == "good":
                assert z[-1] <= 3.0, (rig.seed, label, row, np.rad2deg(sigma[label]))
    assert np.median(z) >= 0.25, np.round(z, 3)


#: Rigs of the wide foreign sweep (seeds 1008, 1022, 1010): a wall 2.8–4.6 m ahead and a sweep starting 30–40°
#: below it, so the floor 0.45 m below the axis answers the beams pointing down before the far wall does.  On
#: main 32–41 % of each scan's echoes fit neither wall nor their edge, and both walls (accurate) were unreliable.
_FLOOR_AHEAD_RIGS = {
    "seed 1008": fs.ForeignRig(
        distance_a=4.121338514325262,
        distance_b=1.3219342973069366,
        roll=0.2026408752589123,
        radial_offset=0.04382797978882796,
        gamma_start=-0.522985031556836,
        gamma_stop=2.5833972257357134,
        steps=106,
        beam_sigma=0.08013072109074708,
        burst=0.00036164713781004423,
        echo_scale=2.0515449305305142,
        corner_gain=0.5669112195008912,
        noise=0.004775653139923942,
        threshold=0.023978155492011384,
        seed=1008,
    ),
    "seed 1022": fs.ForeignRig(
        distance_a=4.616558753464364,
        distance_b=3.0721278669636884,
        roll=0.06118439613583937,
        radial_offset=0.038015561404497016,
        gamma_start=-0.6975801989990393,
        gamma_stop=1.4263626134149066,
        steps=107,
        beam_sigma=0.2422181511026037,
        burst=0.00028302640380694293,
        echo_scale=3.831461897311852,
        corner_gain=1.1737411224135563,
        noise=0.008752533482815569,
        threshold=0.0711902283725994,
        seed=1022,
    ),
    "seed 1010": fs.ForeignRig(
        distance_a=2.818286936813165,
        distance_b=4.613080645633265,
        roll=0.20167594317645832,
        radial_offset=0.04964314160416581,
        gamma_start=-0.598656014697799,
        gamma_stop=2.2263050221011906,
        steps=191,
        beam_sigma=0.32616343461830916,
        burst=0.0002503441444870916,
        echo_scale=3.3404135146255785,
        corner_gain=0.7834213896013921,
        noise=0.0013613163332815731,
        threshold=0.07114731973705621,
        seed=1010,
    ),
}


@pytest.mark.parametrize("name", sorted(_FLOOR_AHEAD_RIGS))
def test_a_floor_answering_before_a_far_wall_does_not_make_the_walls_unreliable(tmp_path, name):
    """The floor's echoes come from beams further off wall a's normal than the wall's own echoes, in front of
    it: a mirror plane there would have answered those nearer face-on beams first, and they heard the wall.
    They say nothing against the walls, whose verdict rests on their own echoes; the share is still named."""
    scan = fs.simulate(_FLOOR_AHEAD_RIGS[name])
    floor = np.count_nonzero(scan.source == 4) / np.count_nonzero(np.isfinite(scan.tof))
    assert floor > 0.15  # the scene's truth: more floor echoes than once made a scan unreliable
    code, _, _, verdicts = _run(tmp_path, scan, fs.Conventions())
    assert code == 0
    for label, row in verdicts.items():
        assert row["verdict"] == "accurate", (label, row)
        assert row["quality"] == "good", (label, row)
        assert any("fit neither wall nor their edge" in r for r in row["reasons"]), row["reasons"]


def test_a_wall_of_few_echoes_beside_a_floor_stays_unreliable(tmp_path):
    """Seed 1030 of the wide sweep: wall a 0.42 m ahead, wall b 4.1 m above seen on 17 echoes, all the corner's
    double bounces 3.6 cm beyond it (a 4.2 cm wrong answer, oracle 1.3 cm); 32 % of the echoes are the floor's,
    behind wall a from beams further off its normal than any it answered.  Wall a, accurate, is good; wall b's
    own evidence is too thin to outweigh the scan's unexplained echoes: it stays unreliable."""
    rig = fs.ForeignRig(
        distance_a=0.4183793600764485,
        distance_b=4.120249906563535,
        roll=0.03142728979553402,
        radial_offset=0.01736572792631874,
        gamma_start=-0.4500875169382161,
        gamma_stop=2.6722660482588316,
        steps=103,
        reverse=True,
        beam_sigma=0.08861165112541602,
        burst=0.00020701329027066385,
        echo_scale=0.9734206478763101,
        corner_gain=1.6047593480878182,
        noise=0.003621990558144156,
        threshold=0.06177420590284422,
        seed=1030,
    )
    code, _, _, verdicts = _run(tmp_path, fs.simulate(rig), fs.Conventions())
    assert code == 0
    a, b = verdicts["a"], verdicts["b"]
    assert a["verdict"] == "accurate" and a["quality"] == "good", a
    assert b["verdict"] != "flagged" or b["quality"] == "unreliable", b


#: The foreign board's comparator at 3.6 σ of a 7 mV receiver noise (threshold 25 mV): over the ~2,000 samples
#: it listens to before a wall's echo comes, the noise crosses it first on about 3 readings in 10.
NOISY_BOARD = fs.ForeignRig(seed=3, steps=150, noise=0.007)


def test_the_readings_a_board_fired_on_noise_are_told_from_its_echoes():
    """Against the scene's truth (the readings no echo had reached when the comparator fired): the noise σ is
    the receiver's, and the readings left out are those, to the few near the level either way."""
    scan = fs.simulate(NOISY_BOARD)
    assembly = _assembled(scan)
    noise, sigma = assembly.noise_triggers()
    truth = np.isfinite(scan.tof) & (scan.source == 0)
    assert truth.sum() > 100  # the scene is what it claims
    # Pooled MAD of ~15,000 AR(1) samples (a few hundred independent ones): within 10 %.
    assert sigma == pytest.approx(NOISY_BOARD.noise, rel=0.1)
    hit = np.count_nonzero(noise & truth)
    assert hit >= 0.85 * truth.sum()  # the noise's crossings over the level: few
    assert hit >= 0.85 * np.count_nonzero(noise)  # weak echoes under it: few
    clean = _assembled(fs.simulate(replace(NOISY_BOARD, noise=0.002)))
    assert not clean.noise_triggers()[0].any()  # 12.5 σ: the noise never fires the board


@pytest.mark.parametrize("noise, qualities", [(0.007, ("good",)), (0.008, ("good", "degraded"))])
def test_readings_a_board_fired_on_noise_are_re_timed_from_the_echo_after_them_and_named(tmp_path, noise, qualities):
    # Before, at 7 mV (3 readings in 10 the noise's): both walls accurate but "30 % of the scan's echoes fit
    # neither wall nor their edge: the walls explain the wrong echoes" (unreliable), the noise's readings
    # counted as echoes the walls failed to explain.  At 8 mV (3 in 4) the scan's median reading shows no echo
    # rising at its time of flight: every plane unreliable, though the other quarter's ranges are right.  Then
    # they were left out; now the echo after each is recovered from its waveform.
    code, _, _, verdicts = _run(
        tmp_path, fs.simulate(replace(NOISY_BOARD, noise=noise)), fs.Conventions(energy_model=False)
    )
    assert code == 0
    for row in verdicts.values():
        assert row["verdict"] == "accurate" and row["quality"] in qualities, row
        assert any(
            "comparator fired on noise; " in r and "re-timed from the first echo over the noise after it" in r
            for r in row["reasons"]
        ), row["reasons"]


#: Boards whose comparator fires on the noise before (nearly) every echo: ours at 2 σ of a 12.5 mV noise, and a
#: sweep's (tools' foreign sweep, seed 14: a threshold at 2.1 σ, a 0.48 ms burst, 3 V echoes; on main its walls
#: were 1.4 and 1.7 m off, flagged unreliable, "the waveforms show no echo starting at the readings' time of
#: flight").
NOISE_EVERYWHERE = {
    "ours": replace(NOISY_BOARD, noise=0.0125),
    "sweep14": fs.ForeignRig(
        distance_a=1.4023666670856414,
        distance_b=2.2568482639551375,
        roll=0.15084620460899476,
        radial_offset=0.03944228571582977,
        gamma_start=0.08603599791408358,
        gamma_stop=2.1045563883229383,
        steps=85,
        beam_sigma=0.2797483775100888,
        burst=0.0004803012523465113,
        echo_scale=2.990557009458441,
        corner_gain=1.6448513041278363,
        noise=0.006821884384379867,
        threshold=0.014449474339743784,
        seed=14,
    ),
}


@pytest.mark.parametrize("name", sorted(NOISE_EVERYWHERE))
def test_the_echo_after_each_noise_trigger_is_recovered_from_its_waveform(name):
    """Against the scene's truth (the first echo after the comparator's crossing that reaches its threshold,
    ``hidden_range``): the readings the board fired on noise get that echo's range back.  Its onset cannot be
    timed before it arrives (less the timing noise), nor after its envelope's half rise (a quarter of the
    Hann burst: the constant-fraction point); within those, the recovered ranges keep one zero (their scatter
    about the truth is the board's jitter, not the noise's crossings')."""
    rig = NOISE_EVERYWHERE[name]
    scan = fs.simulate(rig)
    assembly = _assembled(scan)
    noise, _ = assembly.noise_triggers()
    found, peak = assembly.recovered_echoes()
    behind = noise & np.isfinite(scan.hidden_range)
    assert behind.sum() >= 0.95 * np.isfinite(scan.tof).sum()  # the scene is what it claims
    got = behind & np.isfinite(found)
    assert got.sum() >= 0.9 * behind.sum()
    assert not (np.isfinite(found) & ~behind).any()  # nothing recovered where no echo came
    error = (found - scan.hidden_range)[got]
    inside = (error >= -3 * rig.range_jitter) & (error <= rig.c / 2 * rig.burst / 4)
    assert inside.mean() >= 0.95, np.percentile(error, [1, 50, 99])
    spread = 1.4826 * np.median(np.abs(error - np.median(error)))
    assert spread <= rig.range_jitter, spread
    assert np.all(peak[got] > 0)
    # The board's ranges are the noise's crossings: drawn anew at each reading.
    assert assembly.noise_independence() > 0.8


@pytest.mark.parametrize("name", sorted(NOISE_EVERYWHERE))
def test_a_board_that_fires_on_noise_everywhere_is_reconstructed_from_its_waveforms_and_named(tmp_path, name):
    # The windows alone cannot tell the noise from ranges in another convention ("the waveforms show no echo
    # starting at the readings' time of flight"), so every plane would be unreliable and fitted to the noise's
    # crossings.  The ranges' changing from step to step as independent draws (a surface's, in any convention,
    # change smoothly) tells the noise; each reading's echo after it is recovered.  No plane may be good (the
    # ranges' zero is the waveforms', not the board's).
    code, _, _, verdicts = _run(tmp_path, fs.simulate(NOISE_EVERYWHERE[name]), fs.Conventions(energy_model=False))
    assert code == 0
    for row in verdicts.values():
        assert row["verdict"] == "accurate" and row["quality"] in ("degraded", "unreliable"), row
        assert any(
            "fires on the noise" in r
            and "as independent draws do" in r
            and "re-timed from the first echo over the noise after it" in r
            for r in row["reasons"]
        ), row["reasons"]


def test_echoes_recovered_after_noise_triggers_that_turn_the_walls_are_not_good(tmp_path):
    """Seed 1075 of the wide sweep: wall a 4.9 m ahead never faced, wall b 0.9 m above faced at the sweep's end,
    the L rolled −5.8°; the board fired on noise for 54 % of its readings.  The echoes recovered after them are
    each within millimetres of their true ranges, yet with the board's own (re-timed) readings they turned both
    walls 10.5° and the fit called them good at σ 1.6°.  Fitted on the board's own readings alone the walls
    are 1.5° off: two fits of the same walls that disagree beyond their σ cannot both be right."""
    rig = fs.ForeignRig(
        distance_a=4.874627915695306,
        distance_b=0.9132534492359319,
        roll=-0.10091674290782744,
        radial_offset=0.03505425844836125,
        gamma_start=0.12638209393972225,
        gamma_stop=1.5983101093905057,
        steps=349,
        beam_sigma=0.3860033760634072,
        burst=0.0006428480220254207,
        echo_scale=3.8911276174510165,
        corner_gain=2.682002115113341,
        noise=0.003973162248685014,
        threshold=0.014334639097837151,
        seed=1075,
    )
    code, _, _, verdicts = _run(tmp_path, fs.simulate(rig), fs.Conventions())
    assert code == 0
    for row in verdicts.values():
        assert row["verdict"] == "accurate" or row["quality"] == "unreliable", row


# ----------------------------------------------------------------------------- the codec and the assembly
def _assembly(start=None) -> ScanAssembly:
    return ScanAssembly(start if start is not None else make_scan_start(steps=5))


def _decoded(m):
    return codec.decode(m.SerializeToString(), type(m))


@pytest.mark.parametrize("value", [math.nan, -1.0, math.inf])
def test_a_reading_without_an_echo_may_mark_its_range_any_way(value):
    s = make_sample()
    s.sensors[2].echo_valid = False
    s.sensors[2].distance = s.sensors[2].time_of_flight = value
    scan = _assembly()
    scan.add(_decoded(s))  # before: NonFiniteValueError, the whole step lost
    assert np.isnan(scan.distance[0, 2]) and np.isfinite(scan.distance[0, [0, 1, 3]]).all()


def test_a_valid_echo_needs_its_range_from_either_field():
    s = make_sample()
    d = s.sensors[1].distance
    s.sensors[1].time_of_flight = 0.0  # range only
    s.sensors[3].distance = 0.0  # round trip only
    t3 = s.sensors[3].time_of_flight
    scan = _assembly()
    scan.add(_decoded(s))
    assert scan.distance[0, 1] == d
    assert scan.distance[0, 3] == pytest.approx(343.2 * t3 / 2, rel=1e-12)
    s.sensors[0].time_of_flight = s.sensors[0].distance = 0.0
    with pytest.raises(InvalidMessageError, match="positive distance or time of flight"):
        _decoded(s)


def test_a_time_of_flight_needs_a_speed_of_sound():
    start = make_scan_start(steps=5)
    start.sound_speed, start.air_temperature = 0.0, 303.15  # unset: c from 30 °C
    scan = _assembly(_decoded(start))
    s = make_sample()
    s.sensors[0].distance = 0.0
    scan.add(_decoded(s))
    c30 = 331.3 * math.sqrt(1 + 30 / 273.15)
    assert scan.distance[0, 0] == pytest.approx(c30 * s.sensors[0].time_of_flight / 2, rel=1e-12)
    start.air_temperature = 0.0
    scan = _assembly(_decoded(start))
    with pytest.raises(InvalidMessageError, match="ScanStart.sound_speed"):
        scan.add(_decoded(s))


def test_scan_start_fields_left_unset_are_accepted_or_refused_by_name():
    start = make_scan_start()
    start.sample_rate = start.sound_speed = 0.0  # before: the ScanStart, so the whole scan, refused
    _decoded(start)
    start.capsules[2].capsule_id = 0
    with pytest.raises(InvalidMessageError, match="its own id"):
        _decoded(start)
    start = make_scan_start()
    start.schema_version = 0
    with pytest.raises(SchemaVersionError, match="set schema_version = 1"):
        _decoded(start)


def test_capsules_are_matched_by_the_ids_the_scan_start_gave_them():
    start = make_scan_start(steps=5)
    for c in start.capsules:
        c.capsule_id += 10
    s = make_sample()
    for r in s.sensors:
        r.capsule_id += 10
    s.sensors.reverse()
    scan = _assembly(start)
    scan.add(_decoded(s))  # before: "the scan has capsules 0..3", refused
    assert list(scan.distance[0]) == [1.5, 1.51, 1.52, 1.53]


def test_the_radial_offset_may_be_stated_in_either_place_but_not_two_ways():
    start = make_scan_start()
    start.radial_offset = 0.0  # only in the positions (y of the array frame)
    assert geometry_from_start(start).radial_offset == pytest.approx(0.03)
    start = make_scan_start()
    for c in start.capsules:
        c.position.y = 0.0
        c.boresight.y = 0.0  # unset: +y
    assert geometry_from_start(start).radial_offset == pytest.approx(0.03)
    start = make_scan_start()
    start.radial_offset = 0.05
    with pytest.raises(InvalidMessageError, match="contradicts the capsules' position.y"):
        geometry_from_start(start)
    start = make_scan_start()
    start.rotation_axis.x, start.rotation_axis.z = 0.0, 1.0
    with pytest.raises(InvalidMessageError, match="rotation about \\+x only"):
        geometry_from_start(start)


def test_gamma_measured_left_unset_falls_back_on_the_commanded_angles():
    scan = _assembly()
    for step in range(3):
        s = make_sample(step)
        s.gamma_measured = 0.0
        scan.add(_decoded(s))
    _, gamma, _, _ = scan.arrays()
    assert np.allclose(gamma, np.deg2rad([-10, -8, -6]))
    assert any("gamma_measured" in text for _, text in scan.writer_problems())


def test_each_capsule_may_have_its_own_clock():
    s = make_sample()
    s.sensors[1].waveform.sample_rate = 100_000.0
    s.sensors[2].waveform.t0 = 1e-4
    for r in s.sensors:  # echoes inside the 0.32 ms waveforms
        r.time_of_flight = 1.5e-4
    scan = _assembly()
    scan.add(_decoded(s))
    for i, r in enumerate(s.sensors):
        w = codec.unpack_waveform(r.waveform)
        assert scan.sensor_energy[0, i] == pytest.approx(float(waveform_energy(w, r.waveform.sample_rate)))
        want = echo_amplitude(w, r.waveform.sample_rate, r.waveform.t0, np.array(r.time_of_flight))
        assert np.array_equal(scan.echo_amplitude[0, i], want, equal_nan=True)


def test_angles_beyond_a_turn_are_named_even_in_a_narrow_sweep():
    scan = _assembly()
    for step in range(3):
        s = make_sample(step)
        s.gamma_measured = s.gamma_commanded = 30.0 + step  # degrees: a 2° sweep, yet no angle of a servo
        scan.add(_decoded(s))
    assert [level for level, text in scan.writer_problems() if "beyond a turn" in text] == ["unreliable"]
