"""Overlays: ``extends:`` a base (builtin:NAME or a path beside the overlay), merged key-wise
(mappings recursively, lists and values replaced whole), errors naming the file and line that
wrote the value; the JSON Schema accepts an overlay and ``respecd schema --validate`` checks one."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator

from respecd.cli import main as cli
from respecd.config import load_profile, read_profile
from respecd.errors import ConfigError
from respecd.profile_schema import json_schema

REPO = Path(__file__).resolve().parents[1]
LAB_PROFILES = REPO / "respecd" / "lab" / "profiles"
MAX_OVERLAY_LINES = 25


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def problems(source: Path) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_profile(source)
    return info.value.problems


def test_an_overlay_changes_only_what_it_writes(tmp_path):
    overlay = write(tmp_path / "o.yaml", "extends: builtin:sim-rover\nname: o\ncontroller:\n  reward:\n"
                                         "    credit: per-sensor\n")
    base, profile = load_profile("builtin:sim-rover"), load_profile(overlay)
    assert profile.name == "o" and profile.controller.reward.credit == "per-sensor"
    assert profile.controller.reward.staleness == base.controller.reward.staleness  # a sibling kept
    assert profile.model_copy(update={"name": base.name, "controller": base.controller}) == base


def test_lists_are_replaced_whole_and_mappings_merged(tmp_path):
    overlay = write(tmp_path / "o.yaml", """\
extends: builtin:sim-rover
simulation:
  scenarios: [behind-curtain]
sensors:
  - {name: cam, driver: sim, modality: rgb, power: {per_hz_w: {"640x360": 0.1}}}
""")
    profile = load_profile(overlay)
    assert profile.simulation.scenarios == ["behind-curtain"]  # not appended to sim-rover's seven
    assert profile.simulation.people == load_profile("builtin:sim-rover").simulation.people
    assert [s.name for s in profile.sensors] == ["cam"]  # the base's five are gone, not merged by index


def test_a_mapping_of_the_base_is_merged_key_by_key(tmp_path):
    write(tmp_path / "base.yaml", """\
name: base
sensors:
  - {name: cam, driver: sim, modality: rgb}
controller:
  reward: {beta: 0.2, gamma: 0.5}
""")
    overlay = write(tmp_path / "o.yaml", "extends: base.yaml\ncontroller:\n  reward: {gamma: 0.0}\n")
    reward = load_profile(overlay).controller.reward
    assert (reward.beta, reward.gamma) == (0.2, 0.0)


def test_an_overlays_error_names_its_own_file_and_line(tmp_path):
    overlay = write(tmp_path / "o.yaml", "extends: builtin:sim-rover\nname: o\n\nsync:\n  max_rate_hz: 45\n")
    assert problems(overlay) == [f"{overlay}:5: sync.max_rate_hz: Input should be less than or equal to 30 (got 45)"]


def test_an_error_in_an_inherited_value_names_the_base_file(tmp_path):
    base = write(tmp_path / "bases" / "base.yaml", """\
name: base
sensors:
  - name: cam
    driver: sim
    modality: rgb
    rate_hz: 45
