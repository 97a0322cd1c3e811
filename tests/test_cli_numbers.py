"""Numeric flags are range-checked while the command line is parsed: a bad value is exit 2
with the flag's name and what was expected, no traceback, before a checkpoint loads, a
simulation starts or a benchmark runs (they used to reach numpy, torch or OpenCV, or be
silently replaced). The parser is the one the console script builds; the script itself is
started for a few of them (the full tier)."""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from respecd.argtypes import (
    non_negative_float,
    non_negative_int,
    port_number,
    positive_float,
    positive_int,
    seed,
    unit_interval,
)
from respecd.cli import build_parser
from respecd.lab.bench.controller import rate_levels
from respecd.lab.bench.live import first_port

REPO = Path(__file__).resolve().parents[1]
TABLE = str(REPO / "respecd" / "control" / "tables" / "default-qtable.npz")
LATENCY = str(REPO / "respecd" / "lab" / "experiment" / "latency_tables" / "cpu.json")
T = "{tmp}"  # replaced by the test's own folder: nothing is written into the checkout

# (arguments, the flag the error must name). Without the check each of these ran (minutes of
# training, evaluation or benchmarking, or a daemon that exits 0 at once) or ended in a traceback.
BAD: list[tuple[list[str], str]] = [
    (["--seed", "-1", "--state-dir", T], "--seed"),
    (["--duration", "-5", "--state-dir", T], "--duration"),
    (["--duration", "0", "--state-dir", T], "--duration"),
    (["--duration", "nan", "--state-dir", T], "--duration"),
    (["--duration", "inf", "--state-dir", T], "--duration"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--seed", "-1"], "--seed"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--seed", str(2**64)], "--seed"),  # torch overflowed
    (["train", "--data", "sim", "--out", T + "/t.pt", "--threads", "0"], "--threads"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--lr", "-1"], "--lr"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--lr", "nan"], "--lr"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--keep-cut", "5"], "--keep-cut"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--pseudo-rgb", "-0.5"], "--pseudo-rgb"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--batch", "0"], "--batch"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--eval-frames", "-1"], "--eval-frames"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--val-limit", "0"], "--val-limit"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--scale", "0"], "--scale"),
    (["train", "--data", "sim", "--out", T + "/t.pt", "--radar-alone", "nan"], "--radar-alone"),
    (["train-policy", "--state-dir", T, "--seed", "-1"], "--seed"),
    (["train-policy", "--state-dir", T, "--max-minutes", "-1"], "--max-minutes"),
    (["train-policy", "--state-dir", T, "--samples-per-s", "nan"], "--samples-per-s"),
    (["train-policy", "--state-dir", T, "--max-s", "inf"], "--max-s"),
    (["train-policy", "--state-dir", T, "--latency-repeats", "0"], "--latency-repeats"),
    (["eval", "--out", T, "--seed", "-1"], "--seed"),
    (["eval", "--out", T, "--threads", "0"], "--threads"),
    (["eval", "--out", T, "--frames", "-1"], "--frames"),
    (["eval", "--out", T, "--frames", "0"], "--frames"),
    (["eval", "--out", T, "--attribution-threshold", "2"], "--attribution-threshold"),
    (["eval", "--out", T, "--scale", "-1"], "--scale"),
    (["calibrate", "--weights", "builtin:sim-rover", "--out", T + "/c.pt", "--threads", "0"], "--threads"),
    (["policy", "show", TABLE, "--limit", "-3"], "--limit"),
    (["radar-profile", "--fps", "nan"], "--fps"),
    (["bench", "pipeline", "--seconds", "0"], "--seconds"),
    (["bench", "pipeline", "--seconds", "-1"], "--seconds"),
    (["bench", "sim", "--frames", "0"], "--frames"),
    (["bench", "sim", "--seconds", "-1"], "--seconds"),
    (["bench", "live", "--seconds", "-1"], "--seconds"),
    (["bench", "live", "--port", "99999"], "--port"),
    (["bench", "live", "--port", "65535"], "--port"),
    (["bench", "inference", "--repeats", "0"], "--repeats"),
    (["bench", "controller", "--seed", "-1"], "--seed"),
    (["bench", "controller", "--steps", "-5"], "--steps"),
    (["bench", "controller", "--percepts", "-1"], "--percepts"),
    (["bench", "controller", "--rate-levels", "0"], "--rate-levels"),
    (["bench", "scenarios", "--duration", "-1"], "--duration"),
    (["bench", "scenarios", "--seed", "-1"], "--seed"),
    (["bench", "soak", "--minutes", "-1"], "--minutes"),
    (["bench", "soak", "--every", "0"], "--every"),
    (["bench", "replay", "--seconds", "0"], "--seconds"),
    (["bench", "peers", "--sync-seconds", "nan"], "--sync-seconds"),
    (["bench", "training", "--seed", "-1"], "--seed"),
    (["experiment", "probe", "--latency", LATENCY, "--worlds", "0"], "--worlds"),
    (["experiment", "fixed", "good-light-static", "rgb 640x360@1", "--seeds", "1,1"], "--seeds"),
    (["experiment", "latency", T + "/l.json", "--repeats", "0"], "--repeats"),
]


@pytest.fixture(scope="module")
def parser() -> argparse.ArgumentParser:
    return build_parser()


