"""``respecd radar-profile`` and ``respecd radar-dump``: output, exit status, messages."""

from __future__ import annotations

import argparse
import importlib
import json
import random
import sys
from pathlib import Path

import pytest

from respecd.cli import COMMANDS
from respecd.errors import ConfigError, InputError
from respecd.radar.cfg import parse_lines
from respecd.radar.tlv import MAGIC

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
SDK33 = REAL / "ti_iwr6843_oob_automated_doors" / "xwr68xx_processed_stream_2019_12_04T21_44_51_663.dat"
SDK36 = REAL / "ti_awr1642_oob_piatek" / "AWR1642_test_data_SDK_3_6_0.dat"
PPLCOUNT = REAL / "ti_iwr6843aop_pplcount_niek" / "data.bin"


def main(argv: list[str]) -> int:
    """The registered subcommand, run as ``respecd.cli.main`` runs it (bad input: one line, exit 2).

    Only this command's module is imported, so the test does not depend on every other
    subcommand importing cleanly.
    """
    module = importlib.import_module(COMMANDS[argv[0]][0])
    parser = argparse.ArgumentParser(prog=f"respecd {argv[0]}")
    module.add_arguments(parser)
    try:
        return int(module.main(parser.parse_args(argv[1:])) or 0)
    except (ConfigError, InputError) as err:
        print(f"respecd: {err}", file=sys.stderr)
        return 2


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"shared capture {path} absent (CI clones shared/ beside the repo)")
    return path


def test_radar_profile_prints_a_cfg_with_its_figures(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["radar-profile", "--prefer", "range", "--fps", "10"]) == 0
    out = capsys.readouterr().out
    assert "% Range Resolution(m): 0.0732" in out and "% Maximum unambiguous Range(m): 14.99" in out
    assert "firmware xwr68xx_mmw_demo" in out
    lines = parse_lines(out)
    assert lines[0] == "sensorStop" and lines[-1] == "sensorStart"
    assert "profileCfg 0 60 10 7 28.49 0 0 100 1 256 12499 0 0 30" in lines and "bpmCfg -1 0 0 1" in lines
    assert "cfarFovCfg -1 0 0 14.99" in lines
    assert main(["radar-profile", "--board", "aop"]) == 0
    assert "bpmCfg" not in capsys.readouterr().out  # the AOP image is HWA-only


def test_radar_profile_json_table_and_limits(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["radar-profile", "--prefer", "velocity", "--fps", "30", "--json"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["loops"] == 32 and figures["problems"] == [] and figures["firmware"] == "xwr68xx_mmw_demo"
    assert figures["uart_bytes_per_frame"] == 2144 and figures["max_points"] == 100
    uart_ms = figures["uart_bytes_per_frame"] * 10 / 921600 * 1000
    assert uart_ms <= figures["frame_period_ms"] - figures["active_frame_ms"]
    assert main(["radar-profile", "--fps", "30", "--max-points", "200"]) == 1
    assert "frame timeline" in capsys.readouterr().err
    assert main(["radar-profile", "--table"]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 1 + 60
    assert main(["radar-profile", "--fps", "45"]) == 2
    assert "--fps 45: expected a frame rate from 1 to 30 Hz" in capsys.readouterr().err


def test_radar_dump_json_lines_and_summary(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["radar-dump", str(_need(SDK33)), "--json"]) == 0
    captured = capsys.readouterr()
    records = [json.loads(line) for line in captured.out.splitlines()]
    assert [r["frame"] for r in records] == list(range(209, 310))
    assert {r["version"] for r in records} == {"3.3.0.2"}
    assert all(isinstance(r["points"], int) and r["tlvs"][0] == 1 for r in records)
    assert "101 frames" in captured.err and "0 bytes skipped" in captured.err and "0 gaps" in captured.err


def test_radar_dump_text_reports_skips_and_gaps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = _need(SDK36).read_bytes()
    starts = [i for i in range(len(data)) if data.startswith(MAGIC, i)]
    cut = data[:starts[10]] + data[starts[12]:]  # frames 79 and 80 lost
    capture = tmp_path / "cut.dat"
    capture.write_bytes(cut)
    assert main(["radar-dump", str(capture)]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert len(lines) == 98 and "GAP 2 missing before the previous frame" in lines[11]  # frame 82 confirms 81
    assert "376 bytes skipped" in captured.err and "1 gaps (2 frames missing)" in captured.err


def test_radar_dump_flags_the_people_counting_format(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["radar-dump", str(_need(PPLCOUNT))]) == 0
    captured = capsys.readouterr()
    assert "3473 people-counting frames" in captured.err and "0 frames" in captured.err
    assert "not the out-of-box format" in captured.out.splitlines()[0]


def test_radar_dump_bad_input_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["radar-dump", str(tmp_path / "missing.dat")]) == 2
    assert "missing.dat: no such capture file" in capsys.readouterr().err
    noise = tmp_path / "noise.bin"
    noise.write_bytes(random.Random(3).randbytes(5000))
    assert main(["radar-dump", str(noise)]) == 2
    assert "no TI mmWave data-port frames in 5000 bytes" in capsys.readouterr().err
    assert main(["radar-dump", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err


def test_radar_dump_stops_on_an_endless_stream_without_frames(capsys: pytest.CaptureFixture[str]) -> None:
    # /dev/zero by mistake was read forever; a real capture shows a frame long before 16 MiB
    assert main(["radar-dump", "/dev/zero"]) == 2
    assert "no TI mmWave data-port frames in its first 16777216 bytes" in capsys.readouterr().err


def test_bench_drivers_parses_every_real_frame_whole_and_chunked() -> None:
    from respecd.lab.bench import BENCHES

    bench = importlib.import_module(BENCHES["drivers"])
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(["--data", str(_need(SDK33).parents[1]), "--repeat", "1", "--rounds", "1", "--chunk", "7"])
    figures = bench.SECTIONS["radar_parser"](args)  # only the radar section: the others have their own tests
    assert figures["whole_frames_per_round"] == figures["chunked_frames_per_round"] == 99 + 100 + 101
    assert figures["captures"] == 3 and figures["uart_budget_b_per_s"] == 92160
    assert figures["whole_x_uart_budget"] > 0 and figures["chunked_mb_per_cpu_s"] > 0
    with pytest.raises(InputError, match="cannot read radar capture"):
        bench.SECTIONS["radar_parser"](parser.parse_args(["--data", "/nonexistent", "--repeat", "1", "--rounds", "1"]))
