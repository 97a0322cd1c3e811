"""``respecd adapt``: which logs it refuses (exit 2, saying which log lacks what), how it pairs and
holds back frames, and a run on a session packed from real RGB/thermal pairs (LLVIP, TarDAL: a
smoke test of the mechanics, never a score)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from respecd.clock import ManualClock
from respecd.errors import InputError
from respecd.lab.detector.adapt import Frames, default_freeze, split_frames, view
from respecd.lab.detector.data import Sample
from respecd.lab.detector.recorded import Nearest, open_recording, paired_frames
from respecd.messages import Frame
from respecd.perception import checkpoint
from respecd.record.config import RecordingConfig
from respecd.record.recorder import Recorder

pytestmark = pytest.mark.usefixtures("one_torch_thread")

RGB_CAL = {"intrinsics": {"fx": 60.0, "fy": 60.0, "cx": 32.0, "cy": 18.0, "width": 64, "height": 36}}
THERMAL_CAL = {"intrinsics": {"fx": 15.0, "fy": 20.0, "cx": 8.0, "cy": 6.0, "width": 16, "height": 12},
               "extrinsics": {"translation_m": [0.05, 0.0, 0.0]}}
TINY = {"rgb_widths": (8, 8, 16, 16, 16), "aux_widths": (8, 8, 8, 8, 8), "neck_widths": (16, 16, 16)}


def sensor(name: str, modality: str, calibration: dict | None = None) -> dict:
    return {"name": name, "modality": modality, **({"calibration": calibration} if calibration else {})}


def record(path: Path, sensors: list[dict], seconds: float = 2.0) -> Path:
    """A small session: each listed camera at 10 Hz (RGB 64x36, thermal 16x12 centikelvin)."""
    clock = ManualClock()
    config = RecordingConfig(path=str(path), chunk_size_kib=16, flush_s=0.25, fsync=False)  # chunks to cut between
    recorder = Recorder(config, {"name": "bench-rig", "sensors": sensors}, clock, drain_s=None)  # every frame kept
    recorder.start()
    rng = np.random.default_rng(0)
    for i in range(int(seconds * 10) + 1):
        t = i / 10
        clock.set(t)
        for s in sensors:
            if s["modality"] == "rgb":
                data = rng.integers(60, 200, (36, 64, 3), dtype=np.uint8)
            else:
                data = rng.integers(29_000, 31_000, (12, 16), dtype=np.uint16)
            recorder.on_frame(s["name"], Frame(s["modality"], t, i, data))
    asyncio.run(recorder.close())
    return recorder.paths[0]


def without_metadata(log: Path, out: Path) -> Path:
    """``log`` copied record for record by another MCAP tool that keeps no metadata (the profile)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(log, "rb") as src, open(out, "wb") as dst:
        writer = Writer(dst)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in make_reader(src).iter_messages():
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0), channel.metadata)
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        writer.finish()
    return out


@pytest.fixture
def good_log(tmp_path: Path) -> Path:
    return record(tmp_path / "good.mcap", [sensor("front", "rgb", RGB_CAL), sensor("flir", "thermal", THERMAL_CAL)])


def adapt_cli(cli: Callable, *args: str, out: Path | None = None):
    return cli("adapt", *args, "--out", str(out or Path("unused.pt")), "--no-progress")


# --- refusals --------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("sensors", "said"), [
    ([sensor("front", "rgb", RGB_CAL)], "no thermal camera frames"),
    ([sensor("flir", "thermal", THERMAL_CAL)], "no rgb camera frames"),
    ([sensor("front", "rgb"), sensor("flir", "thermal", THERMAL_CAL)], "sensor 'front' (rgb) has no calibration"),
    ([sensor("front", "rgb", RGB_CAL), sensor("flir", "thermal")], "sensor 'flir' (thermal) has no calibration"),
])
def test_a_log_without_both_calibrated_cameras_is_refused(sensors, said, tmp_path: Path, cli) -> None:
    log = record(tmp_path / "s.mcap", sensors)
    ran = adapt_cli(cli, str(log), out=tmp_path / "a.pt")
    assert ran.returncode == 2, ran.stderr
    assert said in ran.stderr and str(log) in ran.stderr and "Traceback" not in ran.stderr
    assert not (tmp_path / "a.pt").exists()


def test_the_second_of_two_logs_is_named(good_log: Path, tmp_path: Path, cli) -> None:
    bad = record(tmp_path / "rgb-only.mcap", [sensor("front", "rgb", RGB_CAL)])
    ran = adapt_cli(cli, str(good_log), str(bad), out=tmp_path / "a.pt")
    assert ran.returncode == 2 and f"{bad}: no thermal camera frames" in ran.stderr


