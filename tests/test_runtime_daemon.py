"""The daemon and ``--replay --speed max`` with ``perception.runtime`` onnxruntime and openvino: the
checkpoint is exported into the state directory on the first start, and a lockstep replay gives the
percepts torch gives (same instants, confidences and contributions within the equality tolerances).
Each runtime's tests skip where it is not installed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import structlog
import yaml

from respecd.cli import main
from respecd.perception.runtimes import installed

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
RESPECD = [sys.executable, "-m", "respecd.cli"]
RUNTIMES = [pytest.param(name, marks=pytest.mark.skipif(
    not (installed(name) and installed("onnx")), reason=f"{name} is not installed (pip install -e '.[{extra}]')"))
    for name, extra in (("onnxruntime", "onnx"), ("openvino", "openvino"))]


@pytest.fixture(autouse=True)
def _fresh_logging():
    yield
    structlog.reset_defaults()


def _profile(root: Path, perception: dict) -> Path:
    """The simulated rover at 640x360 without depth, with this perception section."""
    profile = yaml.safe_load((CONFIGS / "sim-rover.yaml").read_text())
    profile["name"] = "runtime-test"
    profile["sensors"] = [s for s in profile["sensors"] if s["name"] != "depth"]
    profile["sensors"][0]["resolution"] = [640, 360]
    profile["perception"] = perception
    profile["controller"] = {"decision_period_s": 0.5, "window_s": 0.5}
    path = root / f"profile-{perception.get('runtime', 'torch')}.yaml"
    path.write_text(yaml.safe_dump(profile))
    return path


@pytest.fixture(scope="module")
def session_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 s of the simulated rover, recorded in lockstep (the same log whatever the machine's
    load) without the detector (the replays run it)."""
    from respecd.config import load_profile
    from respecd.record.simulated import record_simulated

    root = tmp_path_factory.mktemp("session")
    profile = load_profile(_profile(root, {"enabled": False}))
    return record_simulated(profile, root / "session.mcap", seconds=3.0, seed=0)


def _replay(log: Path, root: Path, runtime: str) -> dict:
    report = root / f"{runtime}.json"
    config = _profile(root, {"enabled": True, "runtime": runtime})
    argv = ["--replay", str(log), "--speed", "max", "--config", str(config), "--duration", "2", "--seed", "3",
            "--state-dir", str(root / "state"), "--report", str(report), "--log-level", "warning"]
    assert main(argv) == 0
    return json.loads(report.read_text())["policies"]["learn"]


@pytest.mark.slow
@pytest.mark.parametrize("runtime", RUNTIMES)
def test_a_lockstep_replay_through_a_runtime_gives_torchs_percepts(session_log: Path, tmp_path: Path,
                                                                   runtime: str) -> None:
    want, got = _replay(session_log, tmp_path, "torch"), _replay(session_log, tmp_path, runtime)
    assert [p["t"] for p in got["timeline"]] == [p["t"] for p in want["timeline"]] and len(want["timeline"]) >= 3
    for a, b in zip(want["timeline"], got["timeline"], strict=True):
        assert b["conf_agg"] == pytest.approx(a["conf_agg"], abs=2e-4)
        assert b["contributions"] == pytest.approx(a["contributions"], abs=2e-3)  # 1e-3 and the report's rounding
    assert any(p["contributions"] for p in got["timeline"])
    assert [p.name.split("-")[0] for p in (tmp_path / "state" / "exported").iterdir()] == ["sim"]  # sim-rover-...


@pytest.mark.slow
@pytest.mark.parametrize("runtime", RUNTIMES)
def test_the_live_daemon_runs_its_detector_through_a_runtime(tmp_path: Path, runtime: str) -> None:
    config = _profile(tmp_path, {"enabled": True, "runtime": runtime})
    argv = [*RESPECD, "--config", str(config), "--duration", "6", "--policy", "static", "--log-format", "json",
            "--state-dir", str(tmp_path / "state")]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=240, check=False)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    events = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    loaded = [e for e in events if e["event"] == "detector_runtime"]
    assert len(loaded) == 1 and loaded[0]["runtime"] == runtime
    assert Path(loaded[0]["export"]).parent == tmp_path / "state" / "exported"
    statuses = [e for e in events if e["event"] == "status"]
    assert any("detections" in s for s in statuses) and any("contributions" in s for s in statuses)
