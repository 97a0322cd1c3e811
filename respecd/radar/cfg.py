"""Chirp configuration text (.cfg) for the TI out-of-box demo: render, read, interpret.

``render`` turns a ``ChirpProfile`` into the full command sequence the CLI port takes
(``sensorStop``, ``flushCfg``, ..., ``sensorStart``) for the firmware the board runs (the
ISK's HWA+DSP image needs ``bpmCfg``, the HWA-only images reject it). The lines around the
chirp follow TI's mmWave Demo Visualizer 3.6 xWR68xx presets, or a user's own base cfg:
then only the chirp-dependent commands are replaced and everything else (CFAR thresholds,
calibration, clutter removal) is kept in the user's order.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import Literal

from respecd.errors import ConfigError, InputError
from respecd.radar.chirp import UART_BYTES_PER_S, ChirpProfile

Board = Literal["isk", "aop"]
Firmware = Literal["xwr68xx_mmw_demo", "xwr64xx_mmw_demo", "xwr64xxAOP_mmw_demo"]
MAX_CFG_BYTES = 256 * 1024  # TI's cfgs are 1-3 kB; a device or a FIFO is refused by this, not by memory
REQUIRED = ("channelCfg", "profileCfg", "chirpCfg", "frameCfg")  # a base cfg must have these
GENERATED = (*REQUIRED, "guiMonitor", "cfarFovCfg", "CQRxSatMonitor", "CQSigImgMonitor", "bpmCfg")
OPEN_ONLY = ("channelCfg", "adcCfg", "lowPower")  # the demo applies these once per boot: never change them
# The HWA+DSP demo (IWR6843ISK/ODS out-of-box image) counts bpmCfg in its "full configuration" and
# refuses the first sensorStart without it (SDK 3.x mss_main.c, MmwDemo_isAllCfgInPendingState);
# the HWA-only images (xwr64xx, the AOP out-of-box image) have no such command.
BPM_FIRMWARE = frozenset({"xwr68xx_mmw_demo"})
DEFAULT_FIRMWARE: dict[str, Firmware] = {"isk": "xwr68xx_mmw_demo", "aop": "xwr64xxAOP_mmw_demo"}
BPM_LINE = "bpmCfg -1 0 0 1"  # BPM off, as in TI's ISK lab cfgs (e.g. the automated-doors ISK cfg)
_TX_MASKS = {  # chirp order per board: ISK TX1 is the elevation antenna, so TX2 goes second
    ("isk", 3): (1, 4, 2),
    ("isk", 2): (1, 4),
    ("aop", 3): (1, 2, 4),
}
_PHASE = {"isk": " 1 0" * 12, "aop": " 1 0 -1 0" * 6}  # compRangeBiasAndRxChanPhase, 12 virtual antennas
_RX_GAIN = {"isk": 30, "aop": 158}  # as in TI's ISK lab cfg and the AOP visualizer preset
_CFAR_DOPPLER = {"range": "cfarCfg -1 1 0 4 2 3 1 15 1", "velocity": "cfarCfg -1 1 0 8 4 4 1 15 1"}


def parse_lines(text: str) -> list[str]:
    """Command lines of a cfg: comments (%) and blank lines dropped, spacing normalized."""
    out = []
    for line in text.splitlines():
        line = line.split("%", 1)[0].strip()
        if line:
            out.append(" ".join(line.split()))
    return out


def read_cfg(path: str | Path) -> list[str]:
    """A cfg file's command lines; InputError naming the file when it cannot be used."""
    path = Path(path)
    try:
        with path.open("rb") as handle:  # at most one byte past the limit: /dev/zero or a FIFO has no size
            data = handle.read(MAX_CFG_BYTES + 1)
        if len(data) > MAX_CFG_BYTES:
            raise InputError(f"{path}: more than {MAX_CFG_BYTES} bytes, expected a cfg file of ASCII mmWave "
                             "CLI commands (a few kB)")
        lines = parse_lines(data.decode("ascii"))
    except FileNotFoundError as err:
        raise InputError(f"{path}: no such cfg file") from err
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read cfg file ({err}); expected ASCII mmWave CLI commands") from err
    missing = [name for name in REQUIRED if not any(line.split()[0] == name for line in lines)]
    if missing:
        raise InputError(f"{path}: cfg lacks {', '.join(missing)} (expected a TI out-of-box demo chirp cfg)")
    return lines


