"""Profiles that must not eat the machine or pass for what they are not: alias bombs, huge
files, deep nesting, duplicate keys, booleans and strings where numbers belong."""

from __future__ import annotations

import os
import subprocess
import sys
import tracemalloc
from pathlib import Path

import pytest
from conftest import run_cli

from respecd.config import load_profile, read_profile
from respecd.errors import ConfigError
from respecd.profile_yaml import MAX_VALUES, parse

REPO = Path(__file__).resolve().parents[1]
SIM = (REPO / "configs" / "sim-rover.yaml").read_text()


def _with_controller(keys: str) -> str:
    """sim-rover.yaml with ``keys`` (indented lines) added to its ``controller:`` block."""
    assert "\ncontroller:\n" in SIM
    return SIM.replace("\ncontroller:\n", "\ncontroller:\n" + keys, 1)


# 377 bytes: ten levels of nine aliases each stand for 9^10 values
BOMB = "a: &a [1,1,1,1,1,1,1,1,1]\n" + "".join(
    f"{c}: &{c} [" + ",".join(["*" + p] * 9) + "]\n" for p, c in zip("abcdefghi", "bcdefghij", strict=True)
)


def problems_of(tmp_path: Path, text: str) -> list[str]:
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_profile(path)
    return [p.replace(str(path), "P") for p in info.value.problems]


def test_alias_bomb_is_refused_before_it_expands(tmp_path: Path) -> None:
    tracemalloc.start()
    try:
        problems = problems_of(tmp_path, BOMB)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert problems == [f"P:5: aliases expand the profile to more than {MAX_VALUES} values "
                        "(a profile needs a few hundred)"]
    assert peak < 20 * 2**20  # it drove check-config past 3.4 GB


def test_check_config_on_an_alias_bomb_exits_2_without_traceback(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(BOMB)
    result = run_cli("check-config", str(bomb))
    assert result.returncode == 2 and "Traceback" not in result.stderr and "alias" in result.stderr


def test_a_huge_file_is_refused_by_its_size(tmp_path: Path) -> None:
    text = SIM + "".join(f"k{i}: [1, 2, {{a: b}}]\n" for i in range(600_000))  # ~12 MB, took 224 s and 2.3 GB
    problem, = problems_of(tmp_path, text)
    assert problem.startswith("P:1: profile is ") and "more than the 262144 allowed" in problem


def test_many_plain_values_are_refused_too(tmp_path: Path) -> None:
    text = SIM + "".join(f"k{i}: [1, 2, 3, 4, 5, 6]\n" for i in range(8000))
    problem, = problems_of(tmp_path, text)
    assert "the profile holds more than" in problem


def test_deep_nesting_and_recursive_aliases_are_errors_not_crashes(tmp_path: Path) -> None:
    assert "nested more than 64 levels" in problems_of(tmp_path, "a: " + "[" * 100 + "]" * 100 + "\n")[0]
    deep, = problems_of(tmp_path, "a: " + "[" * 50_000 + "]" * 50_000 + "\n")  # libyaml stops at 1000 itself
    assert "nested more than 64 levels" in deep or "exceeded maximum nesting depth" in deep
    assert "refers to itself" in problems_of(tmp_path, "a: &a [1, *a]\n")[0]
    assert "refers to itself" in problems_of(tmp_path, "a: &a {b: *a}\n")[0]


def test_line_index_visits_an_aliased_node_once() -> None:
    text = "x: &x [" + ",".join(["{a: 1}"] * 100) + "]\ny: [" + ",".join(["*x"] * 150) + "]\n"
    parsed = parse("P", text)
    assert len(parsed.lines) < 600  # not one entry per path (15,000 paths lead into x)
    assert parsed.lines[("y", 7)] == 2 and parsed.lines[("x", 3, "a")] == 1


def test_anchors_and_merge_keys_still_work(tmp_path: Path) -> None:
    merged = "name: m\nbase: &b {driver: sim, modality: rgb}\nsensors:\n  - {<<: *b, name: cam, rate_hz: 10}\n"
    problems = problems_of(tmp_path, merged)
    assert problems == ["P:2: base: unknown key (check the spelling; `respecd schema` lists the valid keys)"]
    path = tmp_path / "ok.yaml"
    path.write_text("name: m\nsensors:\n  - &cam {name: cam, driver: sim, modality: rgb, rate_hz: 10}\n"
                    "  - {<<: *cam, name: cam2, rate_hz: 5}\n")
    profile = load_profile(path)
    assert [(s.name, s.rate_hz) for s in profile.sensors] == [("cam", 10), ("cam2", 5)]


def test_duplicate_keys_name_both_lines(tmp_path: Path) -> None:
    text = SIM.replace("    rate_hz: 30\n", "    rate_hz: 30\n    rate_hz: 10\n", 1)
    line = text.splitlines().index("    rate_hz: 10") + 1
    expected = f"P:{line}: sensors.0.rate_hz: duplicate key (first given on line {line - 1})"
    assert problems_of(tmp_path, text) == [expected]
    first, = problems_of(tmp_path, "name: a\nname: b\nsensors: []\n")
    assert first == "P:2: name: duplicate key (first given on line 1)"


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("yes", "expected a number, got True (YAML reads yes/no/on/off/true/false as booleans)"),
        ('"30"', "expected a number, got the text '30' (write numbers without quotes)"),
        ("true", "expected a number, got True (YAML reads yes/no/on/off/true/false as booleans)"),
        # unquoted, but YAML 1.1 reads an exponent without a dot as text: "without quotes" was no help
        ("1e1", "expected a number, got the text '1e1' (YAML reads 1e1 as text, not a number: write 10, or an "
                "exponent with a dot and a sign such as 1.0e+3)"),
    ],
)
def test_numbers_must_be_numbers(tmp_path: Path, value: str, message: str) -> None:
    text = SIM.replace("    rate_hz: 30\n", f"    rate_hz: {value}\n", 1)
    line = text.splitlines().index(f"    rate_hz: {value}") + 1
    assert problems_of(tmp_path, text) == [f"P:{line}: sensors.0.rate_hz: {message}"]