""")
    overlay = write(tmp_path / "o.yaml", "extends: bases/base.yaml\nname: o\nsync:\n  max_rate_hz: 45\n")
    assert problems(overlay) == [
        f"{base}:6: sensors.0.rate_hz: Input should be less than or equal to 30 (got 45)",
        f"{overlay}:4: sync.max_rate_hz: Input should be less than or equal to 30 (got 45)",
    ]


def test_a_value_replaced_by_the_overlay_is_the_overlays(tmp_path):
    base = write(tmp_path / "base.yaml", "name: base\nsensors:\n  - {name: cam, driver: sim, modality: rgb, x: 1}\n")
    overlay = write(tmp_path / "o.yaml", "extends: base.yaml\n\nsensors:\n  - {name: cam, driver: sim, bogus: 2}\n")
    assert {p.split(": ")[0] for p in problems(overlay)} == {f"{overlay}:4"}  # the base's bad list is gone
    assert not [p for p in problems(overlay) if str(base) in p]


def test_chains_resolve_relative_to_each_file_not_the_working_directory(tmp_path, monkeypatch):
    write(tmp_path / "a" / "base.yaml", "extends: builtin:sim-rover\nname: base\nsync: {max_rate_hz: 20}\n")
    write(tmp_path / "a" / "b" / "mid.yaml", "extends: ../base.yaml\nname: mid\nsync: {min_rate_hz: 2}\n")
    top = write(tmp_path / "top.yaml", "extends: a/b/mid.yaml\nname: top\n")
    monkeypatch.chdir(tmp_path / "a")
    profile = load_profile(top)
    assert (profile.name, profile.sync.max_rate_hz, profile.sync.min_rate_hz) == ("top", 20, 2)


def test_a_cycle_is_a_clear_error_and_check_config_exits_2(tmp_path, capsys):
    a = write(tmp_path / "a.yaml", "extends: b.yaml\nname: a\n")
    b = write(tmp_path / "b.yaml", "# b\nextends: a.yaml\n")
    assert problems(a) == [f"{b}:2: extends: profiles extend each other in a cycle: {a} -> {b} -> {a}"]
    assert cli(["check-config", str(a)]) == 2
    err = capsys.readouterr().err
    assert "cycle" in err and "Traceback" not in err
    itself = write(tmp_path / "self.yaml", "extends: self.yaml\n")
    assert "cycle" in problems(itself)[0]


def test_a_missing_or_malformed_base_names_the_extends_line(tmp_path):
    missing = write(tmp_path / "o.yaml", "name: o\nextends: nowhere.yaml\n")
    assert problems(missing) == [f"{missing}:2: extends: {tmp_path / 'nowhere.yaml'}: no such file"]
    unknown = write(tmp_path / "u.yaml", "extends: builtin:no-such-rover\n")
    assert problems(unknown) == [f"{unknown}:1: extends: builtin:no-such-rover: no built-in profile named "
                                 "'no-such-rover'"]
    number = write(tmp_path / "n.yaml", "extends: 3\n")
    assert problems(number) == [f"{number}:1: extends: expected builtin:NAME or a path to a profile, got 3"]


def test_check_config_and_the_preflight_name_the_file_that_wrote_the_value(tmp_path, capsys):
    from respecd.preflight import check_profile

    overlay = write(tmp_path / "o.yaml", "extends: builtin:sim-rover\nname: o\nperception:\n"
                                         "  weights: /nonexistent/rover.pt\n")
    assert check_profile(read_profile(overlay)) == [
        f"{overlay}:4: perception.weights: /nonexistent/rover.pt: no such checkpoint file"]
    good = write(tmp_path / "good.yaml", "extends: builtin:sim-rover\nname: good\n")
    assert cli(["check-config", str(good)]) == 0
    assert f"{good}: ok (good, 5 sensors)" in capsys.readouterr().out


@pytest.mark.e2e
def test_the_daemon_runs_an_overlay(tmp_path):
    overlay = write(tmp_path / "quick.yaml", "extends: builtin:sim-rover\nname: quick\nperception: {enabled: false}\n")
    result = subprocess.run([sys.executable, "-m", "respecd.cli", "--config", str(overlay), "--duration", "1",
                             "--policy", "static", "--state-dir", str(tmp_path / "state"), "--log-format", "json"],
                            capture_output=True, text=True, timeout=90)
    assert result.returncode == 0, result.stderr[-2000:]
    events = [json.loads(line) for line in result.stderr.splitlines() + result.stdout.splitlines()
              if line.startswith("{")]
    assert any(e.get("event") == "pipeline_up" and e.get("profile") == "quick" for e in events)


# -- the schema -------------------------------------------------------------------------------------

def _mapping_paths(schema: dict, node: dict, path: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every key path that holds a mapping of known keys, reached through mappings only."""
    if "$ref" in node:
        node = schema["$defs"][node["$ref"].split("/")[-1]]
    for option in node.get("anyOf", []):
        if "$ref" in option or "properties" in option:
            return _mapping_paths(schema, option, path)
    found = [path] if "properties" in node else []
    for key, child in node.get("properties", {}).items():
        found += _mapping_paths(schema, child, (*path, key))
    return found


