"""The accuracy-load frontier of configurations held per scene (respecd experiment frontier)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import structlog
import yaml

from respecd.cli import main as cli_main
from respecd.config import load_profile
from respecd.lab.detector.metrics import ImageResult
from respecd.lab.experiment.frontier import Cell, against, cheapest_within, descend, family, run

BOX = np.array([[10.0, 10.0, 50.0, 90.0]], np.float32)


@pytest.fixture(autouse=True)
def fresh_logging():
    yield
    structlog.reset_defaults()


def _cell(found: bool, load: float, n: int = 4) -> Cell:
    """``n`` instants of one person each, found (a box on it at 0.9) or missed, at ``load``."""
    hit = ImageResult(BOX.copy(), np.array([0.9], np.float32), BOX.copy())
    miss = ImageResult(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), BOX.copy())
    return Cell([hit if found else miss for _ in range(n)], [load] * n, [1e6] * n)


def test_family_pins_one_rate_and_one_size_per_sensor() -> None:
    actions = load_profile("builtin:sim-rover").controller.actions
    configurations = family(actions)
    assert len(configurations) == 5 * 3 * 2  # rates x RGB sizes x thermal sizes
    change = configurations["rgb 960x540 thermal 160x120 radar range @15"]
    pinned = actions.model_copy(update=change)
    assert pinned.rate_levels_hz == (15.0,) and pinned.rgb_resolutions == ((960, 540),)
    assert pinned.thermal_resolutions == ((160, 120),) and pinned.radar_modes == ("range",)


def test_descent_gives_up_the_cheapest_accuracy_first() -> None:
    table = {
        "a": {"rich": _cell(True, 0.5), "lean": _cell(False, 0.4)},  # saves 0.1 for a miss
        "b": {"rich": _cell(True, 0.5), "lean": _cell(False, 0.1)},  # saves 0.4 for the same miss
        "c": {"rich": _cell(True, 0.5), "lean": _cell(True, 0.2), "waste": _cell(True, 0.6)},
    }
    points = descend(table)
    assert points[0]["choice"] == {"a": "rich", "b": "rich", "c": "lean"}  # as accurate, cheaper; never "waste"
    assert points[0]["map50"] == pytest.approx(1.0) and points[0]["accelerator_load"] == pytest.approx(0.4)
    assert points[1]["choice"] == {"a": "rich", "b": "lean", "c": "lean"}
    assert points[-1]["choice"] == {"a": "lean", "b": "lean", "c": "lean"} and len(points) == 3
    loads = [p["accelerator_load"] for p in points]
    assert loads == sorted(loads, reverse=True)


def test_against_a_policy_takes_the_cheapest_point_within_tolerance() -> None:
    points = [{"map50": 0.90, "accelerator_load": 0.40}, {"map50": 0.85, "accelerator_load": 0.20},
              {"map50": 0.70, "accelerator_load": 0.10}]
    assert cheapest_within(points, 0.86, 0.01) == points[1]
    assert cheapest_within(points, 0.95, 0.01) is None
    bench = {"pooled": {"heuristic": {"map50": 0.86, "accelerator_load": 0.25},
                        "static": {"map50": 0.95, "accelerator_load": 0.7}}}
    out = against(points, bench, 0.01)
    assert out["heuristic"]["frontier_load"] == 0.20 and out["heuristic"]["load_reduction"] == pytest.approx(0.2)
    assert out["static"]["frontier_load"] is None and out["static"]["load_reduction"] is None


@pytest.fixture(scope="module")
def tiny_profile(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """sim-rover with a very narrow detector, one RGB size and two rates: four configurations."""
    from importlib import resources

    doc = yaml.safe_load((resources.files("respecd.profiles") / "sim-rover.yaml").read_text())
    doc["perception"] = {"model": {"rgb_widths": [4, 8, 8, 16, 16], "aux_widths": [4, 8, 8, 16, 16],
                                   "neck_widths": [8, 16, 16], "reg_max": 4}, "torch_threads": 1}
    doc["controller"] = {"min_dwell_s": 0, "actions": {"rgb_resolutions": [[640, 360]], "rate_levels_hz": [1, 30]}}
    path = tmp_path_factory.mktemp("profile") / "tiny.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.slow
def test_every_configuration_runs_under_one_accelerator(tiny_profile: Path, tmp_path: Path) -> None:
    latency = tmp_path / "lat.json"
    latency.write_text(json.dumps({"latency_ms": {"640x360": {"forward_ms": 20.0, "attribution_ms": 50.0}}}))
    result = run(str(tiny_profile), 0, 1, 2.0, str(latency), tmp_path / "cache", random_detector=True)
    again = run(str(tiny_profile), 0, 1, 2.0, str(latency), tmp_path / "cache", random_detector=True,
                choices=[p["choice"] for p in result["frontier"]])
    assert again["chosen_elsewhere"] == result["frontier"]  # the same choices on the same worlds score the same
    rows = result["configurations"]
    assert len(rows) == 7 and all(len(row) == 4 for row in rows.values())
    for row in rows.values():  # the detector runs on every new frame: 30 Hz costs more than 1 Hz
        assert row["rgb 640x360 thermal 160x120 radar range @30"]["accelerator_load"] > \
            row["rgb 640x360 thermal 160x120 radar range @1"]["accelerator_load"] > 0.0
    loads = [p["accelerator_load"] for p in result["frontier"]]
    assert loads == sorted(loads, reverse=True) and result["world_seeds"] == [0, 6]


def test_against_what_is_not_a_bench_json_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bench = tmp_path / "bench.json"
    bench.write_text(json.dumps({"pooled": {"rl": {"map50": 0.8}}}))
    assert cli_main(["experiment", "frontier", "--against", str(bench)]) == 2
    err = capsys.readouterr().err
    assert "expected a bench scenarios JSON" in err and "Traceback" not in err


def test_against_a_run_of_other_worlds_is_refused_before_running(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    bench = tmp_path / "bench.json"
    bench.write_text(json.dumps({"pooled": {"rl": {"map50": 0.8, "accelerator_load": 0.2}}, "world_seeds": [500, 520],
                                 "latency_table": "orin-nano (orin-nano.json), estimate",
                                 "duration_s_per_scenario": 20.0}))
    assert cli_main(["experiment", "frontier", "--seed", "8000", "--against", str(bench)]) == 2
    assert "world_seeds [500, 520], expected [8000, 8020]" in capsys.readouterr().err


def test_choices_of_another_profile_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    other = tmp_path / "frontier.json"
    other.write_text(json.dumps({"frontier": [{"choice": {"good-light-static": "rgb 4k @1"}}]}))
    assert cli_main(["experiment", "frontier", "--choices-from", str(other)]) == 2
    assert "frontier[0].choice is not one configuration of this profile's family" in capsys.readouterr().err
