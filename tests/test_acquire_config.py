"""`lelsonar acquire` configuration: TOML, flags over TOML, and clear errors."""

from __future__ import annotations

import math

import pytest

from lelsonar.cli.acquire import config_from_args
from lelsonar.cli.main import build_parser
from lelsonar.errors import ConfigError, InvalidIdentifierError


def parse(*argv: str):
    return config_from_args(build_parser().parse_args(["acquire", *argv]))


def test_flags_override_toml(tmp_path):
    toml = tmp_path / "rig.toml"
    toml.write_text(
        '[acquire]\nscanner_id = "rig7"\nsteps = 90\ngamma_start_deg = -5\nscans = 2\nenergy_phi = [1.0, 2.0, 3.0]\n'
    )
    cfg = parse("--config", str(toml), "--steps", "120", "--prefix", "robot7/lelsonar")
    assert cfg.scanner_id == "rig7" and cfg.steps == 120 and cfg.scans == 2
    assert cfg.prefix == "robot7/lelsonar"
    assert math.isclose(cfg.gamma_start, math.radians(-5))
    assert (cfg.energy_model.phi0, cfg.energy_model.phi2) == (1.0, 3.0)
    assert cfg.mcap_path(1).name == "scan-2.mcap"


@pytest.mark.parametrize(
    "body, message",
    [
        ("[acquire]\nstepz = 3\n", "unknown key 'stepz'"),
        ('[acquire]\nsteps = "many"\n', "must be of type int"),
        ("[acquire\n", "not valid TOML"),
    ],
)
def test_bad_toml_names_the_problem(tmp_path, body, message):
    toml = tmp_path / "bad.toml"
    toml.write_text(body)
    with pytest.raises(ConfigError, match=message):
        parse("--config", str(toml))


def test_bad_values_are_rejected_with_the_fix():
    with pytest.raises(ConfigError, match="never from a simulator preset; missing: array.capsule_x"):
        parse("--device", "serial")
    with pytest.raises(InvalidIdentifierError):
        parse("--scanner-id", "robot/7")
    with pytest.raises(ConfigError, match="±150°"):
        parse("--gamma-stop", "200")
    with pytest.raises(ConfigError, match="does not exist"):
        parse("--config", "/nonexistent/rig.toml")
