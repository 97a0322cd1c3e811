"""``respecd fleet``: the same reports serially, in a process pool and on a local Ray instance, in
any order; a damaged log reported while the rest run; one table from many logs, exactly what one
learner fed them in order holds; sweeps from the logged reward terms; the bench's figures."""

from __future__ import annotations

import json
import random
from pathlib import Path

import numpy as np
import pytest
import yaml

from respecd.lab.fleet.eval import strip_timing

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def fleet(fleet_logs: list[Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The six logs plus a seventh cut to a third of its bytes (a copy of the first)."""
    cut = tmp_path_factory.mktemp("cut") / "cut.mcap"
    data = fleet_logs[0].read_bytes()
    cut.write_bytes(data[: len(data) // 3])
    return {"logs": fleet_logs[0].parent, "cut": cut}


def _eval(cli, logs: list[str], out: Path, *extra: str) -> dict:
    ran = cli("fleet", "eval", *logs, "--policy", "heuristic", "--out", str(out), *extra)
    assert ran.returncode == 1, ran.stdout + ran.stderr  # the cut log failed, the others ran
    return json.loads((out / "fleet.json").read_text())


def _without_timing(document: dict) -> dict:
    return strip_timing({k: v for k, v in document.items() if k != "timing"})


def test_serial_and_pool_give_the_same_reports_in_any_order(fleet: dict[str, Path], tmp_path: Path, cli) -> None:
    logs = sorted(str(p) for p in fleet["logs"].glob("*.mcap")) + [str(fleet["cut"])]
    serial = _eval(cli, logs, tmp_path / "a")
    shuffled = random.Random(7).sample(logs, len(logs))
    pool = _eval(cli, shuffled, tmp_path / "b", "--workers", "2")
    assert _without_timing(pool) == _without_timing(serial)
    entries = {e["log"]: e for e in serial["logs"]}
    assert set(entries) == {f"rover{i}.mcap" for i in range(6)} | {"cut.mcap"}
    assert entries["cut.mcap"]["report"] is None and "cut short" in entries["cut.mcap"]["error"]
    assert all(e["error"] is None and e["report"]["decisions"] for n, e in entries.items() if n != "cut.mcap")
    assert serial["pooled"]["ran"] == 6 and serial["pooled"]["failed"] == ["cut.mcap"]
    f1 = [e["report"]["quality"]["f1"] for n, e in sorted(entries.items()) if n != "cut.mcap"]
    assert serial["pooled"]["metrics"]["f1"]["mean"] == pytest.approx(sum(f1) / 6, abs=1e-6)
    assert "timing" in serial["pooled"] and serial["timing"]["backend"] == "serial"
    assert pool["timing"]["backend"] == "pool" and pool["timing"]["workers"] == 2
    for name in ("fleet.txt", "fleet.png", "logs/rover3.mcap.json"):
        assert (tmp_path / "a" / name).is_file()
    assert "failed: cut.mcap: damaged: cut short" in (tmp_path / "a" / "fleet.txt").read_text()
    assert str(fleet["logs"]) not in json.dumps(_without_timing(serial))  # names, never paths


@pytest.mark.parametrize("cpus", [1, 2])
def test_a_local_ray_instance_gives_the_serial_reports(fleet: dict[str, Path], tmp_path: Path, cli, cpus: int) -> None:
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'respecd[fleet]')")
    logs = sorted(str(p) for p in fleet["logs"].glob("*.mcap"))[:3] + [str(fleet["cut"])]
    serial = _eval(cli, logs, tmp_path / "a")
    on_ray = _eval(cli, logs[::-1], tmp_path / "b", "--address", "local", "--workers", str(cpus))
    assert on_ray["timing"]["backend"] == "ray" and on_ray["timing"]["workers"] == cpus
    assert _without_timing(on_ray) == _without_timing(serial)


def test_with_the_detector_serial_order_and_pool_agree(fleet_logs: list[Path], tmp_path: Path, cli) -> None:
    """A worker loads the detector once for all its logs: the order they come in must not show."""
    from respecd.errors import ConfigError
    from respecd.perception.checkpoint import resolve

    try:
        resolve("builtin:sim-rover")
    except ConfigError:
        pytest.skip("no built-in detector checkpoint (run `make weights`)")
    profile = yaml.safe_load((fleet_logs[0].parent.parent / "profile0.yaml").read_text())
    profile["perception"] = {"enabled": True}
    config = tmp_path / "detector.yaml"
    config.write_text(yaml.safe_dump(profile))
    from respecd.lab.fleet.eval import EvalSpec
    from respecd.lab.fleet.logs import expand
    from respecd.lab.fleet.run import Where, eval_fleet

    refs = expand([str(p) for p in fleet_logs[:3]])
    spec = EvalSpec("heuristic", profile, duration=1.5)
    forward = eval_fleet(refs, spec, Where())
    backward = eval_fleet(refs[::-1], spec, Where())
    pool = eval_fleet(refs, spec, Where(workers=2))
    assert all(e["report"]["compute"]["percepts"] >= 2 for e in forward["logs"])
    assert _without_timing(forward) == _without_timing(backward) == _without_timing(pool)


def _decisions(log: Path) -> list[dict]:
    from mcap.reader import make_reader

    with open(log, "rb") as f:
        return [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/respecd/decision"])]


def _live_learner(log: Path):
    """The controller the robot ran (its live drivers' capabilities), learning, with a fresh table."""
    from mcap.reader import make_reader

    from respecd.clock import ManualClock
    from respecd.config import Profile
    from respecd.control.controller import Controller
    from respecd.drivers import driver_class

    with open(log, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}["respecd.profile"]
    profile = Profile.model_validate(json.loads(meta["json"]))
    caps = {s.name: driver_class(s.driver)(s, ManualClock()).capabilities for s in profile.sensors}
    config = profile.controller.model_copy(update={"policy": "learn"})
    return Controller.from_profile(config, profile, caps)


def _start_ns(log: Path) -> int:
    from mcap.reader import make_reader

    with open(log, "rb") as f:
        return make_reader(f).get_summary().statistics.message_start_time


def test_fleet_learn_is_one_learner_fed_the_logs_in_order_bit_for_bit(fleet_logs: list[Path], tmp_path: Path,
                                                                      cli) -> None:
    shuffled = [str(p) for p in random.Random(3).sample(fleet_logs, len(fleet_logs))]
    assert cli("fleet", "learn", *shuffled, "--out", str(tmp_path / "a.npz")).returncode == 0
    assert cli("fleet", "learn", *shuffled[::-1], "--workers", "2", "--out", str(tmp_path / "b.npz")).returncode == 0
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert sorted(a.files) == sorted(b.files) and all(np.array_equal(a[k], b[k]) for k in a.files)
    learner = _live_learner(fleet_logs[0])  # the reference: the robot's own update, fed by hand
    table = learner.table
    for log in sorted(fleet_logs, key=lambda p: (_start_ns(p), p.name)):
        decisions = _decisions(log)
        for previous, now in zip(decisions, decisions[1:], strict=False):
            table.update(learner.states.index(previous["state"]), previous["action"], now["reward"],
                         learner.states.index(now["state"]))
    assert table.updates > 10
    assert np.array_equal(a["q"], table.q) and np.array_equal(a["visits"], table.visits)
    meta = json.loads(a["meta"].tobytes())
    assert meta["fleet"]["merge"].startswith("sequential") and len(meta["fleet"]["logs"]) == 6


def test_tables_learned_from_different_logs_have_the_robots_layout(fleet_logs: list[Path], tmp_path: Path,
                                                                    cli) -> None:
    """Logs recorded at other rates: each alone gives a table of the layout its robot saved (and the
    robot's table holds at most one update more: a decision cancelled at stop is never recorded)."""
    from respecd.control.persist import read_table

    for i in (0, 3):
        out = tmp_path / f"t{i}.npz"
        assert cli("fleet", "learn", str(fleet_logs[i]), "--out", str(out)).returncode == 0
        live_meta, _, live_visits = read_table(fleet_logs[i].parent.parent / f"state{i}" / "qtable-sim-rover-fleet.npz")
        meta, _, visits = read_table(out)
        assert meta["fingerprint"] == live_meta["fingerprint"] and visits.shape == live_visits.shape
        assert 0 <= live_meta["updates"] - meta["updates"] <= 1 and (visits <= live_visits).all()


def test_fleet_eval_with_a_table_of_another_profile_exits_2(fleet_logs: list[Path], tmp_path: Path, cli) -> None:
    profile = yaml.safe_load((fleet_logs[0].parent.parent / "profile0.yaml").read_text())
    profile["name"] = "coarse"
    profile["controller"]["actions"] = {"rate_levels_hz": [1, 30]}
    config = tmp_path / "coarse.yaml"
    config.write_text(yaml.safe_dump(profile))
    assert cli("fleet", "learn", *map(str, fleet_logs[:2]), "--profile", str(config),
               "--out", str(tmp_path / "coarse.npz")).returncode == 0
    ran = cli("fleet", "eval", *map(str, fleet_logs), "--policy", "exploit", "--table", str(tmp_path / "coarse.npz"),
              "--out", str(tmp_path / "out"))
    assert ran.returncode == 2
    assert "coarse.npz: the Q-table does not fit rover0.mcap's recorded profile" in ran.stderr
    assert "'coarse'" in ran.stderr and "rates [1.0, 30.0] here [1.0, 5.0, 10.0, 15.0, 30.0]" in ran.stderr
    assert not (tmp_path / "out" / "fleet.json").exists()


def test_sweep_reweighs_the_logged_terms_and_says_when_a_replay_is_needed(fleet_logs: list[Path], tmp_path: Path,
                                                                          cli) -> None:
    logs = [str(p) for p in fleet_logs]
    ran = cli("fleet", "sweep", *logs, "--grid", "reward.beta=0.05,0.5,reward.confidence_level=0.8,3",
              "--out", str(tmp_path / "s"))
    assert ran.returncode == 0, ran.stderr
    document = json.loads((tmp_path / "s" / "sweep.json").read_text())
    rows = {r["name"]: r for r in document["points"]}
    assert list(rows) == ["beta=0.05,confidence_level=0.8", "beta=0.05,confidence_level=3",
                          "beta=0.5,confidence_level=0.8", "beta=0.5,confidence_level=3"]
    # the profile's own weights: the logged rewards, and the very table fleet learn gives
    assert cli("fleet", "learn", *logs, "--out", str(tmp_path / "t.npz")).returncode == 0
    same = np.load(tmp_path / "s" / rows["beta=0.05,confidence_level=0.8"]["table"])
    assert np.array_equal(same["q"], np.load(tmp_path / "t.npz")["q"])
    # power costs more at beta 0.5: every decision earns less, by 0.45 W^-1 x its logged power
    assert rows["beta=0.5,confidence_level=0.8"]["reward"]["mean"] < rows["beta=0.05,confidence_level=0.8"][
        "reward"]["mean"]
    for key in ("reward.compute_w=3", "thresholds.load=0.1,0.9"):
        refused = cli("fleet", "sweep", *logs, "--grid", key, "--out", str(tmp_path / "x"))
        assert refused.returncode == 2 and "replay is needed" in refused.stderr, refused.stderr


def test_reweighed_rewards_move_by_the_changed_term_alone(fleet_logs: list[Path]) -> None:
    from respecd.control.config import RewardWeights
    from respecd.lab.fleet.logs import expand
    from respecd.lab.fleet.rewards import rewards
    from respecd.lab.fleet.transitions import steps_of

    log = steps_of(None, expand([str(fleet_logs[1])])[0])
    old = RewardWeights.model_validate(log.profile["controller"]["reward"])
    assert rewards(log.steps, old, old) == [s.reward for s in log.steps]
    new = old.model_copy(update={"beta": old.beta + 0.3, "gamma": old.gamma})
    for step, reward in zip(log.steps, rewards(log.steps, old, new), strict=True):
        assert reward == pytest.approx(step.reward - 0.3 * step.terms["power_w"], abs=1e-9)


def test_bench_fleet_reports_speedup_overhead_and_one_digest(fleet_logs: list[Path], tmp_path: Path, cli) -> None:
    out = tmp_path / "bench.json"
    ran = cli("bench", "fleet", "--use", *map(str, fleet_logs[:3]), "--workers", "1,2", "--json", str(out))
    assert ran.returncode == 0, ran.stderr
    figures = json.loads(out.read_text())
    assert set(figures["speedup"]) == {"1", "2"} and figures["speedup"]["1"] == 1.0
    assert figures["digests_agree"] and figures["overhead_ms_per_log"] >= 0
    assert len(figures["load_avg"]["before"]) == 3 and figures["runs"]["2"]["pids"] == 2
    assert "digest" in figures and figures["memory_mb"]["max_worker"] > 0


def test_logs_are_files_folders_globs_and_urls(tmp_path: Path) -> None:
    from respecd.errors import InputError
    from respecd.lab.fleet.logs import expand, local_copy

    for name in ("a/x.mcap", "b/x.mcap", "b/y.mcap", "b/notes.txt"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(b"log")
    refs = expand([str(tmp_path / "b"), str(tmp_path / "a" / "*.mcap"), str(tmp_path / "b" / "y.mcap")])
    assert [r.name for r in refs] == ["a/x.mcap", "b/x.mcap", "y.mcap"]  # each once, names unique
    with pytest.raises(InputError, match="no such file"):
        expand([str(tmp_path / "missing.mcap")])
    fsspec = pytest.importorskip("fsspec")
    with fsspec.open("memory://fleet/r9.mcap", "wb") as f:
        f.write(b"remote bytes")
    (remote,) = expand(["memory://fleet/"])
    assert remote.name == "r9.mcap" and remote.remote
    with local_copy(remote) as path:
        assert path.read_bytes() == b"remote bytes"
    assert not path.exists()


def test_address_without_ray_installed_is_exit_2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cli) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # as on a machine without the fleet extra
    log = tmp_path / "r.mcap"
    log.write_bytes(b"not read: Ray is missing first")
    ran = cli("fleet", "eval", str(log), "--address", "local", "--out", str(tmp_path / "out"))
    assert ran.returncode == 2 and "Ray is not installed (pip install 'respecd[fleet]')" in ran.stderr, ran.stderr
