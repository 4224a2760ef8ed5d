"""The mapper: fed the scans of recordings it gives the map `map --source` prints; on Zenoh it publishes
each map on <prefix>/map, answers a get with the latest, and records the maps."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from lelsonar import codec
from lelsonar.cli.main import main
from lelsonar.draw.map_scene import TOPIC_MAP_SCENE
from lelsonar.keys import ScannerKeys
from lelsonar.log import recording
from lelsonar.log.recording import iter_payloads
from lelsonar.map.service import MAP_TOPIC, MapperService, ZenohMapper, map_key
from lelsonar.net.transport import hermetic_settings, open_session
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.replay import replay_mcap
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.v1 import map_pb2
from tests.conftest import simulated_messages


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Two recorded scans, and each one's ScanStart and final estimate."""
    d = tmp_path_factory.mktemp("mapper")
    out = []
    for i in (1, 2):
        path = d / f"scan{i}.mcap"
        with recording.McapRecorder(path) as rec:
            for m in simulated_messages("paper-test1", seed=i, scan_id=i):
                rec.write(m)
        start = next(
            codec.decode(r.payload, codec.ScanStart)
            for r in iter_payloads(path)
            if r.type_name == codec.ScanStart.DESCRIPTOR.full_name
        )
        service = ReconstructionService(ReconstructConfig(compare_methods=(), provisional=False))
        replay_mcap(path, service)
        [final] = service.finals.values()
        out.append((path, start, final))
    return out


def test_the_live_map_equals_the_replayed_one(scans, capsys):
    service = MapperService("s1", DEFAULT_METHOD)
    for _, start, final in scans:
        service.handle_start(start)
        service.handle_estimate(final)
    assert service.handle_estimate(scans[0][2]) is None  # a scan is mapped once
    live = service.latest
    assert main(["map", "--source", *(str(p) for p, _, _ in scans), "--json"]) == 0
    replay = json.loads(capsys.readouterr().out)
    assert len(live.walls) == len(replay["walls"]) and len(live.poses) == len(replay["poses"])
    for a, b in zip(live.walls, replay["walls"]):
        assert a.offset == pytest.approx(b["offset"], abs=1e-9)
        assert [a.normal.x, a.normal.y] == pytest.approx([b["normal"]["x"], b["normal"]["y"]], abs=1e-9)
        assert a.offset_stderr == pytest.approx(b["offset_stderr"], rel=1e-6)
        assert codec.QUALITY_NAME[a.quality] == b["quality"]


def test_the_mapper_publishes_answers_a_get_and_records(scans, zenoh_socket, tmp_path):
    keys = ScannerKeys("lelsonar", "s1")
    record = tmp_path / "maps.mcap"
    got: list[map_pb2.Map] = []
    mapped = [threading.Event(), threading.Event()]

    def on_map(msg):
        got.append(msg)
        mapped[len(got) - 1].set()

    with (
        open_session(hermetic_settings(zenoh_socket, listen=True)) as mapper_session,
        open_session(hermetic_settings(zenoh_socket, listen=False)) as robot,
    ):
        with ZenohMapper(mapper_session, "lelsonar", MapperService("s1", DEFAULT_METHOD), record=record, on_map=on_map):
            pubs = {}
            for key, msg in ((keys.scan, scans[0][1]), (keys.planes, scans[0][2])):
                pub = robot.declare_publisher(key, encoding=zenoh.Encoding(codec.encoding_name(msg)))
                matched = threading.Event()
                pub.declare_matching_listener(lambda status, e=matched: status.matching and e.set())
                assert matched.wait(10)
                pubs[key] = pub
            # A robot's scans come one after the other: each final estimate after its start, the next scan after.
            for (_, start, final), done in zip(scans, mapped):
                pubs[keys.scan].put(start.SerializeToString())
                pubs[keys.planes].put(final.SerializeToString())
                assert done.wait(60)
            querier = robot.declare_querier(map_key("lelsonar"), timeout=10.0)
            matched = threading.Event()
            querier.declare_matching_listener(lambda status: status.matching and matched.set())
            assert matched.wait(10)
            [reply] = list(querier.get())
            latest = map_pb2.Map.FromString(reply.ok.payload.to_bytes())
    assert latest == got[-1] and latest.scans == 2
    assert [p.scan_id for p in latest.poses] == [1, 2]
    assert any("no pose" in n for n in latest.notes)
    with open(record, "rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert {channel.topic for _, channel, _, _ in decoded} == {MAP_TOPIC, TOPIC_MAP_SCENE}
    maps = [m for _, channel, _, m in decoded if channel.topic == MAP_TOPIC]
    scenes = [m for _, channel, _, m in decoded if channel.topic == TOPIC_MAP_SCENE]
    assert len(scenes) == 2
    assert {e.id for e in scenes[-1].entities} >= {f"s1/map/wall/{w.id}" for w in latest.walls} | {"s1/map/free_space"}
    assert len(maps) == 2 and maps[-1].scans == 2
    assert np.isclose(maps[-1].walls[0].offset, latest.walls[0].offset)


def test_an_estimate_that_comes_before_its_start_waits_for_it(scans):
    (_, start1, final1), (_, _start2, final2) = scans
    service = MapperService("s1", DEFAULT_METHOD)
    assert service.handle_estimate(final1) is None  # its start is on another key, still on its way
    first = service.handle_start(start1)
    assert first is not None and first.scans == 1
    assert not any("no ScanStart" in n for n in first.notes)
    assert service.handle_estimate(final2) is None
    last = service.flush()  # the run ends without scan 2's start: it goes in at the origin, and says so
    assert last.scans == 2 and any("scan 2: no ScanStart came" in n for n in last.notes)
    assert service.flush() is None
