"""A robot's session replays on whatever machine opens it: a log recorded under a ``device:
cuda`` profile replays on this CPU (said once in the log and in the report), and a real camera
bag the project never saw replays with a report that names its detector and claims no F1
without ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml
from conftest import run_cli
from real_camera import LLVIP, photos, write_camera_bag, write_log

from respecd.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(not LLVIP.is_dir(), reason=f"shared photos not found at {LLVIP}")


def _jetson_profile() -> dict:
    """The simulated rover's profile as the Jetson would run it: the detector on CUDA, one camera."""
    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["name"] = "jetson-camera"
    profile["sensors"] = [profile["sensors"][0] | {"resolution": [640, 512]}]
    profile["perception"] = {"device": "cuda"}
    profile["controller"] = {"decision_period_s": 0.5, "window_s": 0.5}
    return profile


@pytest.mark.slow
@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: the profile's device is usable")
def test_a_log_of_a_cuda_profile_replays_on_this_cpu(tmp_path: Path) -> None:
    log = write_log(tmp_path / "jetson.mcap", _jetson_profile(), photos(8), hz=4)
    report = tmp_path / "r.json"
    ran = run_cli("--replay", str(log), "--speed", "max", "--policy", "static", "--report", str(report),
                  "--log-format", "json")
    assert ran.returncode == 0, ran.stderr[-2000:]
    detector = json.loads(report.read_text())["policies"]["static"]["detector"]
    assert detector["device"] == "cpu" and detector["profile_device"] == "cuda"
    assert detector["chosen_by"] == "the profile recorded in the log" and "CUDA" in detector["device_note"]
    assert detector["checkpoint"] == "sim-rover.pt" and len(detector["sha256"]) == 64
    said = [json.loads(line) for line in ran.stdout.splitlines() if '"replay.device"' in line]
    assert len(said) == 1 and said[0]["profile_device"] == "cuda" and said[0]["device"] == "cpu"
    # the live daemon keeps its clear refusal of the same profile
    config = tmp_path / "jetson.yaml"
    config.write_text(yaml.safe_dump(_jetson_profile()))
    live = run_cli("--config", str(config), "--duration", "1", "--state-dir", str(tmp_path / "st"))
    assert live.returncode == 2 and "perception.device: 'cuda' cannot be used" in live.stderr


def test_a_device_typo_is_a_profile_error_for_a_replay_too(tmp_path: Path) -> None:
    profile = _jetson_profile()
    profile["perception"] = {"device": "cdua"}
    log = write_log(tmp_path / "typo.mcap", profile, photos(2), hz=4)
    ran = run_cli("--replay", str(log), "--speed", "max")
    assert ran.returncode == 2 and "perception.device: 'cdua' is not a torch device" in ran.stderr
    assert "Traceback" not in ran.stderr


@pytest.mark.parametrize("asked", [{"runtime": "onnxruntime", "device": "tensorrt", "precision": "f16"},
                                   {"runtime": "openvino", "device": "gpu:1", "precision": "f16"}])
def test_a_runtime_profile_replays_with_what_this_machine_has(asked: dict) -> None:
    """A Jetson's TensorRT (or an Intel GPU's OpenVINO) profile: the replay runs that runtime on the
    CPU in f32 where it is installed, else torch on the CPU, and the report names both placements."""
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.runtimes import problem
    from respecd.replay import detector

    placed = detector.place(dict(asked))
    assert placed["device"] == "cpu" and placed["precision"] == "f32"
    assert problem(PerceptionConfig.model_validate(placed)) is None  # it runs here
    described = detector.entry(PerceptionConfig.model_validate(placed), asked, "--profile robot.yaml")
    assert described["profile_device"] == asked["device"] and described["profile_precision"] == "f16"
    assert described["device_note"] and described["runtime"] == placed["runtime"]
    with pytest.raises(ConfigError, match="'cuda' is not a device of runtime openvino"):
        detector.place({"runtime": "openvino", "device": "cuda"})  # wrong on the robot too