@pytest.mark.parametrize(("argv", "flag"), BAD, ids=[" ".join(a) for a, _ in BAD])
def test_a_bad_number_is_refused_while_parsing(argv: list[str], flag: str, parser: argparse.ArgumentParser,
                                               tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        parser.parse_args([a.replace(T, str(tmp_path)) for a in argv])
    err = capsys.readouterr().err
    assert exited.value.code == 2, err
    assert flag in err and "expected" in err and "Traceback" not in err


@pytest.mark.e2e
@pytest.mark.parametrize("argv", [BAD[0][0], ["bench", "pipeline", "--seconds", "0"],
                                  ["experiment", "probe", "--latency", LATENCY, "--worlds", "0"]], ids=" ".join)
def test_the_console_script_refuses_it_without_a_traceback(argv: list[str], tmp_path: Path) -> None:
    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path / "state"), "XDG_CACHE_HOME": str(tmp_path / "cache")}
    done = subprocess.run([sys.executable, "-m", "respecd.cli", *(a.replace(T, str(tmp_path)) for a in argv)],
                          capture_output=True, text=True, timeout=60, cwd=tmp_path, env=env)
    assert done.returncode == 2 and "Traceback" not in done.stderr and "expected" in done.stderr, done.stderr


def _refused(parse: Callable[[str], object], text: str) -> bool:
    try:
        parse(text)
    except argparse.ArgumentTypeError:
        return True
    return False


@pytest.mark.parametrize(("parse", "good", "bad"), [
    (non_negative_int, {"0": 0, "7": 7, "2000003": 2000003}, ["-1", "1.5", "", "x", "nan"]),
    (seed, {"0": 0, "7000": 7000, str(2**63 - 1): 2**63 - 1}, ["-1", str(2**63), str(2**64), "1.5", "x"]),
    (positive_int, {"1": 1, "40": 40}, ["0", "-3", "2.0", "inf"]),
    (port_number, {"1": 1, "8765": 8765, "65535": 65535}, ["0", "-1", "65536", "99999", "http"]),
    (first_port, {"1": 1, "28871": 28871, "65534": 65534}, ["0", "65535", "99999"]),
    (positive_float, {"0.001": 0.001, "20": 20.0, "1e3": 1000.0},
     ["0", "-0", "-5", "nan", "inf", "-inf", "1e400", "five"]),
    (non_negative_float, {"0": 0.0, "0.5": 0.5}, ["-0.1", "nan", "inf"]),
    (unit_interval, {"0": 0.0, "1": 1.0, "0.25": 0.25}, ["-0.01", "1.01", "2", "nan", "inf"]),
    (rate_levels, {"1,10,30": (1.0, 10.0, 30.0), "5": (5.0,)}, ["0", "31", "1,,30", "1,x", "nan", ""]),
])
def test_number_types_take_their_range_and_refuse_the_rest(parse: Callable[[str], object], good: dict,
                                                           bad: list[str]) -> None:
    for text, value in good.items():
        assert parse(text) == value
    refused = [text for text in bad if _refused(parse, text)]
    assert refused == bad


def test_the_error_says_what_was_expected_and_what_was_given() -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=r"expected a finite number > 0, got 'nan'"):
        positive_float("nan")
    with pytest.raises(argparse.ArgumentTypeError, match=r"expected an integer >= 0, got '-1'"):
        non_negative_int("-1")


def test_valid_values_and_documented_zeros_still_parse() -> None:
    parser = build_parser()
    daemon = parser.parse_args(["--duration", "0.5", "--seed", "0"])
    assert daemon.duration == 0.5 and daemon.seed == 0
    assert parser.parse_args([]).duration is None  # no --duration: run until SIGTERM
    train = parser.parse_args(["train", "--data", "sim", "--out", "x.pt", "--epochs", "0", "--steps", "0",
                               "--eval-frames", "0", "--patience", "0", "--keep-cut", "1", "--lr", "0.002"])
    assert (train.epochs, train.steps, train.eval_frames, train.patience, train.keep_cut) == (0, 0, 0, 0, 1.0)
    evaluation = parser.parse_args(["eval", "--frames", "1", "--attribution-threshold", "0", "--seed", "0"])
    assert (evaluation.frames, evaluation.attribution_threshold, evaluation.seed) == (1, 0.0, 0)
    assert parser.parse_args(["policy", "show", "q.npz", "--limit", "0"]).limit == 0  # every visited state
    assert parser.parse_args(["bench", "inference", "--threads", "0"]).threads == 0  # the profile's default
    assert parser.parse_args(["bench", "replay", "--torch-threads", "0"]).torch_threads == 0
    assert parser.parse_args(["bench", "live", "--slow-read-s", "0"]).slow_read_s == 0.0
    assert parser.parse_args(["bench", "controller", "--rate-levels", "1,10,30"]).rate_levels == (1.0, 10.0, 30.0)
    # the defaults are unchanged
    assert (train.threads, train.seed, train.scale, train.val_limit) == (1, 0, 0.5, 300)
    soak = parser.parse_args(["bench", "soak"])
    assert (soak.minutes, soak.every, soak.warmup_min) == (10.0, 10.0, None)
    assert math.isclose(parser.parse_args(["train-policy"]).samples_per_s, 1.0)
