"""``bench pipeline --neighbour N``: the same measurement again beside N spinning processes."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest
from conftest import run_cli

from respecd.lab.bench.neighbour import busy_neighbours, cpu_seconds

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


@linux_only
def test_the_neighbours_burn_cpu_while_held_and_are_gone_after() -> None:
    with busy_neighbours(2) as spinners:
        assert len(spinners) == 2
        time.sleep(1.0)
        burnt = cpu_seconds(spinners)
        assert all(s.poll() is None for s in spinners)
    assert burnt > 0.1  # they spin (2 processes, 1 s; on a loaded machine far less than 2 s)
    assert all(s.returncode is not None for s in spinners)


def test_no_neighbour_means_no_process() -> None:
    with busy_neighbours(0) as spinners:
        assert spinners == []


@linux_only
@pytest.mark.slow
def test_bench_pipeline_reports_both_runs_and_their_ratio(tmp_path: Path) -> None:
    out = tmp_path / "bp.json"
    ran = run_cli("bench", "pipeline", "--seconds", "1", "--neighbour", "1", "--json", str(out))
    assert ran.returncode == 0, ran.stderr
    figures = json.loads(out.read_text())
    loaded = figures["with_neighbour"]
    assert loaded["neighbour_processes"] == 1
    assert loaded["neighbour_cores"] > 0
    assert loaded["bundles"] > 0 and figures["bundles"] > 0
    assert set(figures["neighbour_over_alone"]) == {"sync_jitter_ms_p50", "sync_jitter_ms_p99", "loop_lag_ms_p99"}
    assert "load_average_1min" in loaded and "load_average_1min" in figures


def test_a_negative_neighbour_count_is_refused() -> None:
    ran = run_cli("bench", "pipeline", "--neighbour", "-1")
    assert ran.returncode == 2
    assert "--neighbour" in ran.stderr
