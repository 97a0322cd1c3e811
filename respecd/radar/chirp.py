"""Chirp profiles for the two ReSPEC radar actions, the figures they imply, and TI's limits.

The controller picks a preference and a frame rate; ``lookup`` returns the chirp for that
key. The paper's two modes are *prefer range resolution* and *prefer velocity resolution*:

* range resolution is c / (2 B), B the swept bandwidth the ADC samples (slope x sampling
  time). The "range" rows sweep 2 GHz in 256 samples (0.073 m);
* velocity resolution is lambda / (2 T), T the active (chirping) time of a frame. The
  "velocity" rows spend the time each frame rate leaves: the frame period minus the UART
  write of the frame's points and the demo's inter-frame processing, up to 128 loops
  (the radar cube TI's own velocity preset uses) and a +-2 m/s unambiguous velocity floor.

Both modes sample at 12.499 Msps with a 100 MHz/us slope, so their IF band, and so their
maximum range (TI's 0.8 Fs convention, the cfg's own ``cfarFovCfg``), is the same 14.99 m:
the modes trade resolution, not coverage. TX count, ADC format and power mode are the
same in every row, because the demo cannot change them without a power cycle.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from respecd.messages import RadarMode

C = 3e8  # m/s
UART_BAUD = 921_600
UART_BYTES_PER_S = UART_BAUD / 10  # 8N1: 10 bits on the wire per byte -> 92,160 B/s
UART_OVERHEAD = 1.04  # the radar's own transmit_output_time is 1.00-1.04 x the wire time (real captures)
PROCESSING_MS = 5.0  # inter-frame processing reserve: 3.95-4.31 ms measured on a 98,304-cell cube (SDK 3.3)
BAND_GHZ = (60.0, 64.0)  # IWR6843
MAX_SAMPLE_RATE_KSPS = 12_500  # complex 1x ADC
MAX_SLOPE_MHZ_US = 100.0  # the steepest slope of TI's xWR68xx visualizer presets
IF_FRACTION = 0.8  # TI's range convention: the visualizer's cfarFovCfg limit is 0.8 Fs mapped to range
MIN_IDLE_US = 10.0  # chirp idle (synthesizer ramp-down); TI's presets use 8-388 us
MAX_CUBE_BYTES = 393_216  # radar cube of TI's best-velocity preset (64 bins x 128 loops x 12 antennas x 4 B)
MIN_VELOCITY_MPS = 2.0  # velocity rows keep +-2 m/s unambiguous: walking people and a slow rover
LOOP_STEPS = (128, 64, 32, 16)  # Doppler FFT sizes the table uses (powers of two, as TI's presets)
RATES_HZ = tuple(range(1, 31))  # table keys: every integer rate the controller may ask for
MAX_POINTS = 100  # points per frame the UART timeline is budgeted for (configurable)
RX = 4


@dataclass(frozen=True)
class ChirpProfile:
    """One row of the lookup table: profileCfg/frameCfg knobs, the UART budget, what they imply."""

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
    max_points: int = MAX_POINTS
    range_profile: bool = False  # TLV 2 streamed too

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
    def sampling_us(self) -> float:
        return self.adc_samples / (self.sample_rate_ksps / 1e3)

    @property
    def range_resolution_m(self) -> float:
        """c / (2 B_eff), B_eff = S N / Fs."""
        return C * self.sample_rate_ksps * 1e3 / (2 * self.slope_mhz_us * 1e12 * self.adc_samples)

    @property
    def max_range_m(self) -> float:
        """0.8 Fs of IF band mapped to range by the slope, in cm steps (the cfarFovCfg limit)."""
        metres = C * IF_FRACTION * self.sample_rate_ksps * 1e3 / (2 * self.slope_mhz_us * 1e12)
        return math.floor(metres * 100 + 1e-6) / 100

    @property
    def max_velocity_mps(self) -> float:
        """Unambiguous +- radial velocity: lambda / (4 Tc Ntx)."""
        return C / (4 * self.start_freq_ghz * 1e9 * self.chirp_us * 1e-6 * self.num_tx)

    @property
    def velocity_resolution_mps(self) -> float:
        """lambda / (2 T_active)."""
        return C / (2 * self.start_freq_ghz * 1e9 * self.chirp_us * 1e-6 * self.loops * self.num_tx)

    @property
    def range_bins(self) -> int:
        return 1 << math.ceil(math.log2(self.adc_samples))

    @property
    def doppler_bins(self) -> int:
        return 1 << math.ceil(math.log2(self.loops))

    @property
    def cube_bytes(self) -> int:
        """Radar cube in L3: range bins x Doppler bins x virtual antennas x cmplx16."""
        return self.range_bins * self.doppler_bins * self.num_tx * RX * 4

    def uart_bytes_per_frame(self) -> int:
        """Packet with ``max_points`` points: header, TLVs 1+7 (20 B/pt), 6, 9 (+2), padding to 32."""
        size = 40 + (8 + 16 * self.max_points) + (8 + 4 * self.max_points) + (8 + 24) + (8 + 28)
        if self.range_profile:
            size += 8 + 2 * self.range_bins
        return -(-size // 32) * 32

    @property
    def uart_ms(self) -> float:
        """Wire time of one packet at 921600 baud 8N1."""
        return self.uart_bytes_per_frame() / UART_BYTES_PER_S * 1000.0

    @property
    def chirp_budget_ms(self) -> float:
        """Time a frame leaves for chirping: the UART write (blocking) and processing must fit too."""
        return self.frame_period_ms - PROCESSING_MS - UART_OVERHEAD * self.uart_ms

    def figures(self) -> dict[str, float]:
        """The four radar figures the paper's lookup table yields, plus timing."""
        return {
            "range_resolution_m": round(self.range_resolution_m, 4),
            "max_range_m": self.max_range_m,
            "max_velocity_mps": round(self.max_velocity_mps, 3),
            "velocity_resolution_mps": round(self.velocity_resolution_mps, 4),
            "frame_period_ms": round(self.frame_period_ms, 3),
            "active_frame_ms": round(self.active_frame_ms, 3),
        }

    def problems(self) -> list[str]:
        """TI limits this profile breaks; empty when it is safe to send."""
        out = []
        if self.active_frame_ms > self.chirp_budget_ms:
            out.append(
                f"frame timeline: {self.active_frame_ms:.2f} ms chirping + {PROCESSING_MS:g} ms processing + "
                f"{UART_OVERHEAD * self.uart_ms:.2f} ms UART write ({self.uart_bytes_per_frame()} B at "
                f"{self.max_points} points) exceed the {self.frame_period_ms:.2f} ms frame"
            )
        if self.adc_start_us + self.sampling_us > self.ramp_end_us:
            end = self.adc_start_us + self.sampling_us
            out.append(f"ADC sampling ends at {end:.2f} us, after the ramp ({self.ramp_end_us} us)")
        top = self.start_freq_ghz + self.slope_mhz_us * self.ramp_end_us / 1000.0
        if self.start_freq_ghz < BAND_GHZ[0] or top > BAND_GHZ[1]:
            out.append(f"sweep {self.start_freq_ghz}-{top:.2f} GHz leaves the {BAND_GHZ[0]:g}-{BAND_GHZ[1]:g} GHz band")
        if self.sample_rate_ksps > MAX_SAMPLE_RATE_KSPS or self.slope_mhz_us > MAX_SLOPE_MHZ_US:
            out.append(f"ADC {self.sample_rate_ksps} ksps / slope {self.slope_mhz_us} MHz/us beyond the IWR6843")
        if self.idle_us < MIN_IDLE_US:
            out.append(f"idle time {self.idle_us} us below {MIN_IDLE_US:g} us")
        if self.cube_bytes > MAX_CUBE_BYTES:
            out.append(f"radar cube {self.cube_bytes} B exceeds {MAX_CUBE_BYTES} B")
        return out