def test_booleans_and_texts_are_strict_too(tmp_path: Path) -> None:
    text = SIM.replace("\nrecording:\n", '\nrecording:\n  enabled: "true"\n', 1)
    assert any("recording.enabled: expected true or false, got 'true'" in p for p in problems_of(tmp_path, text))
    assert any("name: Input should be a valid string (got 42)" in p
               for p in problems_of(tmp_path, SIM.replace("name: sim-rover", "name: 42", 1)))
    assert read_profile(REPO / "configs" / "sim-rover.yaml").model.sync.max_rate_hz == 30  # ints pass for floats


def test_paths_stay_inside_their_directories(tmp_path: Path) -> None:
    problem, = problems_of(tmp_path, _with_controller("  table_file: ../outside.npz\n"))
    assert "controller.table_file: Value error, must be a file name inside the state directory" in problem
    with pytest.raises(ConfigError, match="no built-in profile"):
        load_profile("builtin:../configs/sim-rover")


def test_a_control_character_is_named_by_its_1_based_line_without_pyyamls_position(tmp_path: Path) -> None:
    problem, = problems_of(tmp_path, "name: r\x15over\n")
    assert problem == ("P:1: not valid YAML: character U+0015 at column 8: control characters are not allowed "
                       "(a profile is plain UTF-8 text: is this the right file?)")
    problem, = problems_of(tmp_path, "name: rover\nsensors:\n  - {name: \"a\x01\"}\n")
    assert problem.startswith("P:3: not valid YAML: character U+0001 at column 14") and "position" not in problem


@pytest.mark.e2e
def test_a_device_or_a_fifo_is_refused_before_it_is_read(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"^/dev/zero: is a character device, not a regular file; expected a profile"):
        read_profile("/dev/zero")
    fifo = tmp_path / "p.yaml"
    os.mkfifo(fifo)  # opening it for reading would wait for a writer, and SIGTERM could not end the wait
    result = subprocess.run(["bash", "-c", f"ulimit -v 3000000; exec {sys.executable} -m respecd.cli check-config "
                             f"/dev/zero {fifo}"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{fifo}: is a FIFO (named pipe), not a regular file" in result.stderr


def test_bytes_that_are_not_utf8_are_named_by_offset(tmp_path: Path) -> None:
    path = tmp_path / "p.yaml"
    path.write_bytes(b"name: rover\n\x85x: 1\n")
    with pytest.raises(ConfigError, match=r"p\.yaml:2: not UTF-8 text: byte 12 is 0x85 \(expected a YAML profile"):
        read_profile(path)
