"""Profiles: the shipped ones and the lab's candidates validate; bad ones give FILE:LINE: path: message,
exit 2. Overlays (``extends:``): tests/test_profile_overlay.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import run_cli

from respecd.config import load_profile
from respecd.errors import ConfigError
from respecd.profile_schema import json_schema

REPO = Path(__file__).resolve().parents[1]
LAB_PROFILES = REPO / "respecd" / "lab" / "profiles"

BAD = """\
name: bad
sensors:
  - name: rgb
    driver: sim
    modality: rgb
    rate_hz: 45
    resolutoin: [640, 360]
  - name: thermal
    driver: simm
    modality: thermal
sync:
  max_rate_hz: "fast"
"""


def problems_of(tmp_path: Path, text: str) -> list[str]:
    path = tmp_path / "profile.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_profile(path)
    return [p.replace(str(path), "P") for p in info.value.problems]


@pytest.mark.parametrize("path", sorted([*(REPO / "configs").glob("*.yaml"), *LAB_PROFILES.glob("*.yaml")]),
                         ids=lambda p: p.name)
def test_shipped_and_lab_profiles_validate(path):
    profile = load_profile(path)
    assert profile.sensors


def test_embedded_default_profile_loads_from_the_package():
    assert load_profile("builtin:sim-rover").name == "sim-rover"


def _ablation_difference(name: str, key: str) -> tuple[object, object]:
    """``controller.<key>`` of sim-rover and of the lab's candidate ``<name>.yaml``, after checking
    that nothing else but the name differs: docs/RESULTS.md compares the two, and any other drift
    (an overlay writing one key too many) would make that comparison unfair."""
    base = load_profile("builtin:sim-rover").model_dump()
    ablation = load_profile(LAB_PROFILES / f"{name}.yaml").model_dump()
    base_value, ablation_value = base["controller"].pop(key), ablation["controller"].pop(key)
    # the candidates were learned with each sensor at its own rate; sim-rover ties them since M44TS
    assert ablation["controller"]["actions"].pop("shared_rate") == ()
    assert base["controller"]["actions"].pop("shared_rate") == ("rgb", "thermal", "radar")
    assert ablation.pop("name") == name and base.pop("name") == "sim-rover"
    assert ablation == base
    return base_value, ablation_value


def test_paper_reward_ablation_differs_from_sim_rover_only_in_the_reward():
    base_reward, ablation_reward = _ablation_difference("sim-rover-paper-reward", "reward")
    assert ablation_reward == {**base_reward, "alpha": 4.0, "confidence_level": 0.0, "compute_w": 0.0,
                               "staleness": (0.0, 0.0, 0.0), "bandwidth": 0.0}


def test_free_bandwidth_ablation_differs_from_sim_rover_only_in_the_bandwidth_weight():
    base_reward, ablation_reward = _ablation_difference("sim-rover-free-bandwidth", "reward")
    assert base_reward["bandwidth"] > 0 and ablation_reward == {**base_reward, "bandwidth": 0.0}


def test_per_sensor_candidates_differ_from_their_bases_only_in_the_credit():
    base_reward, candidate_reward = _ablation_difference("sim-rover-per-sensor", "reward")
    assert base_reward["credit"] == "shared" and candidate_reward == {**base_reward, "credit": "per-sensor"}
    _, free = _ablation_difference("sim-rover-free-bandwidth", "reward")
    _, free_per_sensor = _ablation_difference("sim-rover-per-sensor-free-bandwidth", "reward")
    assert free_per_sensor == {**free, "credit": "per-sensor"}


def test_resolution_candidates_differ_from_e_only_in_latency_and_quality_weights():
    _, e = _ablation_difference("sim-rover-per-sensor-free-bandwidth", "reward")
    _, g = _ablation_difference("sim-rover-no-latency", "reward")
    _, h = _ablation_difference("sim-rover-quality", "reward")
    assert e["gamma"] > 0 and g == {**e, "gamma": 0.0}
    assert h == {**g, "confidence_level": h["confidence_level"]}
    assert h["confidence_level"] == pytest.approx(3 * e["confidence_level"])


def test_slowest_delay_candidates_differ_from_their_parents_only_in_what_each_adds():
    _, f = _ablation_difference("sim-rover-per-sensor", "reward")
    _, e = _ablation_difference("sim-rover-per-sensor-free-bandwidth", "reward")
    _, s = _ablation_difference("sim-rover-per-sensor-slowest", "reward")
    _, se = _ablation_difference("sim-rover-per-sensor-free-bandwidth-slowest", "reward")
    _, se44 = _ablation_difference("sim-rover-per-sensor-free-bandwidth-slowest-44", "reward")
    assert f["delay"] == e["delay"] == "contribution"
    assert s == {**f, "delay": "slowest"} and se == {**e, "delay": "slowest"}
    assert se["staleness"] == (0.0, 2.0, 4.0) and se44 == {**se, "staleness": (0.0, 4.0, 4.0)}
    _, s44 = _ablation_difference("sim-rover-per-sensor-slowest-44", "reward")
    _, m44 = _ablation_difference("sim-rover-per-sensor-slowest-44-immediate", "reward")
    assert s["bandwidth"] > 0 and s44 == {**s, "staleness": (0.0, 4.0, 4.0)}
    assert s44 == {**se44, "bandwidth": s["bandwidth"]}
    assert s44["unread"] == "bootstrap" and m44 == {**s44, "unread": "immediate"}


def test_heavy_bandwidth_candidate_differs_from_sim_rover_only_in_the_bandwidth_weight():
    base_reward, candidate_reward = _ablation_difference("sim-rover-heavy-bandwidth", "reward")
    assert candidate_reward == {**base_reward, "bandwidth": 3 * base_reward["bandwidth"]}


def test_no_load_ablation_differs_from_sim_rover_only_in_the_learners_factors():
    base_factors, ablation_factors = _ablation_difference("sim-rover-no-load", "factors")
    assert ablation_factors == tuple(f for f in base_factors if f != "load")


def test_every_problem_has_file_line_path_and_expectation(tmp_path):
    assert problems_of(tmp_path, BAD) == [
        "P:6: sensors.0.rate_hz: Input should be less than or equal to 30 (got 45)",
        "P:7: sensors.0.resolutoin: unknown key (check the spelling; `respecd schema` lists the valid keys)",
        "P:9: sensors.1.driver: unknown driver 'simm' (expected one of: "
        + ", ".join(sorted(__import__("respecd.drivers").drivers.DRIVERS))
        + ")",
        "P:12: sync.max_rate_hz: expected a number, got the text 'fast'",
    ]


def test_missing_required_key(tmp_path):
    problems = problems_of(tmp_path, "name: x\nsensors:\n  - driver: sim\n    modality: rgb\n")
    assert problems == ["P:3: sensors.0.name: required key is missing"]


def test_yaml_syntax_error_names_the_line(tmp_path):
    problems = problems_of(tmp_path, "name: x\nsensors: [\n  - a: b\n")
    assert len(problems) == 1 and problems[0].startswith("P:3: not valid YAML")


def test_top_level_must_be_a_mapping(tmp_path):
    assert problems_of(tmp_path, "- just a list\n")[0].startswith("P:1: profile must be a mapping")


def test_duplicate_sensor_names(tmp_path):
    text = "name: x\nsensors:\n" + "  - {name: cam, driver: sim, modality: rgb}\n" * 2
    assert "sensor names must be unique, repeated: cam" in problems_of(tmp_path, text)[0]


def test_missing_file():
    with pytest.raises(ConfigError, match="no such file"):
        load_profile("/nonexistent/profile.yaml")


def test_check_config_cli_exits_2_without_traceback(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(BAD)
    good = REPO / "configs" / "sim-rover.yaml"
    result = run_cli("check-config", str(good), str(bad))
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert f"{bad}:7: sensors.0.resolutoin: unknown key" in result.stderr
    assert "sim-rover.yaml: ok" in result.stdout


def test_run_with_bad_profile_exits_2(tmp_path):
    result = run_cli("--config", str(tmp_path / "absent.yaml"), "--state-dir", str(tmp_path / "state"))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "absent.yaml: no such file" in result.stderr


def test_schema_command_prints_the_profile_schema():
    result = run_cli("schema")
    schema = json.loads(result.stdout)
    assert schema["title"] == "respecd profile"
    assert {"sensors", "sync", "perception", "controller", "recording", "telemetry"} <= set(schema["properties"])


def test_shipped_schema_file_is_current():
    """The profiles point yaml-language-server at profile.schema.json beside them (configs/ links
    docs/profile.schema.json; the wheel ships it), the lab's at docs/: keep it in step."""
    assert (REPO / "configs" / "profile.schema.json").resolve() == (REPO / "docs" / "profile.schema.json").resolve()
    for profile in (REPO / "configs").glob("*.yaml"):
        assert profile.read_text().startswith("# yaml-language-server: $schema=profile.schema.json\n"), profile
    for profile in LAB_PROFILES.glob("*.yaml"):
        header = profile.read_text().splitlines()[0]
        assert header == "# yaml-language-server: $schema=../../../docs/profile.schema.json", profile
    shipped = json.loads((REPO / "docs" / "profile.schema.json").read_text())
    assert shipped == json.loads(json.dumps(json_schema())), "run: respecd schema --out docs/profile.schema.json"