def test_a_log_with_no_recorded_profile_asks_for_one(good_log: Path, tmp_path: Path, cli) -> None:
    log = without_metadata(good_log, tmp_path / "copied.mcap")
    assert open_recording(log, {"sensors": [sensor("front", "rgb", RGB_CAL), sensor("flir", "thermal", RGB_CAL)]})
    ran = adapt_cli(cli, str(log), "--weights", "builtin:sim-rover", out=tmp_path / "a.pt")
    assert ran.returncode == 2 and "no recorded profile" in ran.stderr and "--config FILE" in ran.stderr


def test_the_calibration_can_come_from_a_profile(tmp_path: Path) -> None:
    log = record(tmp_path / "s.mcap", [sensor("front", "rgb"), sensor("flir", "thermal")])
    profile = {"sensors": [sensor("front", "rgb", RGB_CAL), sensor("flir", "thermal", THERMAL_CAL)]}
    rec = open_recording(log, profile)
    assert rec.calibration["thermal"].extrinsics.translation_m == (0.05, 0.0, 0.0)
    with pytest.raises(InputError, match="no calibration.intrinsics"):
        open_recording(log)


def test_a_bad_calibration_names_the_field(tmp_path: Path) -> None:
    log = record(tmp_path / "s.mcap", [sensor("front", "rgb", RGB_CAL),
                                       sensor("flir", "thermal", {"intrinsics": {"fx": -1}})])
    with pytest.raises(InputError, match=r"sensor 'flir': calibration\.intrinsics\.fx"):
        open_recording(log)


def test_damaged_and_cut_logs(good_log: Path, tmp_path: Path, cli) -> None:
    data = good_log.read_bytes()
    cases = {"empty.mcap": b"", "text.mcap": b"rgb,thermal\n1,2\n", "head.mcap": data[:40]}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        ran = adapt_cli(cli, str(tmp_path / name), out=tmp_path / "a.pt")
        assert ran.returncode == 2, name
        assert str(tmp_path / name) in ran.stderr and "Traceback" not in ran.stderr, ran.stderr
    assert "cut before its first complete chunk" in adapt_cli(cli, str(tmp_path / "head.mcap")).stderr
    cut = tmp_path / "cut.mcap"  # cut in its data: what is before the cut is still learned from
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rec = open_recording(cut)
    pairs = list(paired_frames(rec, ("thermal",), 0.0, 0.1))
    assert rec.truncated and 0 < len(pairs) < 21


def test_a_damaged_recorded_profile_is_exit_2(good_log: Path, tmp_path: Path, cli) -> None:
    data = bytearray(good_log.read_bytes())
    at = data.find(b'"calibration"')
    assert at > 0
    data[at:at + 3] = b"\x00\x00\x00"
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    ran = adapt_cli(cli, str(damaged), out=tmp_path / "a.pt")
    assert ran.returncode == 2 and str(damaged) in ran.stderr and "Traceback" not in ran.stderr, ran.stderr


def test_a_ros_bag_is_refused(shared_data: Path, tmp_path: Path, cli) -> None:
    bags = shared_data / "rosbags"
    for bag in (bags / "kapture_t265_ros1" / "trimmed_locoffice.bag",
                next(p.parent for p in (bags / "rosbag2_fixtures").rglob("metadata.yaml"))):
        ran = adapt_cli(cli, str(bag), out=tmp_path / "a.pt")
        assert ran.returncode == 2 and f"{bag}: a ROS bag, not a respecd session log" in ran.stderr


def test_a_checkpoint_without_thermal_is_refused(good_log: Path, tmp_path: Path, cli) -> None:
    from respecd.perception.config import ModelSpec

    path = tmp_path / "rgb-radar.pt"
    checkpoint.save(path, checkpoint.build(ModelSpec(aux_modalities=("radar",))))
    ran = adapt_cli(cli, str(good_log), "--weights", str(path), out=tmp_path / "a.pt")
    assert ran.returncode == 2 and "the net has no thermal input" in ran.stderr


# --- pairing and holding back ----------------------------------------------------------------------------------------

def test_nearest_pairs_within_the_skew_and_skips_flat_field_frames() -> None:
    frames = [Frame("thermal", t, i, np.zeros((2, 2), np.uint16), {"ffc": t == 0.3}) for i, t in
              enumerate((0.0, 0.11, 0.3, 0.42, 1.0))]
    near = Nearest(iter(frames))
    assert near.at(0.05, 0.1).t == 0.0
    assert near.at(0.31, 0.2).t == 0.42  # the flat-field frame at 0.3 never pairs
    assert near.at(0.7, 0.1) is None  # 0.28 s from either neighbour


