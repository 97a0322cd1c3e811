"""System signals for the load factor and the power term: CPU from /proc, and on a Jetson
the GPU load (devfreq) and the INA3221 power rails, found by discovery under sysfs.

Paths follow jetson_stats and the L4T docs (see shared SENSORS.md §6.1): a devfreq entry
whose ``device/of_node/name`` is one of the NVIDIA GPU names has a ``load`` file in
per-mille; the INA3221 hwmon directory has ``in{N}_label`` (VDD_IN is the whole module),
``in{N}_input`` in mV and ``curr{N}_input`` in mA. Old L4T exposes ``in_power{N}_input``
in mW under iio. The files are re-read each call (the i2c read can take milliseconds: the
stage calls ``read`` in a worker thread). ``root`` lets tests point at a recorded tree.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import structlog

log = structlog.get_logger(__name__)

GPU_NODE_NAMES = {"gv11b", "gp10b", "ga10b", "gpu"}
TOTAL_RAIL_LABELS = ("VDD_IN", "POM_5V_IN")


@dataclass(frozen=True, slots=True)
class SystemSample:
    cpu: float | None  # busy share of all cores since the last read, 0..1
    gpu: float | None  # GPU load 0..1 (Jetson devfreq)
    power_w: float | None  # board input power from the rails
    busy: float | None = None  # detector busy share of the window, where known better than its samples say


def _read_int(path: Path) -> int | None:
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


class SystemProbe:
    """Discovers what this board exposes once, then reads it cheaply."""

    def __init__(self, root: Path = Path("/"), power_rails: bool = True) -> None:
        self.root = root
        self._cpu_last: tuple[int, int] | None = None
        self.gpu_load_path = self._find_gpu()
        self.rail = self._find_rail() if power_rails else None
        log.info(
            "system_probe",
            gpu=str(self.gpu_load_path) if self.gpu_load_path else None,
            rail=str(self.rail[0]) if self.rail else None,
        )

    def read(self) -> SystemSample:
        return SystemSample(self._cpu(), self._gpu(), self._power())

    # CPU ---------------------------------------------------------------------------------
    def _cpu(self) -> float | None:
        try:
            fields = (self.root / "proc/stat").read_text().splitlines()[0].split()[1:]
        except (OSError, IndexError):
            return None
        ticks = [int(x) for x in fields]
        idle = ticks[3] + (ticks[4] if len(ticks) > 4 else 0)  # idle + iowait
        total = sum(ticks[:8])  # guest time is already inside user/nice
        last, self._cpu_last = self._cpu_last, (idle, total)
        if last is None or total <= last[1]:
            return None
        return 1.0 - (idle - last[0]) / (total - last[1])

    # GPU ---------------------------------------------------------------------------------
    def _find_gpu(self) -> Path | None:
        devfreq = self.root / "sys/class/devfreq"
        if devfreq.is_dir():
            for entry in sorted(devfreq.iterdir()):
                node = entry / "device" / "of_node" / "name"
                try:
                    name = node.read_text().strip("\x00\n ")
                except OSError:
                    continue
                load = (entry / "device").resolve() / "load"
                if name in GPU_NODE_NAMES and load.is_file():
                    return load
        legacy = self.root / "sys/devices/gpu.0/load"  # Nano / TX2
        return legacy if legacy.is_file() else None

    def _gpu(self) -> float | None:
        if self.gpu_load_path is None:
            return None
        value = _read_int(self.gpu_load_path)
        return None if value is None else value / 1000.0  # per-mille -> share

    # power -------------------------------------------------------------------------------
    def _find_rail(self) -> tuple[Path, Path | None] | None:
        """(voltage or power file, current file or None for a direct mW reading)."""
        base = self.root / "sys/bus/i2c/drivers"
        for label in sorted(base.glob("ina3221/*/hwmon/hwmon*/in*_label")):
            try:
                name = label.read_text().strip()
            except OSError:
                continue
            if name in TOTAL_RAIL_LABELS:
                channel = label.name[2:].split("_")[0]
                return label.with_name(f"in{channel}_input"), label.with_name(f"curr{channel}_input")
        for power in sorted(base.glob("ina3221x/*/iio:device*/in_power0_input")):
            return power, None  # old L4T: channel 0 is the module input, already in mW
        return None

    def _power(self) -> float | None:
        if self.rail is None:
            return None
        first, current = self.rail
        value = _read_int(first)
        if value is None:
            return None
        if current is None:
            return value / 1000.0  # mW -> W
        milliamps = _read_int(current)
        return None if milliamps is None else value * milliamps / 1e6  # mV * mA -> W