def test_averaged_candidate_differs_from_m44_only_in_the_step_size_floor():
    m44 = load_profile(LAB_PROFILES / "sim-rover-per-sensor-slowest-44-immediate.yaml").model_dump()
    averaged = load_profile(LAB_PROFILES / "sim-rover-per-sensor-slowest-44-averaged.yaml").model_dump()
    assert averaged.pop("name") == "sim-rover-per-sensor-slowest-44-averaged"
    m44.pop("name")
    m44_learning, averaged_learning = m44["controller"].pop("learning"), averaged["controller"].pop("learning")
    assert averaged == m44
    assert m44_learning["learning_rate"] == 0.2 and averaged_learning == {**m44_learning, "learning_rate": 0.05}


def test_truth_candidate_differs_from_m44_only_in_what_quality_reads():
    m44 = load_profile(LAB_PROFILES / "sim-rover-per-sensor-slowest-44-immediate.yaml").model_dump()
    truth = load_profile(LAB_PROFILES / "sim-rover-per-sensor-slowest-44-truth.yaml").model_dump()
    assert truth.pop("name") == "sim-rover-per-sensor-slowest-44-truth"
    m44.pop("name")
    assert m44["controller"]["reward"].pop("quality") == "confagg"
    assert truth["controller"]["reward"].pop("quality") == "truth"
    assert truth == m44


def test_the_profiles_sensor_union_holds_every_registered_driver():
    """``Profile.sensors`` is typed statically (mypy follows it); the registry is what starts drivers:
    a driver added to one must be added to the other."""
    import typing

    from respecd.config import SensorEntry
    from respecd.drivers import config_classes

    union, _ = typing.get_args(SensorEntry)
    assert set(typing.get_args(union)) == set(config_classes())
