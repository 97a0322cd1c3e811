"""Chirp table, FMCW figures, TI limit checks and cfg text."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from respecd.errors import ConfigError, InputError
from respecd.radar import cfg
from respecd.radar.chirp import (
    LOOP_STEPS,
    MAX_CUBE_BYTES,
    PROCESSING_MS,
    RATES_HZ,
    UART_OVERHEAD,
    ChirpProfile,
    build_table,
    lookup,
    max_rate_hz,
)

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"

# TI mmWave Demo Visualizer 3.6 xWR68xx presets at 10 fps, 3 TX (Homerlars/Slim-IWR6843-Parser
# radar_config/, SENSORS.md §2.4): the renderer's reference, no longer rows of the table
BEST_RANGE = ChirpProfile("range", 10.0, 60.0, 388.0, 7.0, 28.49, 30.0, 256, 12499, 16)
BEST_VELOCITY = ChirpProfile("velocity", 10.0, 60.0, 115.0, 7.0, 15.0, 100.0, 64, 9142, 128)
VISUALIZER_RANGE = [
    "profileCfg 0 60 388 7 28.49 0 0 30 1 256 12499 0 0 158", "chirpCfg 0 0 0 0 0 0 0 1", "chirpCfg 1 1 0 0 0 0 0 2",
    "chirpCfg 2 2 0 0 0 0 0 4", "frameCfg 0 2 16 0 100 1 0", "CQRxSatMonitor 0 3 4 63 0", "CQSigImgMonitor 0 127 4",
    "cfarFovCfg -1 0 0 49.99", "channelCfg 15 7 0", "compRangeBiasAndRxChanPhase 0.0" + " 1 0 -1 0" * 6,
]
VISUALIZER_VELOCITY = [
    "profileCfg 0 60 115 7 15 0 0 100 1 64 9142 0 0 158", "frameCfg 0 2 128 0 100 1 0",
    "CQRxSatMonitor 0 3 4 19 0", "CQSigImgMonitor 0 31 4", "cfarFovCfg -1 0 0 10.97", "cfarFovCfg -1 1 -3.20 3.20",
    "cfarCfg -1 1 0 8 4 4 1 15 1",
]


def _figures(profile: ChirpProfile) -> tuple[float, float, float, float]:
    return (profile.range_resolution_m, profile.max_range_m, profile.max_velocity_mps, profile.velocity_resolution_mps)


def test_figures_follow_ti_conventions_on_the_visualizer_presets() -> None:
    # max range by TI's 0.8 Fs convention is exactly the presets' own cfarFovCfg limit (49.99, 10.97)
    assert _figures(BEST_RANGE) == pytest.approx((0.244, 49.99, 1.00, 0.125), rel=2e-3)
    assert _figures(BEST_VELOCITY) == pytest.approx((0.214, 10.97, 3.20, 0.050), rel=3e-3)


def test_figures_match_real_visualizer_cfg_headers() -> None:
    # the visualizer's 30-fps preset states range res 0.434 m, vmax 15.14 m/s
    lines = ["channelCfg 15 7 0", "profileCfg 0 60 8 7 19.52 0 0 30 1 144 12499 0 0 158",
             "frameCfg 0 2 16 0 33.333 1 0"]
    fast = cfg.profile_from_lines(lines)
    assert fast.range_resolution_m == pytest.approx(0.434, abs=1e-3)
    assert fast.max_velocity_mps == pytest.approx(15.14, abs=1e-2) and fast.rate_hz == pytest.approx(30, abs=1e-3)
    path = REAL / "ti_awr1642_oob_piatek" / "AWR1642-SDK_3_6_0.cfg"
    if not path.exists():
        pytest.skip(f"{path} absent")
    # header: Range Resolution 0.044, Maximum Radial Velocity 1, Radial velocity resolution 0.13, 100 ms
    real = cfg.profile_from_lines(cfg.read_cfg(path))
    assert real.num_tx == 2 and real.rate_hz == 10
    assert (real.range_resolution_m, real.max_velocity_mps, real.velocity_resolution_mps) == pytest.approx(
        (0.044, 1.0, 0.13), abs=6e-3)


def _cfar_range(lines: list[str]) -> float:
    return float(next(line for line in lines if line.startswith("cfarFovCfg -1 0 ")).split()[-1])


def test_every_row_does_what_its_mode_says_within_its_limits() -> None:
    for num_tx in (2, 3):
        table = build_table(num_tx)
        assert len(table) == 2 * len(RATES_HZ)
        open_only = set()
        for (preference, rate), profile in table.items():
            assert profile.preference == preference and profile.rate_hz == rate
            assert profile.problems() == [], (preference, rate)
            idle = profile.frame_period_ms - profile.active_frame_ms
            assert profile.uart_ms * UART_OVERHEAD + PROCESSING_MS <= idle  # the blocking UART write fits
            assert profile.loops in LOOP_STEPS and profile.cube_bytes <= MAX_CUBE_BYTES
            lines = cfg.render(profile, board="isk")
            assert profile.max_range_m <= _cfar_range(lines)  # within the cfg's own range limit
            open_only.add(tuple(line for line in lines if line.split()[0] in cfg.OPEN_ONLY))
        assert len(open_only) == 1  # channelCfg, adcCfg, lowPower never change at runtime
        for rate in RATES_HZ:
            range_row, velocity_row = table[("range", rate)], table[("velocity", rate)]
            assert range_row.range_resolution_m < velocity_row.range_resolution_m / 3
            assert velocity_row.velocity_resolution_mps < range_row.velocity_resolution_mps
            assert range_row.max_range_m == velocity_row.max_range_m  # the modes trade resolution, not coverage


def test_velocity_rows_spend_the_time_each_rate_leaves() -> None:
    rows = [lookup("velocity", rate) for rate in RATES_HZ]
    resolutions = [p.velocity_resolution_mps for p in rows]
    assert resolutions == sorted(resolutions)  # a faster frame rate never buys finer velocity resolution
    assert len({p.chirp_us for p in rows}) >= 15  # the chirp follows the rate
    for p in rows:
        capped = p.max_velocity_mps < 2.01 and p.loops == LOOP_STEPS[0]  # +-2 m/s floor at 128 loops
        assert capped or p.active_frame_ms >= 0.97 * p.chirp_budget_ms, p.rate_hz
    assert lookup("velocity", 30).loops < lookup("velocity", 10).loops
    assert lookup("range", 30).loops < lookup("range", 10).loops  # range rows keep their sweep; loops follow the rate


def test_problems_catch_each_limit() -> None:
    assert any("frame timeline" in p for p in lookup("range", 30, max_points=200).problems())
    assert max_rate_hz("range", max_points=200) < 30 and max_rate_hz("range") == 30
    too_long = dataclasses.replace(lookup("range", 30), loops=256)
    assert any("frame timeline" in p for p in too_long.problems())
    assert any("radar cube" in p for p in too_long.problems())
    off_band = dataclasses.replace(BEST_VELOCITY, ramp_end_us=50.0)
    assert any("band" in p for p in off_band.problems())
    short_ramp = dataclasses.replace(BEST_RANGE, ramp_end_us=20.0)
    assert any("ADC sampling" in p for p in short_ramp.problems())
    fast_adc = dataclasses.replace(BEST_RANGE, sample_rate_ksps=20_000, idle_us=5.0)
    assert any("ksps" in p for p in fast_adc.problems()) and any("idle" in p for p in fast_adc.problems())


def test_lookup_picks_the_nearest_tabulated_rate() -> None:
    assert lookup("range", 12.4).rate_hz == 12 and lookup("velocity", 0.2).rate_hz == 1


def test_render_reproduces_the_visualizer_presets() -> None:
    for preset, expected in ((BEST_RANGE, VISUALIZER_RANGE), (BEST_VELOCITY, VISUALIZER_VELOCITY)):
        lines = cfg.render(dataclasses.replace(preset, range_profile=True), board="aop")
        assert lines[:2] == ["sensorStop", "flushCfg"] and lines[-1] == "sensorStart"
        for line in expected:
            assert line in lines, line
        assert "guiMonitor -1 1 1 0 0 0 1" in lines
        assert not any(line.startswith("bpmCfg") for line in lines)  # the AOP demo is HWA-only


def test_bpm_cfg_follows_the_firmware() -> None:
    isk = cfg.render(lookup("range", 10), board="isk")
    assert "bpmCfg -1 0 0 1" in isk and isk.index("bpmCfg -1 0 0 1") == isk.index("lvdsStreamCfg -1 0 0 0") - 1
    hwa = cfg.render(lookup("range", 10), board="isk", firmware="xwr64xx_mmw_demo")
    assert not any(line.startswith("bpmCfg") for line in hwa)
    base = [line for line in isk if not line.startswith("bpmCfg")]  # a user cfg without it
    assert "bpmCfg -1 0 0 1" in cfg.render(lookup("velocity", 20), board="isk", base=base)
    assert not any(line.startswith("bpmCfg") for line in cfg.render(lookup("range", 5), "aop", base=isk))


def test_render_for_isk_two_tx_and_without_range_profile() -> None:
    lines = cfg.render(lookup("range", 10, num_tx=2), board="isk")
    assert "channelCfg 15 5 0" in lines and "guiMonitor -1 1 0 0 0 0 1" in lines
    assert [line for line in lines if line.startswith("chirpCfg")] == ["chirpCfg 0 0 0 0 0 0 0 1",
                                                                      "chirpCfg 1 1 0 0 0 0 0 4"]
    assert any(line.startswith("frameCfg 0 1 ") for line in lines)
    with pytest.raises(ConfigError, match="aop"):
        cfg.render(lookup("range", 10, num_tx=2), board="aop")


def test_render_keeps_a_user_base_cfg_and_replaces_only_the_chirp() -> None:
    path = REAL / "ti_iwr6843_oob_automated_doors" / "profile_3d_automated_doors_ISK.cfg"
    if not path.exists():
        pytest.skip(f"{path} absent")
    base = cfg.read_cfg(path)
    row = lookup("velocity", 20)
    lines = cfg.render(row, board="isk", base=base)
    assert lines[:2] == ["sensorStop", "flushCfg"] and lines[-1] == "sensorStart"
    assert lines.count("sensorStart") == 1 and lines.count("sensorStop") == 1
    profile_lines = [line for line in lines if line.startswith("profileCfg")]
    assert profile_lines == [f"profileCfg 0 60 {row.idle_us:g} 7 13.13 0 0 100 1 64 12499 0 0 30"]
    assert "cfarCfg -1 0 2 8 4 3 0 20 0" in lines and "clutterRemoval -1 1" in lines  # the user's choices stay
    assert "gatingParam 4 2 2 2 10" in lines  # commands we do not know are kept in place
    assert lines.count("bpmCfg -1 0 0 1") == 1  # the lab cfg's own, kept
    assert lines.index(profile_lines[0]) < lines.index("frameCfg 0 2 128 0 50 1 0")


def test_read_cfg_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such cfg file"):
        cfg.read_cfg(tmp_path / "missing.cfg")
    partial = tmp_path / "partial.cfg"
    partial.write_text("% only comments\nsensorStop\nguiMonitor -1 1 0 0 0 0 1\n")
    with pytest.raises(InputError, match="partial.cfg: cfg lacks channelCfg, profileCfg, chirpCfg, frameCfg"):
        cfg.read_cfg(partial)
    with pytest.raises(InputError, match="/dev/zero: more than 262144 bytes, expected a cfg file"):
        cfg.read_cfg("/dev/zero")  # read whole, it was a MemoryError


def test_uart_model_matches_the_radars_own_transmit_time() -> None:
    """The stats TLV of frame k+1 times the UART send of frame k: 8N1 at 921600 baud, +3-4 %."""
    from respecd.radar.chirp import UART_BYTES_PER_S
    from respecd.radar.parser import MmwParser

    names = ("ti_awr1642_oob_piatek/AWR1642_test_data_SDK_3_6_0.dat",
             "ti_iwr6843_oob_automated_doors/xwr68xx_processed_stream_2019_12_04T21_44_51_663.dat")
    for name in names:
        if not (REAL / name).exists():
            pytest.skip(f"{REAL / name} absent")
        packets = MmwParser().feed((REAL / name).read_bytes())
        ratios = [after.stats["transmit_output_time_us"] * 1e-6 / (len(before.raw) / UART_BYTES_PER_S)
                  for before, after in zip(packets, packets[1:], strict=False)]
        assert len(ratios) >= 99 and all(1.0 <= r <= 1.06 for r in ratios), name