def chirp_lines(profile: ChirpProfile, board: Board = "isk", firmware: Firmware | None = None) -> dict[str, list[str]]:
    """The chirp- and firmware-dependent commands, grouped by command name."""
    masks = _TX_MASKS.get((board, profile.num_tx))
    if masks is None:
        raise ConfigError(f"{profile.num_tx} TX is not supported on the {board} board (use 3, or 2 on isk)")
    tx_enable = sum(masks)
    sampling_us = profile.sampling_us
    vmax = math.floor(profile.max_velocity_mps * 100) / 100  # never beyond the unambiguous limit
    bpm = (firmware or DEFAULT_FIRMWARE[board]) in BPM_FIRMWARE
    return {
        "channelCfg": [f"channelCfg 15 {tx_enable} 0"],
        "profileCfg": [
            f"profileCfg 0 {_num(profile.start_freq_ghz)} {_num(profile.idle_us)} {_num(profile.adc_start_us)} "
            f"{_num(profile.ramp_end_us)} 0 0 {_num(profile.slope_mhz_us)} 1 {profile.adc_samples} "
            f"{profile.sample_rate_ksps} 0 0 {_RX_GAIN[board]}"
        ],
        "chirpCfg": [f"chirpCfg {i} {i} 0 0 0 0 0 {mask}" for i, mask in enumerate(masks)],
        "frameCfg": [f"frameCfg 0 {profile.num_tx - 1} {profile.loops} 0 {_num(profile.frame_period_ms)} 1 0"],
        "guiMonitor": [f"guiMonitor -1 1 {int(profile.range_profile)} 0 0 0 1"],  # points + side info, stats
        "cfarFovCfg": [f"cfarFovCfg -1 0 0 {profile.max_range_m:.2f}", f"cfarFovCfg -1 1 -{vmax:.2f} {vmax:.2f}"],
        # saturation monitor slices of 4 x 0.16 us over the sampling window; image monitor N/2 - 1 slices
        "CQRxSatMonitor": [f"CQRxSatMonitor 0 3 4 {2 * int(sampling_us / 0.64) - 1} 0"],
        "CQSigImgMonitor": [f"CQSigImgMonitor 0 {profile.adc_samples // 2 - 1} 4"],
        "bpmCfg": [BPM_LINE] if bpm else [],
    }


def default_base(profile: ChirpProfile, board: Board = "isk") -> list[str]:
    """The visualizer preset lines; chirp-dependent ones are placeholders filled by ``render``."""
    return [
        "sensorStop", "flushCfg", "dfeDataOutputMode 1", "channelCfg", "adcCfg 2 1", "adcbufCfg -1 0 1 1 1",
        "profileCfg", "chirpCfg", "frameCfg", "lowPower 0 0", "guiMonitor",
        "cfarCfg -1 0 2 8 4 3 0 15 1", _CFAR_DOPPLER[profile.preference], "multiObjBeamForming -1 1 0.5",
        "clutterRemoval -1 0", "calibDcRangeSig -1 0 -5 8 256", "extendedMaxVelocity -1 0", "bpmCfg",
        "lvdsStreamCfg -1 0 0 0",
        f"compRangeBiasAndRxChanPhase 0.0{_PHASE[board]}", "measureRangeBiasAndRxChanPhase 0 1.5 0.2",
        "CQRxSatMonitor", "CQSigImgMonitor", "analogMonitor 0 0", "aoaFovCfg -1 -90 90 -90 90",
        "cfarFovCfg", "calibData 0 0 0", "sensorStart",
    ]


