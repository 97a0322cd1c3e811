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


@pytest.mark.slow
def test_platform_tables_name_their_source_and_the_orin_table_is_rederived_from_it(tmp_path) -> None:
    import json

    import pytest

    from respecd.config import load_profile
    from respecd.errors import InputError
    from respecd.lab.experiment import platforms
    from respecd.lab.experiment.rollout import controller_for
    from respecd.lab.experiment.setup import rgb_resolutions

    resolutions = rgb_resolutions(controller_for(load_profile("builtin:sim-rover"), "static"))
    orin, cpu = (platforms.resolve(name, resolutions) for name in ("orin-nano", "cpu"))
    assert orin.label() == "orin-nano (orin-nano.json), estimate" and cpu.label() == "cpu (cpu.json)"
    assert orin.accelerator_w == platforms.ORIN_BOARD_W and cpu.accelerator_w == 3.5
    shipped = json.loads(platforms.table_path("orin-nano").read_text())
    derived = platforms.derive_orin()
    assert derived["latency_ms"] == shipped["latency_ms"]  # the shipped table is what its recipe gives
    assert derived["gflops"]["640x360"] == pytest.approx(3.06, abs=0.01)  # the figure for the net
    assert derived["gflops"]["1280x720"] == pytest.approx(11.7, abs=0.05)
    small, large = orin.latency[min(resolutions)], orin.latency[max(resolutions)]
    (_, g0, ms0), (_, g1, ms1) = platforms.ORIN_PUBLISHED
    assert ms0 - (g0 - 3.06) * (ms1 - ms0) / (g1 - g0) == pytest.approx(1000 * small.forward_s, abs=0.01)
    assert 1000 * large.forward_s < ms0 + 2 and large.forward_s > small.forward_s
    for lat_cpu, lat_orin in ((cpu.latency[r], orin.latency[r]) for r in resolutions):  # the CPU's multiple
        assert lat_orin.attribution_s / lat_orin.forward_s == pytest.approx(
            lat_cpu.attribution_s / lat_cpu.forward_s, rel=1e-3)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**shipped, "accelerator_w": "lots"}))
    with pytest.raises(InputError, match="accelerator_w: expected watts"):
        platforms.resolve(bad, resolutions)
