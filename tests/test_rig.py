"""The rig file drives real hardware (here the emulated servo and board, byte for byte), never a preset.

Also: every command reads --config, an explicit flag beats the file, a default never does;
`calibrate --device serial` guides the six shots and writes φ back.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.acquire.emulate.ax12_emulator import AX12EmulatorConfig
from lelsonar.acquire.emulate.rig import emulated_rig
from lelsonar.acquire.emulate.sensor_board_emulator import SensorBoardEmulatorConfig, sim_shot_source
from lelsonar.acquire.rig import RIG_KEYS, load_rig, write_energy_model
from lelsonar.cli.config_file import parse_args
from lelsonar.cli.main import build_parser, main
from lelsonar.errors import ConfigError
from lelsonar.log import recording
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
from lelsonar.sim import preset

EXAMPLE = Path(__file__).parents[1] / "examples" / "rig.toml"


def test_example_rig_documents_every_key_and_loads():
    text = EXAMPLE.read_text()
    for table, keys in RIG_KEYS.items():
        assert f"[{table}]" in text
        for key in keys:
            assert re.search(rf"^#?\s*{key}\s*=", text, re.M), f"[{table}].{key} is not documented"
    rig = load_rig(EXAMPLE)
    assert rig.missing() == []
    c, t = rig.sound_speed_and_temperature()
    assert t == pytest.approx(293.15) and c == pytest.approx(331.3 * math.sqrt(1 + 20 / 273.15))


def test_serial_names_everything_missing_at_once(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text('[servo]\nport = "/dev/ttyUSB0"\nzero_raw = 512\n')
    with pytest.raises(ConfigError) as err:
        main_args = build_parser().parse_args(["acquire", "--device", "serial", "--config", str(rig)])
        from lelsonar.cli.acquire import config_from_args

        config_from_args(main_args)
    text = str(err.value)
    assert "never from a simulator preset" in text
    for key in (
        "array.capsule_x",
        "servo.gamma_min_deg",
        "sensor_board.port",
        "air.temperature_c or air.sound_speed",
        "energy_model.phi",
        "schedule.steps",
    ):
        assert key in text
    assert "servo.port" not in text.split("missing:")[1]
    # Bad values name the key.
    rig.write_text("[servo]\nzero_raw = 2000\n")
    with pytest.raises(ConfigError, match=r"zero_raw must be in 0..1023"):
        load_rig(rig)
    rig.write_text("[array]\ncapsule_z = 1\n")
    with pytest.raises(ConfigError, match="unknown key 'capsule_z' in \\[array\\]"):
        load_rig(rig)


RIG = """
[array]
capsule_x = [-0.11, -0.035, 0.035, 0.11]
radial_offset = 0.025
[servo]
port = "/dev/nonexistent-servo"
zero_raw = 512
gamma_min_deg = -12.0
gamma_max_deg = 112.0
latency_timer_ms = 2.0
[sensor_board]
port = "{board}"
sample_rate = 200000
window_samples = 3500
[air]
temperature_c = 25.0
[energy_model]
phi = [3000.0, 2000.0, -1500.0]
d_min = 0.8
d_max = 1.9
[schedule]
gamma_start_deg = -5.0
gamma_stop_deg = 100.0
steps = 184
[acquire]
scanner_id = "rigtest"
out_dir = "{out}"
"""


def test_the_rig_file_drives_device_serial_end_to_end(tmp_path):
    sim = preset("paper-test1")
    with emulated_rig(
        sim_shot_source(sim, np.random.default_rng(0)),
        AX12EmulatorConfig(return_delay=0, initial_position=512),
        SensorBoardEmulatorConfig(),
        zero_raw=512,
    ) as emu:
        rig = tmp_path / "rig.toml"
        rig.write_text(RIG.format(board=emu.board.path, out=tmp_path / "ignored"))
        # --motor-port overrides the file's bogus port, --steps its schedule, --out its [acquire] out_dir;
        # --preset names another scene and must change nothing on a serial rig.
        code = main(
            [
                "acquire",
                "--device",
                "serial",
                "--config",
                str(rig),
                "--motor-port",
                emu.motor.path,
                "--steps",
                "5",
                "--out",
                str(tmp_path / "out"),
                "--no-zenoh",
                "--preset",
                "paper-test2",
            ]
        )
    assert code == 0
    msgs = list(recording.read_messages(tmp_path / "out" / "scan.mcap"))
    start = msgs[0]
    assert isinstance(start, codec.ScanStart) and start.device == "serial" and start.scanner_id == "rigtest"
    assert [c.position.x for c in start.capsules] == [-0.11, -0.035, 0.035, 0.11]
    assert {c.position.y for c in start.capsules} == {0.025}
    assert start.radial_offset == 0.025
    assert start.air_temperature == pytest.approx(298.15)
    assert start.sound_speed == pytest.approx(331.3 * math.sqrt(1 + 25 / 273.15))
    e = start.energy_model
    assert (e.phi0, e.phi1, e.phi2, e.valid_min_range, e.valid_max_range) == (3000.0, 2000.0, -1500.0, 0.8, 1.9)
    assert start.steps == 5 and start.gamma_start == pytest.approx(math.radians(-5))
    assert start.gamma_stop == pytest.approx(math.radians(100))
    samples = [m for m in msgs if isinstance(m, codec.Sample)]
    assert len(samples) == 5 and isinstance(msgs[-1], codec.ScanEnd) and msgs[-1].status == 1
    # γ read back from the servo, within an AX-12 unit of the schedule.
    np.testing.assert_allclose(
        [s.gamma_measured for s in samples], np.radians(np.linspace(-5, 100, 5)), atol=math.radians(300 / 1024)
    )
    assert not (tmp_path / "ignored").exists()
    meta = recording.read_metadata(tmp_path / "out" / "scan.mcap")["lelsonar.config"]
    assert "preset" not in meta and meta["rig.servo.zero_raw"] == "512" and meta["device"] == "serial"


def test_every_command_reads_config_and_only_explicit_flags_win(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        '[reconstruct]\nmethod = "ls"\nscan-timeout = 3\njson = true\n'
        '[zenoh]\nprefix = "robot7/lelsonar"\nconnect = ["tcp/10.0.0.1:7447"]\n'
        "[planner]\ntimeout = 5\n"
    )
    a = parse_args(build_parser(), ["reconstruct", "--config", str(cfg)])
    assert (a.method, a.scan_timeout, a.json, a.prefix, a.connect) == (
        "ls",
        3.0,
        True,
        "robot7/lelsonar",
        ["tcp/10.0.0.1:7447"],
    )
    # An explicit flag wins even when it repeats the default value.
    a = parse_args(build_parser(), ["reconstruct", "--config", str(cfg), "--scan-timeout", "10", "-e", "tcp/x:1"])
    assert (a.scan_timeout, a.connect, a.method) == (10.0, ["tcp/x:1"], "ls")
    a = parse_args(build_parser(), ["planner", "--config", str(cfg)])
    assert (a.timeout, a.prefix) == (5.0, "robot7/lelsonar")
    # Every subcommand takes --config.
    sub = next(x for x in build_parser()._actions if x.dest == "command")
    for name, p in sub.choices.items():
        assert any(x.dest == "config" for x in p._actions), name
    cfg.write_text('[reconstruct]\nmethd = "ls"\n')
    with pytest.raises(ConfigError, match="unknown key 'methd' in \\[reconstruct\\]"):
        parse_args(build_parser(), ["reconstruct", "--config", str(cfg)])
    cfg.write_text('[reconstruct]\nmethod = "nope"\n')
    assert main(["reconstruct", "--config", str(cfg)]) == 2


def test_write_energy_model_replaces_only_its_table(tmp_path):
    rig = tmp_path / "rig.toml"
    text = EXAMPLE.read_text()
    rig.write_text(text)
    write_energy_model(rig, (1.0, 2.0, 3.0), 0.5, 2.5, note="test")
    after = rig.read_text()
    doc = tomllib.loads(after)
    assert doc["energy_model"] == {"phi": [1.0, 2.0, 3.0], "d_min": 0.5, "d_max": 2.5}
    before = tomllib.loads(text)
    assert {k: v for k, v in doc.items() if k != "energy_model"} == {
        k: v for k, v in before.items() if k != "energy_model"
    }
    # Comments of the other tables survive.
    assert after.split("[energy_model]")[0] == text.split("[energy_model]")[0]
    assert after.split("[schedule]")[1] == text.split("[schedule]")[1]


@pytest.mark.parametrize("mistyped", [False, True])
def test_calibrate_serial_guides_six_shots_and_writes_phi(tmp_path, monkeypatch, capsys, mistyped):
    from lelsonar.acquire.calibrate_rig import range_tolerance
    from lelsonar.sim import simulate_step
    from lelsonar.sim.calibrate import PAPER_CALIBRATION_DISTANCES, calibrate_simulator
    from lelsonar.sim.scene import Scene

    sim = preset("paper-test1")
    wall = {"d": 1.0}
    rng = np.random.default_rng(5)

    def shots(step, gamma, n_samples, fs_hz):  # the wall the "user" placed, face-on
        scene = Scene.wall(wall["d"] + sim.geometry.radial_offset, reflectivity=sim.scene.panels[0].reflectivity)
        shot = simulate_step(dataclasses.replace(sim, scene=scene), gamma, rng)
        ns = np.where(np.isfinite(shot.tof), np.round(np.nan_to_num(shot.tof) * 1e9), 0xFFFFFFFF)
        return ns.astype(np.uint32), np.asarray(shot.waveforms, dtype=np.float32)

    answers = iter(PAPER_CALIBRATION_DISTANCES)

    class Typist:  # moves the wall, then types the distance it measured (or, mistyped, one 3 tolerances off)
        shot = 0

        def readline(self):
            wall["d"] = next(answers)
            Typist.shot += 1
            off = 3 * range_tolerance(wall["d"], 343.0) if mistyped and Typist.shot == 4 else 0.0
            return f"{wall['d'] + off}\n"

    monkeypatch.setattr("sys.stdin", Typist())
    with emulated_rig(
        shots, AX12EmulatorConfig(return_delay=0, initial_position=700), SensorBoardEmulatorConfig(), zero_raw=512
    ) as emu:
        rig = tmp_path / "rig.toml"
        rig.write_text(
            EXAMPLE.read_text()
            .replace("/dev/ttyUSB0", emu.motor.path)
            .replace("/dev/ttyACM0", emu.board.path)
            .replace("latency_timer_ms = 16.0", "latency_timer_ms = 2.0")
        )
        before = rig.read_text()
        if mistyped:  # refused, the file untouched, the shot named
            assert main(["calibrate", "--device", "serial", "--config", str(rig)]) == 2
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and "1 of 6 shots disagree" in err and "shot 4 typed" in err
            assert rig.read_text() == before
            return
        assert main(["calibrate", "--device", "serial", "--config", str(rig)]) == 0
        assert emu.motor.gamma_source(512)() == pytest.approx(0.0, abs=math.radians(0.3))  # turned face-on
    out = capsys.readouterr().out
    assert out.count("shot ") == 6 and "wrote [energy_model]" in out
    got = tomllib.loads(rig.read_text())["energy_model"]
    assert (got["d_min"], got["d_max"]) == (0.9, 1.8)
    # Independent: the simulator's own six-shot calibration (no serial link, no ADC) predicts the same E0.
    ref = calibrate_simulator(sim, seed=5).model
    d = np.linspace(0.9, 1.8, 7)
    e0 = 1.0 / (got["phi"][0] * d**2 + got["phi"][1] * d + got["phi"][2])
    np.testing.assert_allclose(e0, ref.expected_energy(d), rtol=0.05)
    assert "# calibrated " in rig.read_text() and "[schedule]" in rig.read_text()


def test_the_example_rig_configures_every_command_it_has_tables_for():
    from lelsonar.acquire.rig import serial_setup
    from lelsonar.cli.acquire import config_from_args

    a = parse_args(build_parser(), ["reconstruct", "--config", str(EXAMPLE)])
    assert (a.method, a.compare, a.prefix) == (DEFAULT_METHOD, "ls", "lelsonar")  # the file keeps the default
    cfg = config_from_args(parse_args(build_parser(), ["acquire", "--config", str(EXAMPLE)]))
    setup = serial_setup(cfg)
    assert cfg.device == "serial" and setup.motor.port == "/dev/ttyUSB0" and setup.board.port == "/dev/ttyACM0"
    assert setup.steps == 184 and setup.info.geometry.capsule_x == (-0.12, -0.04, 0.04, 0.12)
    assert setup.energy_model.d_min == 0.9 and setup.motor.zero_raw == 512
    # The schedule applies to the simulated devices too; flags still win.
    cfg = config_from_args(
        parse_args(build_parser(), ["acquire", "--config", str(EXAMPLE), "--device", "sim", "--gamma-stop", "90"])
    )
    assert (cfg.steps, cfg.gamma_start, cfg.gamma_stop) == (184, math.radians(-10.0), math.radians(90.0))
    for command in ("planner", "router", "review", "emulate", "simulate", "calibrate", "demo"):
        argv = [command, "--config", str(EXAMPLE)] + (["x.mcap"] if command == "review" else [])
        parse_args(build_parser(), argv)  # no unknown keys, nothing required missing
