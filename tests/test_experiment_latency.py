"""The detector latency the compute figures rest on: wall time, or CPU time on a busy machine."""

from __future__ import annotations

import time

import pytest

from respecd.lab.experiment import latency as lat


class WaitingDetector:
    """Waits 20 ms per call (a detector that is off the CPU, as one that waits for a core is)
    and burns a little CPU when asked to attribute."""

    def __init__(self) -> None:
        self.calls = 0

    def infer(self, frames: dict, attribute: bool) -> None:
        self.calls += 1
        time.sleep(0.02)
        if attribute:
            end = time.process_time() + 0.01
            while time.process_time() < end:
                pass


def test_wall_clock_counts_the_wait_and_cpu_clock_does_not() -> None:
    detector = WaitingDetector()
    wall = lat.measure(detector, lambda res: {}, [(640, 360)], 3, lat.CLOCKS["wall"])[(640, 360)]
    cpu = lat.measure(detector, lambda res: {}, [(640, 360)], 3, lat.CLOCKS["cpu"])[(640, 360)]
    assert detector.calls == 2 * 2 * (1 + 3)  # two clocks x (plain, attributed) x (warm-up + repeats)
    assert wall.forward_s >= 0.02 and cpu.forward_s < 0.01
    assert cpu.attribution_s >= 0.009  # the CPU the attributed call spent is counted


@pytest.mark.slow
def test_reference_file_is_what_train_policy_and_bench_read(tmp_path) -> None:
    import json

    from respecd.cli import main as cli_main
    from respecd.config import load_profile
    from respecd.lab.experiment.rollout import controller_for
    from respecd.lab.experiment.setup import rgb_resolutions

    out = tmp_path / "latency.json"
    assert cli_main(["experiment", "latency", str(out), "--repeats", "1"]) == 0
    doc = json.loads(out.read_text())
    assert doc["clock"] == "cpu" and doc["repeats"] == 1 and len(doc["detector_fingerprint"]) == 16
    resolutions = rgb_resolutions(controller_for(load_profile("builtin:sim-rover"), "static"))
    table = lat.load(out, resolutions)
    assert set(table) == set(resolutions)
    small, large = table[min(resolutions)], table[max(resolutions)]
    assert large.forward_s > small.forward_s  # more pixels, more work: a real measurement