def render(
    profile: ChirpProfile, board: Board = "isk", base: Iterable[str] | None = None, firmware: Firmware | None = None
) -> list[str]:
    """The full command sequence: sensorStop, flushCfg, config, sensorStart."""
    generated = chirp_lines(profile, board, firmware)
    lines = list(base) if base is not None else default_base(profile, board)
    if generated["bpmCfg"] and not any(line.split()[0] == "bpmCfg" for line in lines):
        lines = _insert_before(lines, "bpmCfg", ("lvdsStreamCfg", "compRangeBiasAndRxChanPhase", "sensorStart"))
    out, emitted = ["sensorStop", "flushCfg"], set()
    for line in lines:
        command = line.split()[0]
        if command in ("sensorStop", "flushCfg", "sensorStart"):
            continue
        if command in generated:
            if command not in emitted:
                out.extend(generated[command])
                emitted.add(command)
            continue
        out.append(line)
    out.append("sensorStart")
    return out


def _insert_before(lines: list[str], line: str, anchors: tuple[str, ...]) -> list[str]:
    """``lines`` with ``line`` before the first command named in ``anchors`` (else at the end)."""
    for anchor in anchors:
        for i, existing in enumerate(lines):
            if existing.split()[0] == anchor:
                return [*lines[:i], line, *lines[i:]]
    return [*lines, line]


def header(profile: ChirpProfile, board: Board, firmware: Firmware | None = None) -> list[str]:
    """Comment lines (%) that state the figures, as the visualizer's cfg headers do."""
    f = profile.figures()
    frame_bytes = profile.uart_bytes_per_frame()
    return [
        f"% respecd chirp profile: prefer {profile.preference} resolution, {_num(profile.rate_hz)} fps, "
        f"board {board}, firmware {firmware or DEFAULT_FIRMWARE[board]}, {profile.num_tx} TX, {profile.loops} loops",
        f"% Range Resolution(m): {f['range_resolution_m']}",
        f"% Maximum unambiguous Range(m): {f['max_range_m']}",
        f"% Maximum Radial Velocity(m/s): {f['max_velocity_mps']}",
        f"% Radial velocity resolution(m/s): {f['velocity_resolution_mps']}",
        f"% Frame Duration(msec): {f['frame_period_ms']} (active {f['active_frame_ms']})",
        f"% UART: {frame_bytes} B/frame at {profile.max_points} points = {profile.uart_ms:.2f} ms, "
        f"{100 * frame_bytes * profile.rate_hz / UART_BYTES_PER_S:.0f}% of 921600 baud",
    ]


def profile_from_lines(lines: Iterable[str], preference: str = "range") -> ChirpProfile:
    """Read profileCfg/frameCfg/channelCfg of an existing cfg back into a ChirpProfile."""
    found = {line.split()[0]: line.split()[1:] for line in lines}
    try:
        p, frame, channel = found["profileCfg"], found["frameCfg"], found["channelCfg"]
        num_tx = bin(int(channel[1])).count("1")
        return ChirpProfile(
            preference=preference,  # type: ignore[arg-type]
            rate_hz=1000.0 / float(frame[4]),
            start_freq_ghz=float(p[1]), idle_us=float(p[2]), adc_start_us=float(p[3]), ramp_end_us=float(p[4]),
            slope_mhz_us=float(p[7]), adc_samples=int(p[9]), sample_rate_ksps=int(p[10]),
            loops=int(frame[2]), num_tx=num_tx,
        )
    except (KeyError, IndexError, ValueError, ZeroDivisionError) as err:
        raise InputError(f"cfg profileCfg/frameCfg/channelCfg unreadable: {err!r}") from err


def _num(value: float) -> str:
    """Shortest text for a cfg number (60 not 60.0, 28.49 stays)."""
    return f"{value:.3f}".rstrip("0").rstrip(".")
