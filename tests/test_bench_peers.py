"""``respecd bench peers`` on a tiny input: ours is measured, a missing peer is skipped with its reason."""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from respecd.errors import InputError
from respecd.lab.bench import peer_radar, peer_sync, peers


def args(data: Path, *extra: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    peers.add_arguments(parser)
    return parser.parse_args(["--data", str(data), "--repeat", "1", "--rounds", "1", "--sync-seconds", "2",
                              "--detector-repeats", "1", *extra])


@pytest.mark.slow
def test_peers_bench_measures_ours_and_skips_missing_peers(shared_data: Path, tmp_path: Path) -> None:
    figures = peers.run(args(shared_data, "--peers", str(tmp_path)))  # an empty folder: no checkout in it
    radar, sync, detector = figures["radar_parser"], figures["synchronizer"], figures["detector"]
    assert radar["ours"]["frames"] == 101 and radar["ours"]["cpu_us_per_frame"] > 0
    assert "parser_mmw_demo.py" in radar["ti"]["skipped"] and "xwr68xxisk" in radar["juhasch"]["skipped"]
    assert sync["ours"]["inputs"] > 150 and sync["ours"]["us_per_input"] > 0
    assert "message_filters" in sync["message_filters"]["skipped"]
    assert detector["input"] == [1, 5, 384, 640] and detector["ours"]["cpu_ms"] > 0
    if importlib.util.find_spec("ultralytics") is None:
        assert "make bench-peers" in detector["yolov8n"]["skipped"]
    else:
        assert detector["yolov8n"]["params"] == 3_157_200 and detector["yolov8n"]["x_ours"] > 0
    assert "no --peers" in peers.run(args(shared_data))["radar_parser"]["ti"]["skipped"]
    assert "radar parser: ours" in peers.summary(figures)


def test_bad_arguments_are_input_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="--repeat"):
        peers.run(args(tmp_path, "--repeat", "0"))
    with pytest.raises(InputError, match="cannot read the radar capture"):
        peers.radar_parser(args(tmp_path))


def test_the_output_comparison_catches_one_changed_value(shared_data: Path) -> None:
    mine = peer_radar.decode_ours(peer_radar.ours((shared_data / peer_radar.CAPTURE).read_bytes()))
    theirs = {k: (p.copy(), None if s is None else s.copy()) for k, (p, s) in mine.items()}
    assert peer_radar.compare(mine, theirs)["identical"]
    offset = next(k for k, (p, s) in theirs.items() if len(p) and s is not None)
    theirs[offset][1][0, 0] += 1  # one SNR off by 0.1 dB
    assert peer_radar.compare(mine, theirs) == {"frames_compared": 101, "frames_identical": 100, "identical": False}
    theirs[offset][1][0, 0] -= 1
    theirs[offset][0][0, 3] = np.nextafter(theirs[offset][0][0, 3], np.float32(1))  # one velocity, one ulp
    assert not peer_radar.compare(mine, theirs)["identical"]


def test_the_synchronizer_stream_keeps_every_sensor_at_its_rate() -> None:
    arrivals = peer_sync.stream(10.0)
    counts = {name: sum(a.sensor == name for a in arrivals) for name in peer_sync.RATES}
    assert counts == {name: int(10 * rate) for name, rate in peer_sync.RATES.items()}
    assert all(a.t <= b.t for a, b in zip(arrivals, arrivals[1:], strict=False))
    ours = peer_sync.ours(arrivals)
    assert 295 <= ours["bundles"] <= 300 and ours["complete_bundles"] > 0.9 * ours["bundles"]