def test_the_schema_accepts_any_partial_overlay_and_still_knows_the_keys():
    schema = json_schema()
    validator = Draft202012Validator(schema)
    paths = _mapping_paths(schema, schema)
    assert ("controller", "reward") in paths and ("sync",) in paths
    for path in paths:  # an overlay may write any section with none of its keys
        document: dict = {"extends": "builtin:sim-rover"}
        cursor = document
        for key in path:
            cursor = cursor.setdefault(key, {})
        assert not list(validator.iter_errors(document)), path
    assert list(validator.iter_errors({"extends": "builtin:sim-rover", "sync": {"max_rate": 1}}))  # a typo
    assert list(validator.iter_errors({"sync": {}}))  # not an overlay: name and sensors are required
    whole = {"name": "x", "sensors": [{"name": "cam", "driver": "sim", "modality": "rgb"}]}
    assert not list(validator.iter_errors(whole))
    assert list(validator.iter_errors({**whole, "simulation": {"rgb_intrinsics": {"fx": 500}}}))  # nothing to merge


def test_schema_validate_accepts_an_overlay_and_names_a_typo_line(tmp_path, capsys):
    overlay = write(tmp_path / "o.yaml", "extends: builtin:sim-rover\ncontroller:\n  reward:\n    credit: per-sensor\n")
    assert cli(["schema", "--validate", str(overlay)]) == 0
    assert f"{overlay}: ok" in capsys.readouterr().out
    bad = write(tmp_path / "bad.yaml", """\
extends: builtin:sim-rover
controller:
  reward:
    credt: per-sensor
sensors:
  - {name: cam, driver: simm}
  - {name: cam2, driver: sim, rate_hz: fast}
""")
    whole = write(tmp_path / "whole.yaml", "sync: {}\n")
    assert cli(["schema", "--validate", str(bad), str(whole)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"{bad}:4: controller.reward.credt: unknown key (check the spelling; `respecd schema` lists the valid keys)",
        f"{bad}:6: sensors.0.driver: unknown driver 'simm' (expected one of: flirone, iwr6843, realsense, replay, "
        "sim, uvc)",
        f"{bad}:7: sensors.1.modality: required key is missing",
        f"{bad}:7: sensors.1.rate_hz: 'fast' is not of type 'number'",
        f"{whole}:1: name: required key is missing",
        f"{whole}:1: sensors: required key is missing",
    ]


# -- the shipped overlays ---------------------------------------------------------------------------

def _overlays() -> list[Path]:
    files = [*(REPO / "configs").glob("*.yaml"), *LAB_PROFILES.glob("*.yaml")]
    return sorted(f for f in files if "\nextends:" in f.read_text())


def test_every_lab_candidate_is_a_small_overlay_that_resolves_and_matches_the_schema(capsys):
    assert set(LAB_PROFILES.glob("*.yaml")) <= set(_overlays())
    assert any(p.parent.name == "configs" for p in _overlays())
    for path in _overlays():
        assert len(path.read_text().splitlines()) <= MAX_OVERLAY_LINES, path
        assert load_profile(path).name == path.stem
        assert cli(["schema", "--validate", str(path)]) == 0, capsys.readouterr().err
    assert not [p for p in (REPO / "configs").glob("sim-rover-*.yaml")], "candidates live in respecd/lab/profiles"


@pytest.mark.e2e
def test_a_profile_without_a_realsense_loads_without_pyrealsense2():
    """The sensor union is built at import from every driver's config model; the drivers import
    their SDKs only when a sensor starts. ``None`` in sys.modules makes ``import pyrealsense2`` fail."""
    code = ("import sys; sys.modules['pyrealsense2'] = None; from respecd.config import load_profile; "
            "print(load_profile('builtin:sim-rover').name)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert (result.returncode, result.stdout) == (0, "sim-rover\n"), result.stderr