# The chirps of the two modes (slope, sampling, ramp); loops and idle come from the frame timeline.
RANGE_CHIRP = dict(start_freq_ghz=60.0, idle_us=MIN_IDLE_US, adc_start_us=7.0, ramp_end_us=28.49,
                   slope_mhz_us=100.0, adc_samples=256, sample_rate_ksps=12_499)
VELOCITY_CHIRP = dict(start_freq_ghz=60.0, idle_us=MIN_IDLE_US, adc_start_us=7.0, ramp_end_us=13.13,
                      slope_mhz_us=100.0, adc_samples=64, sample_rate_ksps=12_499)


def _range_row(rate_hz: float, num_tx: int, max_points: int, range_profile: bool) -> ChirpProfile:
    """Fixed wide sweep; 32 loops where they take at most half the chirp budget, else 16."""
    row = ChirpProfile("range", float(rate_hz), loops=32, num_tx=num_tx, max_points=max_points,
                       range_profile=range_profile, **RANGE_CHIRP)  # type: ignore[arg-type]
    if row.active_frame_ms > 0.5 * row.chirp_budget_ms or row.cube_bytes > MAX_CUBE_BYTES:
        row = dataclasses.replace(row, loops=16)
    return row


def _velocity_row(rate_hz: float, num_tx: int, max_points: int, range_profile: bool) -> ChirpProfile:
    """Fill the chirp budget: the most loops whose chirp still has MIN_IDLE_US, Tc capped for +-2 m/s."""
    base = ChirpProfile("velocity", float(rate_hz), loops=LOOP_STEPS[-1], num_tx=num_tx, max_points=max_points,
                        range_profile=range_profile, **VELOCITY_CHIRP)  # type: ignore[arg-type]
    tc_max_us = C / (4 * base.start_freq_ghz * 1e9 * MIN_VELOCITY_MPS * num_tx) * 1e6
    for loops in LOOP_STEPS:
        row = dataclasses.replace(base, loops=loops)
        if row.cube_bytes > MAX_CUBE_BYTES:
            continue
        tc_us = min(row.chirp_budget_ms * 1000.0 / (loops * num_tx), tc_max_us)
        idle = math.floor((tc_us - row.ramp_end_us) * 100) / 100  # profileCfg takes 10-ns steps
        if idle >= MIN_IDLE_US:
            return dataclasses.replace(row, idle_us=idle)
    return base  # nothing fits: its problems() say why


