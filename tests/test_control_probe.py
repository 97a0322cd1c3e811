"""System probe: CPU share from /proc/stat, Jetson GPU load and INA3221 rails by discovery.

The Jetson trees are laid out as L4T exposes them (SENSORS.md §6.1), built under tmp_path.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from respecd.control.probe import SystemProbe, SystemSample


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def _orin(root: Path) -> None:
    """JetPack 6 Orin Nano: devfreq entry linked to the GPU device, INA3221 under hwmon."""
    gpu = root / "sys/devices/platform/17000000.gpu"
    _write(gpu / "load", "437\n")  # per-mille
    _write(gpu / "of_node/name", "ga10b\x00")
    entry = root / "sys/class/devfreq/17000000.gpu"
    entry.mkdir(parents=True)
    (entry / "device").symlink_to(gpu)
    other = root / "sys/class/devfreq/15340000.vic"
    _write(other / "device/of_node/name", "vic\x00")
    hwmon = root / "sys/bus/i2c/drivers/ina3221/1-0040/hwmon/hwmon3"
    rails = ((1, "VDD_IN", 5072, 1420), (2, "VDD_CPU_GPU_CV", 5064, 380), (3, "VDD_SOC", 5070, 300))
    for channel, label, mv, ma in rails:
        _write(hwmon / f"in{channel}_label", f"{label}\n")
        _write(hwmon / f"in{channel}_input", f"{mv}\n")
        _write(hwmon / f"curr{channel}_input", f"{ma}\n")


def test_orin_gpu_load_and_module_power(tmp_path: Path) -> None:
    _orin(tmp_path)
    _write(tmp_path / "proc/stat", "cpu  100 0 100 800 0 0 0 0 0 0\n")
    probe = SystemProbe(tmp_path)
    first = probe.read()
    assert first.cpu is None  # needs two readings
    assert first.gpu == pytest.approx(0.437)
    assert first.power_w == pytest.approx(5.072 * 1.420)
    _write(tmp_path / "proc/stat", "cpu  250 0 150 900 0 0 0 0 0 0\n")
    assert probe.read().cpu == pytest.approx(200 / 300)


def test_old_l4t_rail_in_milliwatts_and_legacy_gpu(tmp_path: Path) -> None:
    _write(tmp_path / "sys/bus/i2c/drivers/ina3221x/6-0040/iio:device0/in_power0_input", "3560\n")
    _write(tmp_path / "sys/devices/gpu.0/load", "120\n")
    probe = SystemProbe(tmp_path)
    sample = probe.read()
    assert sample.power_w == pytest.approx(3.56)
    assert sample.gpu == pytest.approx(0.12)


def test_power_rails_off_and_plain_pc(tmp_path: Path) -> None:
    _orin(tmp_path)
    assert SystemProbe(tmp_path, power_rails=False).read().power_w is None
    bare = SystemProbe(tmp_path / "nothing")
    assert bare.read() == SystemSample(None, None, None)


def test_this_machine_proc_stat() -> None:
    probe = SystemProbe()
    probe.read()
    sum(range(200_000))  # burn a little CPU between readings
    cpu = probe.read().cpu
    assert cpu is None or 0.0 <= cpu <= 1.0
