"""`respecd bench controller` runs end to end and reports the documented keys (no timing asserts)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import structlog

from respecd.cli import main

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _unbind_structlog():  # type: ignore[no-untyped-def]
    """The bench command binds structlog to this test's captured stdout; unbind it afterwards."""
    yield
    structlog.reset_defaults()


def test_bench_controller_writes_the_documented_keys(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "controller.json"
    assert main(["bench", "controller", "--steps", "300", "--percepts", "20", "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    for key in ("step_us_p50", "step_us_p99", "state_us_p50", "features_us_p50", "probe_us_p50"):
        assert figures[key] > 0
    # sim-rover ties thermal and radar to RGB's rate: 15 × 2 × 2 × 5 configurations, 15 + 2 + 2 + 5 columns
    assert figures["steps"] == 300 and figures["actions"] == 300 and figures["table_columns"] == 24
    assert figures["states"] == 3645
    assert "step_us_p50:" in capsys.readouterr().out


def test_bench_controller_product_space_too_large_is_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    own_rates = str(REPO / "respecd" / "lab" / "profiles" / "sim-rover-per-sensor.yaml")  # 4500 configurations
    assert main(["bench", "controller", "--steps", "10", "--mode", "product", "--profile", own_rates]) == 2
    assert "max_actions=4096" in capsys.readouterr().err