def derive(
    preference: RadarMode, rate_hz: float, num_tx: int = 3, max_points: int = MAX_POINTS, range_profile: bool = False
) -> ChirpProfile:
    """The chirp for one key of the table."""
    make = _range_row if preference == "range" else _velocity_row
    return make(rate_hz, num_tx, max_points, range_profile)


Table = dict[tuple[RadarMode, int], ChirpProfile]
_TABLES: dict[tuple[int, int, bool], Table] = {}


def build_table(num_tx: int = 3, max_points: int = MAX_POINTS, range_profile: bool = False) -> Table:
    """The lookup table keyed by (preference, frame rate in Hz)."""
    return {
        (pref, rate): derive(pref, rate, num_tx, max_points, range_profile)
        for pref in ("range", "velocity")
        for rate in RATES_HZ
    }


def lookup(
    preference: RadarMode, rate_hz: float, num_tx: int = 3, max_points: int = MAX_POINTS, range_profile: bool = False
) -> ChirpProfile:
    """The table row for the nearest tabulated rate (1-30 Hz)."""
    key = (num_tx, max_points, range_profile)
    table = _TABLES.get(key) or _TABLES.setdefault(key, build_table(*key))
    rate = min(RATES_HZ, key=lambda r: abs(r - rate_hz))
    return table[(preference, rate)]


def max_rate_hz(
    preference: RadarMode, num_tx: int = 3, max_points: int = MAX_POINTS, range_profile: bool = False
) -> int:
    """Highest tabulated rate whose profile passes every check."""
    ok = [r for r in RATES_HZ if not lookup(preference, r, num_tx, max_points, range_profile).problems()]
    if not ok:
        raise ValueError(f"no {preference} profile fits the frame timeline with {max_points} points per frame")
    return max(ok)
