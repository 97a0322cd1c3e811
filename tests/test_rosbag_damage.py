"""A robot's bag with bad messages, or whose metadata.yaml lies (issue "Open doors", items 7-8):
a bad message costs that message (skipped, counted per topic, reported with its index and why,
exit 1), never the rest of the sensor's replay; metadata.yaml's numbers are checked against the
storage, and the storage wins."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from respecd.cli import main
from respecd.record.rosbag_in import open_bag

T0 = 1_700_000_000 * 10**9
STORE = get_typestore(Stores.ROS2_HUMBLE)
IMAGE = "sensor_msgs/msg/Image"
TOPIC = "/cam/image_raw"
TRUNCATED, SHORT_DATA = 5, 12  # message indexes made bad


def _image(k: int, rows: int = 36) -> object:
    t = STORE.types
    ns = T0 + k * 100_000_000
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                      frame_id="cam")
    data = np.full((rows, 64, 3), k * 8, np.uint8).reshape(-1)
    return t[IMAGE](header=header, height=36, width=64, encoding="rgb8", is_bigendian=0, step=192, data=data)


def _raw(k: int, serialize) -> bytes:
    if k == SHORT_DATA:
        return serialize(_image(k, rows=2), IMAGE)  # says 36 rows, carries 2: it deserializes, then fails
    raw = serialize(_image(k), IMAGE)
    return raw[:40] if k == TRUNCATED else raw  # cut inside the message: it does not deserialize


def _write(path: Path, kind: str) -> Path:
    if kind == "ros1":
        path = path.with_suffix(".bag")
        with Writer1(path) as w:
            conn = w.add_connection(TOPIC, IMAGE, typestore=STORE)
            for k in range(30):
                w.write(conn, T0 + k * 100_000_000, _raw(k, STORE.serialize_ros1))
        return path
    storage = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=8, storage_plugin=storage) as w:
        conn = w.add_connection(TOPIC, IMAGE, typestore=STORE)
        for k in range(30):
            w.write(conn, T0 + k * 100_000_000, _raw(k, STORE.serialize_cdr))
    return path


@pytest.mark.parametrize("kind", ["mcap", "sqlite3", "ros1"])
def test_a_bad_message_costs_that_message_only(tmp_path: Path, kind: str) -> None:
    bag = open_bag(_write(tmp_path / "bag", kind), {"rgb": TOPIC})
    frames = list(bag.frames("rgb"))
    assert [f.seq for f in frames] == [k for k in range(30) if k not in (TRUNCATED, SHORT_DATA)]
    assert sorted(bag.skipped[TOPIC]) == [TRUNCATED, SHORT_DATA]
    report = bag.skipped_report()[TOPIC]
    assert report["count"] == 2 and "Serde" in report["first"][0]["why"] and "ValueError" in report["first"][1]["why"]


@pytest.mark.slow
def test_a_replay_reports_skipped_messages_and_exits_1(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = _write(tmp_path / "bag", "mcap")
    status = main(["--replay", str(path), "--topics", f"rgb={TOPIC}", "--speed", "max",
                   "--report", str(tmp_path / "r.json"), "--state-dir", str(tmp_path / "st")])
    err = capsys.readouterr().err
    assert status == 1
    assert re.search(rf"{TOPIC}: 2 message\(s\) skipped, unreadable: index 5: SerdeError: .*; index 12: ", err)
    entry = json.loads((tmp_path / "r.json").read_text())["policies"]["learn"]
    assert entry["skipped"][TOPIC]["count"] == 2


def _lie(bag: Path, duration: int | None = None, count: int | None = None, twice: bool = False) -> None:
    """Edit metadata.yaml as a broken tool (or a hand) would."""
    import yaml

    meta = bag / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    info = doc["rosbag2_bagfile_information"]
    if duration is not None:
        info["duration"]["nanoseconds"] = duration
    if count is not None:
        info["topics_with_message_count"][0]["message_count"] = count
    if twice:
        info["relative_file_paths"] *= 2
    meta.write_text(yaml.safe_dump(doc))


@pytest.mark.parametrize("kind", ["mcap", "sqlite3"])
@pytest.mark.parametrize("lie, claim", [
    ({"duration": 900_000_000_000_000_000}, "duration 900000000.000 s, the storage's messages span 2.900 s"),
    ({"duration": -5_000_000_000}, "duration -5.000 s, the storage's messages span 2.900 s"),
    ({"count": 7}, "/cam/image_raw: message_count 7, the storage holds 30"),
    ({"twice": True}, "relative_file_paths lists bag."),
])
def test_the_storage_wins_over_metadata_yaml(tmp_path: Path, kind: str, lie: dict, claim: str) -> None:
    path = _write(tmp_path / "bag", kind)
    _lie(path, **lie)
    bag = open_bag(path, {"rgb": TOPIC})
    assert any(note.startswith(claim) for note in bag.metadata_notes), bag.metadata_notes
    assert bag.duration_s == pytest.approx(2.9, abs=1e-3) and bag.frame_count("rgb") == 30
    assert len(list(bag.frames("rgb"))) == 28  # every message once (two of them are bad)


@pytest.mark.slow
def test_a_huge_duration_replays_what_the_storage_holds(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = _write(tmp_path / "bag", "mcap")
    _lie(path, duration=900_000_000_000_000_000)
    status = main(["--replay", str(path), "--topics", f"rgb={TOPIC}", "--speed", "max",
                   "--report", str(tmp_path / "r.json"), "--state-dir", str(tmp_path / "st")])
    err = capsys.readouterr().err
    assert status == 1  # the two bad messages; the replay itself ends with the storage's 2.9 s
    assert "metadata.yaml: duration 900000000.000 s, the storage's messages span 2.900 s" in err
    entry = json.loads((tmp_path / "r.json").read_text())["policies"]["learn"]
    assert entry["replayed_s"] == pytest.approx(2.9, abs=0.2)


def test_log_info_shows_the_storage_numbers_and_warns(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = _write(tmp_path / "bag", "sqlite3")
    _lie(path, count=7, twice=True)
    assert main(["log", "info", "--json", str(path)]) == 0
    out, err = capsys.readouterr()
    described = json.loads(out)
    assert described["topics"][0]["messages"] == 30 and len(described["metadata_mismatch"]) == 2
    assert "metadata.yaml: /cam/image_raw: message_count 7, the storage holds 30" in err


def test_a_sensor_mapped_twice_is_an_error() -> None:
    """--topics rgb=/a,rgb=/b was accepted, the last one silently winning."""
    from respecd.errors import InputError
    from respecd.record.rosbag_in import parse_topics

    with pytest.raises(InputError, match=r"--topics: rgb is given twice \(rgb=/a and rgb=/b\)"):
        parse_topics("rgb=/a,rgb=/b")
    assert parse_topics("rgb=/a,thermal=/b") == {"rgb": "/a", "thermal": "/b"}