def test_frames_pair_every_interval(good_log: Path) -> None:
    pairs = list(paired_frames(open_recording(good_log), ("thermal", "radar"), 0.5, 0.05))
    assert [round(p["rgb"].t, 2) for p in pairs] == [0.0, 0.5, 1.0, 1.5, 2.0]
    assert all(set(p) == {"rgb", "thermal"} and abs(p["thermal"].t - p["rgb"].t) <= 0.05 for p in pairs)


def test_whole_blocks_are_held_back() -> None:
    frames = Frames(samples=[_sample(i) for i in range(40)], keys=[(i // 20, (i % 20) // 5) for i in range(40)])
    train, val = split_frames(frames, 0.25, seed=3)
    assert len(val) == 10 and len(train) == 30  # two of eight blocks of five
    held = {(s.meta["i"] // 20, (s.meta["i"] % 20) // 5) for s in val}
    assert len(held) == 2 and not held & {(s.meta["i"] // 20, (s.meta["i"] % 20) // 5) for s in train}


def test_views_switch_sensors_off_as_the_daemon_does() -> None:
    s = _sample(0)
    thermal = view(s, "thermal only", ("thermal", "radar"))
    assert not thermal.planes[:3].any() and thermal.planes[3].all() and not thermal.planes[4].any()
    assert thermal.presence.tolist() == [1.0, 0.0]
    rgb = view(s, "RGB only", ("thermal", "radar"))
    assert rgb.planes[:3].all() and not rgb.planes[3:].any() and rgb.presence.tolist() == [0.0, 0.0]
    assert view(s, "every sensor", ("thermal", "radar")).planes.all() and s.planes.all()


def _sample(i: int) -> Sample:
    return Sample(np.full((5, 4, 4), 9, np.uint8), np.ones(2, np.float32), np.zeros((0, 4), np.float32),
                  np.zeros(0, bool), meta={"i": i})


# --- a session built from real pairs ----------------------------------------------------------------------------------

def pack_pairs(shared: Path, path: Path) -> Path:
    """The shared LLVIP and TarDAL pairs as one session: RGB and thermal at 1 Hz, pixel-aligned, so both
    cameras get the same normalised intrinsics and no offset (LLVIP is evaluation data: mechanics only)."""
    pairs = [(p, shared / "llvip_pairs" / "infrared" / p.name)
             for p in sorted((shared / "llvip_pairs" / "visible").glob("*.jpg"))]
    pairs += [(p, next((shared / "tardal_ir_vis_samples" / "ir").glob(p.stem + ".*")))
              for p in sorted((shared / "tardal_ir_vis_samples" / "vi").iterdir())]
    cal = {"intrinsics": {"fx": 1000.0, "fy": 1000.0, "cx": 640.0, "cy": 512.0, "width": 1280, "height": 1024}}
    profile = {"name": "flir-one-pairs", "sensors": [sensor("rgb", "rgb", cal), sensor("thermal", "thermal", cal)],
               "perception": {"weights": "builtin:rgbt"}}
    clock = ManualClock()
    config = RecordingConfig(path=str(path), rgb_format="jpeg", thermal_colormap="none")
    recorder = Recorder(config, profile, clock, drain_s=None)
    recorder.start()
    for i, (visible, infrared) in enumerate(pairs):
        clock.set(float(i))
        recorder.on_frame("rgb", Frame("rgb", float(i), i, cv2.imread(str(visible), cv2.IMREAD_COLOR)))
        recorder.on_frame("thermal", Frame("thermal", float(i), i, cv2.imread(str(infrared), cv2.IMREAD_GRAYSCALE)))
    asyncio.run(recorder.close())
    return recorder.paths[0]


@pytest.mark.slow
@pytest.mark.timeout(400)  # packing 23 full-size pairs, a CLI process and a run: over 120 s at load 20 on 2 cores
def test_adapt_runs_on_a_session_of_real_pairs(shared_data: Path, tmp_path: Path, cli) -> None:
    log = pack_pairs(shared_data, tmp_path / "pairs.mcap")
    out = tmp_path / "adapted.pt"
    ran = adapt_cli(cli, str(log), "--epochs", "1", "--steps", "2", "--batch", "2", "--crop", "192x160",
                    "--block", "6", "--val-share", "0.3", out=out)
    assert ran.returncode == 0, ran.stderr
    assert "| thermal only |" in ran.stdout and "adapt builtin:rgbt" in ran.stdout  # the session's own checkpoint
    card = json.loads(out.with_suffix(".json").read_text(encoding="utf-8"))
    report = card["adapt"]
    assert report["frames"]["seen"] == 23 and report["frames"]["held_out"] > 0 and report["frames"]["train"] > 0
    assert set(report["before"]) == set(report["after"]) == {"thermal only", "every sensor", "RGB only"}
    assert report["before"]["RGB only"] == pytest.approx(1.0)  # the teacher's own boxes
    start, adapted = checkpoint.load("builtin:rgbt")[0], checkpoint.load(str(out))[0]
    moved = {name.split(".")[0] for name, p in adapted.state_dict().items()
             if not torch.equal(p, start.state_dict()[name])}
    assert moved and moved <= {"aux", "fuse"}  # the thermal path learned; nothing that serves RGB moved
    assert default_freeze(adapted) == ("rgb", "head", "fuse.*.rgb")
    for name, p in adapted.state_dict().items():
        if name.startswith("fuse.") and ".rgb." in name:
            assert torch.equal(p, start.state_dict()[name]), name


# --- a damaged start: respecd train --reinit -----------------------------------------------------------------------

def test_reinit_gives_only_the_named_parts_fresh_weights(tmp_path: Path, cli) -> None:
    from respecd.perception.config import ModelSpec

    spec = ModelSpec(**TINY)
    start, damaged = tmp_path / "start.pt", tmp_path / "damaged.pt"
    torch.manual_seed(5)
    checkpoint.save(start, checkpoint.build(spec))
    ran = cli("train", "--data", "sim", "--init", str(start), "--reinit", "aux", "--epochs", "0", "--eval-frames",
              "0", "--out", str(damaged), "--no-progress")
    assert ran.returncode == 0, ran.stderr
    before, after = checkpoint.load(str(start))[0].state_dict(), checkpoint.load(str(damaged))[0].state_dict()
    moved = {name for name, p in after.items() if not torch.equal(p, before[name])}
    assert moved and all(name.startswith("aux.") for name in moved)
    assert any(name.startswith("aux.p5") for name in moved)  # the whole part, not its first layer only
    ran = cli("train", "--data", "sim", "--reinit", "aux", "--out", str(tmp_path / "x.pt"), "--no-progress")
    assert ran.returncode == 2 and "--reinit aux: re-initialises parts of --init's net; give --init" in ran.stderr


# --- what is learned, and what is kept --------------------------------------------------------------------------------


def test_frames_are_aligned_with_the_recorded_calibration(good_log: Path, tmp_path: Path) -> None:
    from respecd.lab.detector.adapt import AdaptConfig, label_frames
    from respecd.perception.align import Aligner
    from respecd.perception.config import ModelSpec, PerceptionConfig

    spec = ModelSpec(**TINY, aux_modalities=("thermal",))
    weights = tmp_path / "tiny.pt"
    checkpoint.save(weights, checkpoint.build(spec))
    rec = open_recording(good_log)
    cfg = AdaptConfig(logs=(good_log,), out=tmp_path / "a.pt", weights=str(weights), confident=0.0, unsure=0.0,
                      every_s=0.5, progress=False)
    frames = label_frames([rec], spec, cfg)
    assert frames.seen == 5 and len(frames.samples) == 5 and frames.keys == [(0, 0)] * 5
    first = next(paired_frames(rec, ("thermal",), 0.5, 0.1))
    expected = Aligner(PerceptionConfig(model=spec), rec.calibration).align(first)
    assert np.array_equal(frames.samples[0].planes[3], np.round(expected.tensor[3, :36, :64] * 255).astype(np.uint8))
    plain = Aligner(PerceptionConfig(model=spec)).align(first)  # no calibration: a plain resize, which differs
    assert not np.array_equal(frames.samples[0].planes[3], np.round(plain.tensor[3, :36, :64] * 255).astype(np.uint8))
    dark = label_frames([rec], spec, AdaptConfig(logs=(good_log,), out=tmp_path / "a.pt", weights=str(weights),
                                                 min_light=250.0, every_s=0.5, progress=False))
    assert dark.seen == dark.dark == 5 and not dark.samples


def test_the_sensors_off_anchor_keeps_what_rgb_alone_sees() -> None:
    """Backbone 2 trained on thermal inputs moves its answer to an empty input, which the RGB-alone detector
    reads; the anchor holds it (train mode, as in training)."""
    from respecd.lab.detector.adapt import ANCHOR_WEIGHT, SensorsOff
    from respecd.perception.config import ModelSpec
    from respecd.perception.model import FusionNet

    drift = {}
    for anchored in (False, True):
        torch.manual_seed(0)
        model = FusionNet(ModelSpec(**TINY))
        anchor = SensorsOff(model, (64, 64))
        model.train()
        opt = torch.optim.SGD(model.aux.parameters(), lr=0.05)
        for _ in range(30):
            x = torch.rand(4, 2, 64, 64)
            loss = -model.encode_aux(x, torch.ones(4, 2))[2].mean()  # any objective that moves backbone 2
            if anchored:
                loss = loss + anchor(model)
            opt.zero_grad()
            loss.backward()
            opt.step()
        drift[anchored] = float(anchor(model).detach()) / ANCHOR_WEIGHT
    assert drift[True] < 0.25 * drift[False]
