"""``evaluate``: one layout per profile whatever a log recorded, requests a log cannot serve
counted, a table that does not fit refused (exit 2), and a pure, deterministic report."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import yaml

from respecd.control.persist import StoredTable, read_table
from respecd.replay.evaluate import evaluate

pytestmark = pytest.mark.slow


def test_tables_from_logs_recorded_at_other_rates_have_the_live_layout(fleet_logs: list[Path]) -> None:
    """Each log recorded its sensors at other rates; the replay's table layout is the profile's,
    the very one the live run saved its table with."""
    live_meta, _, _ = read_table(fleet_logs[0].parent.parent / "state0" / "qtable-sim-rover-fleet.npz")
    prints = set()
    for log in fleet_logs[:3]:
        report = evaluate(log, policy="learn", duration=1.0)
        assert report.learned is not None
        prints.add(report.learned.meta["fingerprint"])
        assert report.learned.q.shape[1] == len(live_meta["layout"]["actions"]["names"])
    assert prints == {live_meta["fingerprint"]}


def test_a_rate_the_log_did_not_record_is_applied_served_and_counted(fleet_logs: list[Path]) -> None:
    log = fleet_logs[3]  # rgb recorded at 5 Hz
    result = evaluate(log, policy="static").result
    unserved = result["unserved"]["rgb"]
    assert unserved["asked_hz"] == 30.0 and unserved["recorded_hz"] < 15 and unserved["requests"] >= 1
    assert unserved["seconds"] > 1.0
    rgb = [c for c in result["configs"] if c["sensor"] == "rgb"]
    assert rgb[-1]["rate_hz"] == 30.0  # what the robot would have run (and pays for in energy)
    assert result["actions"]["switches"] == 0  # static still never moves


def _other_profile_table(log: Path, tmp_path: Path) -> Path:
    profile = yaml.safe_load((log.parent.parent / "profile0.yaml").read_text())
    profile["name"] = "sim-rover-coarse"
    profile["controller"]["actions"] = {"rate_levels_hz": [1, 10, 30]}
    learned = evaluate(log, profile=profile, policy="learn", duration=1.0).learned
    assert learned is not None
    path = tmp_path / "coarse.npz"
    learned.write(path)
    return path


def test_exploit_with_a_table_of_another_profile_exits_2_naming_the_mismatch(
    fleet_logs: list[Path], tmp_path: Path, cli
) -> None:
    other = _other_profile_table(fleet_logs[0], tmp_path)
    ran = cli("--replay", str(fleet_logs[1]), "--speed", "max", "--policy", "exploit", "--table", str(other),
              "--log-level", "warning")
    assert ran.returncode == 2, ran.stderr
    assert "coarse.npz: the Q-table does not fit" in ran.stderr
    assert "'sim-rover-coarse'" in ran.stderr and "rgb rates [1.0, 10.0, 30.0] here [1.0, 5.0, 10.0, 15.0, 30.0]" \
        in ran.stderr
    assert "Traceback" not in ran.stderr


def test_allow_no_table_runs_and_marks_the_row(fleet_logs: list[Path], tmp_path: Path, cli) -> None:
    other = _other_profile_table(fleet_logs[0], tmp_path)
    with pytest.raises(Exception, match="does not fit"):  # a given table that does not fit is never dropped
        evaluate(fleet_logs[1], policy="exploit", table=StoredTable.read(other), duration=1.0, allow_no_table=True)
    report = tmp_path / "r.json"
    ran = cli("--replay", str(fleet_logs[1]), "--speed", "max", "--policy", "exploit", "--allow-no-table",
              "--config", str(_no_shipped_profile(fleet_logs[1], tmp_path)), "--report", str(report),
              "--log-level", "warning")
    assert ran.returncode == 0, ran.stderr
    assert "no table (--allow-no-table)" in ran.stdout
    assert json.loads(report.read_text())["policies"]["exploit"]["table"] == "no table"


def _no_shipped_profile(log: Path, tmp_path: Path) -> Path:
    """The recorded profile with a state factor less: no table, not even the shipped one, fits it."""
    profile = yaml.safe_load((log.parent.parent / "profile1.yaml").read_text())
    profile["controller"]["factors"] = ["illumination", "motion", "confidence"]
    path = tmp_path / "few-factors.yaml"
    path.write_text(yaml.safe_dump(profile))
    return path


def test_exploit_without_any_table_that_fits_exits_2(fleet_logs: list[Path], tmp_path: Path, cli) -> None:
    ran = cli("--replay", str(fleet_logs[1]), "--speed", "max", "--policy", "exploit",
              "--config", str(_no_shipped_profile(fleet_logs[1], tmp_path)), "--log-level", "warning")
    assert ran.returncode == 2 and "no Q-table fits this profile" in ran.stderr, ran.stderr


def test_evaluate_writes_nothing_names_no_path_and_repeats_itself(
    fleet_logs: list[Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    state = fleet_logs[2].parent.parent / "state2"
    before = sorted(os.listdir(tmp_path)), sorted(os.listdir(state))
    a = evaluate(fleet_logs[2], policy="learn", seed=4)
    b = evaluate(fleet_logs[2], policy="learn", seed=4)
    assert (sorted(os.listdir(tmp_path)), sorted(os.listdir(state))) == before
    text = json.dumps({"log": a.log, **a.entry()})
    assert str(fleet_logs[2].parent) not in text and a.log["name"] == "rover2.mcap"
    assert a.result == b.result and a.log == b.log and len(a.result["decisions"]) >= 3
    assert set(a.timing) >= {"wall_s", "cpu_s"} and not set(a.timing) & set(a.result)
    assert a.learned is not None and b.learned is not None
    assert (a.learned.q == b.learned.q).all() and (a.learned.visits == b.learned.visits).all()