@pytest.mark.slow
def test_a_real_camera_bag_names_its_detector_and_claims_no_f1(tmp_path: Path) -> None:
    """Seven real photos at 5 Hz (1.2 s): the simulator's detector, modelled at 1.6 s for its first
    (attributed) 1280x1024 inference, outlives the bag; the replay waits for that percept."""
    bag = write_camera_bag(tmp_path / "street", photos(7, (1280, 1024)), hz=5)
    report = tmp_path / "r.json"
    ran = run_cli("--replay", str(bag), "--speed", "max", "--report", str(report), "--log-format", "json")
    assert ran.returncode == 0, ran.stderr[-2000:]
    first = json.loads(ran.stdout.splitlines()[0])
    assert first["event"] == "replay.detector" and first["weights"] == "builtin:sim-rover"
    assert "--profile builtin:spec-rover" in first["hint"]
    entry = json.loads(report.read_text())["policies"]["learn"]
    assert entry["compute"]["percepts"] >= 1 and entry["timeline"]  # the last inference was waited for
    assert entry["reference"] == "none" and entry["quality"]["f1"] is None
    assert entry["quality"]["note"] == "no ground truth"
    detector = entry["detector"]
    assert detector["checkpoint"] == "sim-rover.pt" and "--profile builtin:spec-rover" in detector["hint"]
    assert detector["chosen_by"].startswith("the default profile")
    table = ran.stdout[ran.stdout.index("policy "):]
    assert "no ground truth" in table and "0.000" not in table
    assert "detector: builtin:sim-rover (sim-rover.pt) on cpu" in table


FIXTURES = LLVIP.parents[1] / "rosbags" / "rosbag2_fixtures"


@pytest.mark.parametrize(("storage", "messages", "topic"), [
    ("rosbag2_py/test/resources/mcap/talker/talker.mcap", 20, "/topic [std_msgs/msg/String]"),
    ("rosbag2_tests/resources/mcap/cdr_test/cdr_test_0.mcap", 7, "/array_topic [test_msgs/msg/Arrays]"),
    ("rosbag2_py/test/resources/mcap/wbag/wbag_2.mcap", 1240, "AAA [std_msgs/msg/String]"),
])
def test_a_ros2_mcap_copied_alone_is_a_bag(tmp_path: Path, storage: str, messages: int, topic: str) -> None:
    """What rosbag2 itself wrote, without its metadata.yaml: a bag for log info and --replay, never
    a respecd log ('format 1', no sensors). These hold no sensor topic: the replay says so, naming them."""
    alone = tmp_path / Path(storage).name
    alone.write_bytes((FIXTURES / storage).read_bytes())
    info = run_cli("log", "info", str(alone), "--json")
    assert info.returncode == 0, info.stderr
    described = json.loads(info.stdout)
    assert described["kind"] == "rosbag2" and described["messages"] == messages
    ran = run_cli("--replay", str(alone), "--speed", "max")
    assert ran.returncode == 2 and "Traceback" not in ran.stderr
    assert f"{alone}: no sensor_msgs Image/CompressedImage/PointCloud2/Imu topic to replay" in ran.stderr
    assert topic in ran.stderr and "format 1" not in ran.stderr


@pytest.mark.slow
def test_a_camera_bags_mcap_copied_alone_replays_with_and_without_topics(tmp_path: Path) -> None:
    bag = write_camera_bag(tmp_path / "bag", photos(6), hz=4)
    alone = tmp_path / "alone" / "street.mcap"
    alone.parent.mkdir()
    alone.write_bytes(next(bag.glob("*.mcap")).read_bytes())
    for topics in ((), ("--topics", "rgb=/camera/color/image_raw/compressed")):
        report = tmp_path / f"r{len(topics)}.json"
        ran = run_cli("--replay", str(alone), *topics, "--speed", "max", "--policy", "static", "--report", str(report))
        assert ran.returncode == 0, ran.stderr[-2000:]
        assert ("guessed from message types: --topics rgb=/camera/color/image_raw/compressed" in ran.stderr) == \
            (not topics)
        entry = json.loads(report.read_text())["policies"]["static"]
        assert entry["compute"]["frames"] == {"rgb": 6} and entry["compute"]["percepts"] >= 1
