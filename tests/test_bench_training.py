"""`respecd bench training` runs end to end and reports the documented keys (no timing asserts)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import structlog

from respecd.cli import main


@pytest.fixture(autouse=True)
def _unbind_structlog():  # type: ignore[no-untyped-def]
    """The bench command binds structlog to this test's captured stdout; unbind it afterwards."""
    yield
    structlog.reset_defaults()


@pytest.mark.slow
def test_bench_training_times_both_precisions_on_the_same_batches(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "training.json"
    assert main(["bench", "training", "--steps", "1", "--warmup", "0", "--threads", "1", "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert set(figures["step_ms"]) == {"fp32", "bf16"} and min(figures["step_ms"].values()) > 0
    assert figures["render_ms"] > 0 and figures["steps"] == 1 and figures["threads"] == 1
    assert figures["bf16_over_fp32"] == pytest.approx(figures["step_ms"]["bf16"] / figures["step_ms"]["fp32"],
                                                      abs=1e-3)
    assert figures["bf16_cpu"] in (True, False, None)
    assert "training step (1 threads" in capsys.readouterr().out


def test_bench_training_rejects_a_step_count_below_one(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "training", "--steps", "0"]) == 2
    assert "expected steps >= 1" in capsys.readouterr().err
