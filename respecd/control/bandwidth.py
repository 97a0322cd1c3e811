"""Sensing bandwidth: the bytes per second a configuration makes the sensors produce.

The reward charges it (``reward.bandwidth``, per MB/s) and the benchmark reports it with the
same rule, so what the agent pays for is what the comparison counts. Per frame: raw pixels
as the drivers deliver them (RGB BGR8, 3 B per pixel; thermal 16-bit counts and depth 16-bit
millimetres, 2 B), the radar's TLV packet as the IWR6843 out-of-box demo writes it to the
UART (a fixed part plus 20 B per detected point: TLV 1 x, y, z, Doppler as float32 and TLV 7
SNR and noise), six float32 per IMU sample. Times the frame rate; a disabled sensor costs
nothing. The radar's share depends on the scene (how many points it reports), so the
caller passes the mean point count it saw.
"""

from __future__ import annotations

from collections.abc import Iterable

from respecd.messages import SensorConfig
from respecd.sim.radar_model import FRAME_OVERHEAD_BYTES, POINT_BYTES

BYTES_PER_PIXEL = {"rgb": 3.0, "thermal": 2.0, "depth": 2.0}
IMU_SAMPLE_BYTES = 6 * 4.0  # gyro and accelerometer, three float32 each


def frame_bytes(config: SensorConfig, radar_points: float = 0.0) -> float:
    """Bytes one frame of this sensor puts on its link."""
    if not config.enabled:
        return 0.0
    per_pixel = BYTES_PER_PIXEL.get(config.modality)
    if per_pixel is not None and config.resolution:
        return config.resolution[0] * config.resolution[1] * per_pixel
    if config.modality == "radar":
        return FRAME_OVERHEAD_BYTES + POINT_BYTES * max(radar_points, 0.0)
    if config.modality == "imu":
        return IMU_SAMPLE_BYTES
    return 0.0


def sensor_bandwidth(config: SensorConfig, radar_points: float | None = None) -> float:
    """Bytes per second of one sensor (0 when disabled; radar at ``radar_points`` per frame)."""
    return frame_bytes(config, radar_points or 0.0) * config.rate_hz


def sensing_bandwidth(configs: Iterable[SensorConfig], radar_points: float | None = None) -> float:
    """Bytes per second of every running sensor in ``configs`` (radar at ``radar_points`` per frame)."""
    return sum(sensor_bandwidth(c, radar_points) for c in configs)
