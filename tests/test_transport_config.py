"""Zenoh configuration precedence: typed flags > --zenoh-config file > command defaults; a failed close."""

from __future__ import annotations

import argparse
import json
import logging

import pytest
import zenoh

from lelsonar.net import transport
from lelsonar.net.transport import add_zenoh_arguments, zenoh_settings_from_args

FILE = """{
  // a robot's session: none of this may be replaced by a default
  mode: "client",
  connect: { endpoints: ["tcp/10.0.0.5:7447"] },
  listen: { endpoints: ["tcp/10.0.0.6:7448"] },
  scouting: { multicast: { enabled: true } },
}
"""


def resolved(argv: list[str], default_mode: str = "peer") -> dict:
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser, default_mode=default_mode)
    cfg = zenoh_settings_from_args(parser.parse_args(argv)).to_config()
    return {
        k: json.loads(cfg.get_json(k))
        for k in ("mode", "connect/endpoints", "listen/endpoints", "scouting/multicast/enabled")
    }


def test_a_config_file_is_overridden_only_by_the_flags_the_user_typed(tmp_path):
    path = tmp_path / "robot.json5"
    path.write_text(FILE)
    from_file = {
        "mode": "client",
        "connect/endpoints": ["tcp/10.0.0.5:7447"],
        "listen/endpoints": ["tcp/10.0.0.6:7448"],
        "scouting/multicast/enabled": True,
    }
    assert resolved(["--zenoh-config", str(path)]) == from_file
    assert resolved(["--zenoh-config", str(path)], default_mode="client") == from_file
    typed = resolved(["--zenoh-config", str(path), "--mode", "peer", "--connect", "tcp/127.0.0.1:9"])
    assert typed == {**from_file, "mode": "peer", "connect/endpoints": ["tcp/127.0.0.1:9"]}
    # No file: the command's defaults, multicast scouting off.
    assert resolved([]) == {
        "mode": "peer",
        "connect/endpoints": ["tcp/127.0.0.1:7447"],
        "listen/endpoints": [],
        "scouting/multicast/enabled": False,
    }
    # A file that says nothing of multicast does not get Zenoh's default (on).
    quiet = tmp_path / "quiet.json5"
    quiet.write_text('{ mode: "peer" /* multicast is not configured here */ }')
    assert resolved(["--zenoh-config", str(quiet)])["scouting/multicast/enabled"] is False


def test_a_session_close_that_fails_is_a_warning_not_a_crash(monkeypatch, caplog):
    class Session:
        def close(self):
            raise zenoh.ZError("close operation timed out!")

    monkeypatch.setattr(transport.zenoh, "open", lambda cfg: Session())
    with caplog.at_level(logging.WARNING, logger="lelsonar.net.transport"):
        with transport.open_session(transport.ZenohSettings()):
            pass
    assert any("close operation timed out" in r.getMessage() for r in caplog.records)
    with pytest.raises(RuntimeError):  # an error inside the block still propagates
        with transport.open_session(transport.ZenohSettings()):
            raise RuntimeError("inside")
