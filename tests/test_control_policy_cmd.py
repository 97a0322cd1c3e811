"""`respecd policy show FILE`: the learned policy as a table; bad files exit 2 in one line."""

from __future__ import annotations

from pathlib import Path

import pytest

from respecd.cli import main
from respecd.config import load_profile
from respecd.control.controller import Controller
from respecd.control.persist import save_table
from respecd.control.state import Observation


def _learned_table(path: Path) -> Controller:
    profile = load_profile("builtin:sim-rover")
    moves = profile.controller.actions.model_copy(update={"mode": "moves", "shared_rate": ()})  # each its own rate
    controller = Controller.from_profile(profile.controller.model_copy(update={"min_dwell_s": 0.0, "actions": moves}),
                                         profile)
    for step in range(60):
        dark = step % 20 < 10
        controller.step(Observation(t=float(step), n_percepts=10, illumination=0.05 if dark else 0.6,
                                    conf_agg=0.7, latency_s=0.05))
    save_table(path, controller.table, controller.layout(), {"profile": profile.name})
    return controller


def test_policy_show_prints_visited_states(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "qtable-sim-rover.npz"
    controller = _learned_table(path)
    assert main(["policy", "show", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("Q-table sim-rover: 3645 states x 15 actions, 59 updates")
    assert lines[1].startswith("states visited: 2 of 3645 (0.1 %)")
    assert lines[2].split() == ["illumination", "motion", "radar_density", "load", "sync", "confidence",
                                "dominant", "best", "action", "Q", "visits", "tried"]
    rows = lines[3:]
    assert len(rows) == 2 and {r.split()[0] for r in rows} == {"dark", "bright"}
    dark = next(r for r in rows if r.startswith("dark"))
    state = controller.states.index(controller.states.from_names({
        "illumination": "dark", "motion": "still", "radar_density": "sparse", "load": "low",
        "sync": "good", "confidence": "high", "dominant": "none"}))
    best = controller.table.greedy_tried(state)
    assert controller.space.describe(best) in dark and f"{controller.table.q[state, best]:.3f}" in dark


def test_policy_show_limit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "q.npz"
    _learned_table(path)
    assert main(["policy", "show", str(path), "--limit", "1", "--sort", "q"]) == 0
    out = capsys.readouterr().out
    assert "(1 of 2 visited states shown, sorted by q; --limit 0 shows all)" in out


@pytest.mark.parametrize(("content", "message"), [(None, "no such file"),
                                                  (b"junk", "not a respecd Q-table: it looks like text")])
def test_policy_show_bad_file_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes | None, message: str
) -> None:
    path = tmp_path / "q.npz"
    if content is not None:
        path.write_bytes(content)
    assert main(["policy", "show", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and message in err[0]


def test_policy_show_factored_table_names_a_cell_per_sensor(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    profile = load_profile("builtin:sim-rover")
    config = profile.controller.model_copy(update={
        "min_dwell_s": 0.0, "actions": profile.controller.actions.model_copy(update={"mode": "factored",
                                                                                     "shared_rate": ()})})
    controller = Controller.from_profile(config, profile)
    for step in range(30):  # a low ConfAgg keeps every target below the optimistic 1.0: each cell gets tried
        controller.step(Observation(t=float(step), n_percepts=10, illumination=0.6, conf_agg=0.1, latency_s=0.05))
    path = tmp_path / "q.npz"
    save_table(path, controller.table, controller.layout(), {"profile": profile.name})
    assert main(["policy", "show", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("Q-table sim-rover: 3645 states x 40 actions, 29 updates")
    (row,) = lines[3:]
    assert row.split()[-2:] == ["29", "40/40"]  # 29 updates (each touched all four sensor blocks), all cells tried
    state = controller.states.index(controller.states.from_names({
        "illumination": "bright", "motion": "still", "radar_density": "sparse", "load": "low",
        "sync": "good", "confidence": "low", "dominant": "none"}))
    best = controller.space.describe(controller.table.greedy_tried(state))
    assert best.startswith("rgb ") and " depth " in best and best in row


def test_policy_show_names_the_sensors_that_share_a_rate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    profile = load_profile("builtin:sim-rover")
    actions = profile.controller.actions.model_copy(update={"mode": "factored", "shared_rate": ("rgb", "radar")})
    controller = Controller.from_profile(profile.controller.model_copy(update={"min_dwell_s": 0.0,
                                                                               "actions": actions}), profile)
    for step in range(30):
        controller.step(Observation(t=float(step), n_percepts=10, illumination=0.6, conf_agg=0.1, latency_s=0.05))
    path = tmp_path / "q.npz"
    save_table(path, controller.table, controller.layout(), {"profile": profile.name})
    assert main(["policy", "show", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("Q-table sim-rover: 3645 states x 32 actions")  # radar: 2 modes, no rate of its own
    assert lines[2] == "shared rate: radar at rgb's rate"
    assert " radar range " in lines[-1] or " radar velocity " in lines[-1]
