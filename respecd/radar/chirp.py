"""Chirp profiles for the two ReSPEC radar actions, and the figures they imply.

The controller picks a preference (range or velocity) and a frame rate; ``lookup`` returns
the chirp profile for that key. Both start from TI's mmWave Demo Visualizer 3.6 xWR68xx
presets ("best range", "best velocity resolution"; SENSORS.md §2.4). A higher frame rate
leaves less time per frame, so the table first halves the chirp loops (coarser velocity
resolution) and then shortens the idle time (higher max velocity) until the active frame
fits the duty budget: the coupling the paper describes. The four figures come from the
standard FMCW relations; ``problems`` checks TI's limits.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from respecd.messages import RadarMode

C = 3e8  # m/s
UART_BAUD = 921_600
UART_BYTES_PER_S = UART_BAUD / 10  # 8N1: 10 bits on the wire per byte -> 92,160 B/s
BAND_GHZ = (60.0, 64.0)  # IWR6843
DUTY = 0.5  # active chirping may use at most half the frame: the rest is inter-frame processing + UART send
MIN_LOOPS = 16  # smallest Doppler FFT the visualizer offers
MIN_IDLE_US = 8.0  # the visualizer's own 30-fps preset uses 8 us
RATES_HZ = tuple(range(1, 31))  # table keys: every integer rate the controller may ask for
MAX_POINTS = 100  # points per frame assumed for the UART budget check (configurable)


@dataclass(frozen=True)
class ChirpProfile:
    """One row of the lookup table: profileCfg/frameCfg knobs and what they imply."""

    preference: RadarMode
    rate_hz: float
    start_freq_ghz: float
    idle_us: float
    adc_start_us: float
    ramp_end_us: float
    slope_mhz_us: float
    adc_samples: int
    sample_rate_ksps: int
    loops: int
    num_tx: int = 3

    @property
    def frame_period_ms(self) -> float:
        return 1000.0 / self.rate_hz

    @property
    def chirp_us(self) -> float:
        """Tc: one chirp, idle + ramp."""
        return self.idle_us + self.ramp_end_us

    @property
    def active_frame_ms(self) -> float:
        """Chirping time per frame: loops x TX (TDM) x Tc."""
        return self.loops * self.num_tx * self.chirp_us / 1000.0

    @property
    def range_resolution_m(self) -> float:
        """c / (2 B_eff), B_eff = S N / Fs."""
        return C * self.sample_rate_ksps * 1e3 / (2 * self.slope_mhz_us * 1e12 * self.adc_samples)

    @property
    def max_range_m(self) -> float:
        """IF bandwidth 0.9 Fs (complex 1x ADC) mapped to range by the slope."""
        return 300 * 0.9 * self.sample_rate_ksps / (2 * self.slope_mhz_us * 1e3)

    @property
    def cfar_range_m(self) -> float:
        """The range limit TI's visualizer writes to cfarFovCfg (it uses 0.8 Fs)."""
        return 300 * 0.8 * self.sample_rate_ksps / (2 * self.slope_mhz_us * 1e3)

    @property
    def max_velocity_mps(self) -> float:
        """Unambiguous +- radial velocity: lambda / (4 Tc Ntx)."""
        return C / (4 * self.start_freq_ghz * 1e9 * self.chirp_us * 1e-6 * self.num_tx)

    @property
    def velocity_resolution_mps(self) -> float:
        return C / (2 * self.start_freq_ghz * 1e9 * self.chirp_us * 1e-6 * self.loops * self.num_tx)

    @property
    def range_bins(self) -> int:
        return 1 << math.ceil(math.log2(self.adc_samples))

    @property
    def doppler_bins(self) -> int:
        return 1 << math.ceil(math.log2(self.loops))

    def figures(self) -> dict[str, float]:
        """The four radar figures the paper's lookup table yields, plus timing."""
        return {
            "range_resolution_m": round(self.range_resolution_m, 4),
            "max_range_m": round(self.max_range_m, 2),
            "max_velocity_mps": round(self.max_velocity_mps, 3),
            "velocity_resolution_mps": round(self.velocity_resolution_mps, 4),
            "frame_period_ms": round(self.frame_period_ms, 3),
            "active_frame_ms": round(self.active_frame_ms, 3),
        }

    def uart_bytes_per_frame(self, max_points: int = MAX_POINTS, range_profile: bool = False) -> int:
        """Packet size with ``max_points`` points: header, TLVs 1+7 (20 B/pt), 6, 9, padding to 32."""
        size = 40 + (8 + 16 * max_points) + (8 + 4 * max_points) + (8 + 24) + (8 + 28)
        if range_profile:
            size += 8 + 2 * self.range_bins
        return -(-size // 32) * 32

    def problems(self, max_points: int = MAX_POINTS, range_profile: bool = False) -> list[str]:
        """TI limits this profile breaks; empty when it is safe to send."""
        out = []
        if self.active_frame_ms >= self.frame_period_ms:
            out.append(f"active frame {self.active_frame_ms:.2f} ms >= frame period {self.frame_period_ms:.2f} ms")
        sampling_us = self.adc_samples / (self.sample_rate_ksps / 1e3)
        if self.adc_start_us + sampling_us > self.ramp_end_us:
            end = self.adc_start_us + sampling_us
            out.append(f"ADC sampling ends at {end:.2f} us, after the ramp ({self.ramp_end_us} us)")
        top = self.start_freq_ghz + self.slope_mhz_us * self.ramp_end_us / 1000.0
        if self.start_freq_ghz < BAND_GHZ[0] or top > BAND_GHZ[1]:
            out.append(f"sweep {self.start_freq_ghz}-{top:.2f} GHz leaves the {BAND_GHZ[0]:g}-{BAND_GHZ[1]:g} GHz band")
        load = self.uart_bytes_per_frame(max_points, range_profile) * self.rate_hz
        if load > UART_BYTES_PER_S:
            out.append(f"UART needs {load:.0f} B/s at {max_points} points, over {UART_BYTES_PER_S:.0f} B/s")
        return out


# TI mmWave Demo Visualizer 3.6 presets for xWR68xx at 10 fps, 3 TX (SENSORS.md §2.4)
TEMPLATES: dict[RadarMode, ChirpProfile] = {
    "range": ChirpProfile("range", 10.0, 60.0, 388.0, 7.0, 28.49, 30.0, 256, 12499, 16),
    "velocity": ChirpProfile("velocity", 10.0, 60.0, 115.0, 7.0, 15.0, 100.0, 64, 9142, 128),
}


def derive(preference: RadarMode, rate_hz: float, num_tx: int = 3) -> ChirpProfile:
    """The template refitted to ``rate_hz``: fewer loops first, then a shorter idle time."""
    profile = dataclasses.replace(TEMPLATES[preference], rate_hz=float(rate_hz), num_tx=num_tx)
    budget_ms = DUTY * profile.frame_period_ms
    while profile.active_frame_ms > budget_ms and profile.loops > MIN_LOOPS:
        profile = dataclasses.replace(profile, loops=profile.loops // 2)
    if profile.active_frame_ms > budget_ms:
        chirp_us = budget_ms * 1000.0 / (profile.loops * num_tx)
        idle = math.floor((chirp_us - profile.ramp_end_us) * 100) / 100  # profileCfg takes 0.01 us steps
        if idle < MIN_IDLE_US:
            raise ValueError(f"{preference} preset cannot run at {rate_hz} Hz with {num_tx} TX")
        profile = dataclasses.replace(profile, idle_us=idle)
    return profile


def build_table(num_tx: int = 3) -> dict[tuple[RadarMode, int], ChirpProfile]:
    """The lookup table keyed by (preference, frame rate in Hz)."""
    return {(pref, rate): derive(pref, rate, num_tx) for pref in ("range", "velocity") for rate in RATES_HZ}


_TABLES: dict[int, dict[tuple[RadarMode, int], ChirpProfile]] = {}


def lookup(preference: RadarMode, rate_hz: float, num_tx: int = 3) -> ChirpProfile:
    """The table row for the nearest tabulated rate (1-30 Hz)."""
    table = _TABLES.get(num_tx) or _TABLES.setdefault(num_tx, build_table(num_tx))
    rate = min(RATES_HZ, key=lambda r: abs(r - rate_hz))
    return table[(preference, rate)]


def max_rate_hz(
    preference: RadarMode, num_tx: int = 3, max_points: int = MAX_POINTS, range_profile: bool = False
) -> int:
    """Highest tabulated rate whose profile passes every check."""
    ok = [r for r in RATES_HZ if not lookup(preference, r, num_tx).problems(max_points, range_profile)]
    if not ok:
        raise ValueError(f"no {preference} profile fits the UART budget with {max_points} points per frame")
    return max(ok)
