"""``respecd bench soak``: the RSS slope it reports is a least-squares fit after warm-up."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import structlog
import yaml

from respecd.cli import main
from respecd.lab.bench.soak import rss_slope

REPO = Path(__file__).resolve().parents[1]


def _rows(slope_mb_per_h: float, warmup_jump_mb: float) -> list[dict]:
    rng = np.random.default_rng(1)
    rows = []
    for t in range(0, 3600, 10):
        rss = 1000 + slope_mb_per_h * t / 3600 + rng.normal(0, 2)
        if t < 600:  # warm-up: the allocator and caches fill in
            rss -= warmup_jump_mb * (1 - t / 600)
        rows.append({"t_s": float(t), "rss_mb": rss})
    return rows


def test_slope_after_warmup_ignores_the_warmup_climb() -> None:
    fit = rss_slope(_rows(3.0, 80.0), warmup_s=600)
    assert abs(fit["slope_mb_per_h"] - 3.0) < 3 * fit["slope_stderr_mb_per_h"] + 0.5
    assert rss_slope(_rows(3.0, 80.0), warmup_s=0)["slope_mb_per_h"] > 30  # with warm-up it looks like a leak
    assert fit["samples"] == 300 and fit["median_last_2min_mb"] > fit["median_first_2min_mb"]


@pytest.mark.slow
def test_a_short_soak_writes_its_samples(tmp_path: Path) -> None:
    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["perception"] = {"enabled": False}
    config = tmp_path / "p.yaml"
    config.write_text(yaml.safe_dump(profile))
    out = tmp_path / "soak.json"
    assert main(["bench", "soak", "--minutes", "0.05", "--every", "0.5", "--config", str(config),
                 "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert len(figures["samples"]) >= 4 and figures["rss"]["slope_mb_per_h"] is not None
    assert figures["threads_after_warmup"]["min"] >= 2 and figures["fds_after_warmup"]["max"] > 0
    assert set(figures["queue_depth_max"]) >= {"rgb", "bundles", "percepts"}
    assert all(depth <= 8 for depth in figures["queue_depth_max"].values())  # bounded by the queue sizes
    heap = figures["heap_mb_after_warmup"]  # glibc here: in use and free-but-held are both read
    assert heap["in_use"]["median_last_2min"] > 0 and heap["free_held"]["median_last_2min"] >= 0
    structlog.reset_defaults()
