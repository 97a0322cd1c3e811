"""The action space: which configurations the controller may put the sensors in.

Each controlled sensor is a *slot* with a list of settings (RGB/thermal/depth resolution or
radar chirp preference, cheapest first) and a list of rate levels (ascending, never below
1 Hz so that a modality can prove useful again). A *position* picks one setting and one
rate per slot. The profile chooses how actions move between positions:

* ``moves``   action 0 keeps the position; the others raise or lower one slot's rate or
              setting by one step. |A| = 1 + 2·(rate ladders) + 2·(setting ladders): 13 for
              RGB + thermal + radar + depth, small enough to learn online.
* ``product`` every action is a whole position (the paper's full configurations);
              |A| = Π |settings|·|rates|, which grows fast, so it is capped by ``max_actions``.
* ``factored`` every action is a whole position too, but chosen sensor by sensor: the
              Q-table holds one block of |settings|·|rates| columns per slot
              (``FactoredQTable``), Σ instead of Π — 40 columns for the four sensors
              where the product has 7500. Action ids are the product's, so a decision
              names the full position it asks for.

Capabilities fold into the space when they are known: rate levels above what a driver can
do (the FLIR One stops near 9 Hz) collapse onto its maximum instead of becoming actions
that change nothing, and unsupported resolutions are dropped.

``shared_rate`` ties the rates of some sensors to the first of them (the *leader*): a follower
slot chooses only its setting and runs at the leader's rate, clamped to what it can do. The
detector runs on every new frame of its fastest input, so a camera at 1 Hz beside a radar at
5 Hz saves bytes but not load; independent per-sensor rates left the learner unable to find
"all of them slow" (docs/CONTROLLER.md "Actions").
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from respecd.control.config import ActionSpaceConfig
from respecd.errors import ConfigError
from respecd.messages import Modality, RadarMode, Resolution, SensorConfig
from respecd.sensors import MIN_RATE_HZ, Capabilities, DriverConfigBase, clamp_request

Setting = Resolution | RadarMode | None
Position = tuple[tuple[int, int], ...]  # (setting index, rate index) per slot


@dataclass(frozen=True, slots=True)
class Slot:
    """One controlled sensor: its settings (cheapest first) and rate levels (ascending)."""

    name: str
    modality: Modality
    settings: tuple[Setting, ...]
    rates: tuple[float, ...]
    follows: int | None = None  # index of the slot whose rate this one runs at (``shared_rate``)

    @property
    def n_cells(self) -> int:
        """How many (setting, rate) cells the slot chooses from: a follower chooses its setting only."""
        return len(self.settings) * (1 if self.follows is not None else len(self.rates))

    def request(self, setting: int, rate: int) -> SensorConfig:
        value = self.settings[setting]
        return SensorConfig(
            modality=self.modality,
            enabled=True,
            rate_hz=self.rates[rate],
            resolution=value if isinstance(value, tuple) else None,
            mode=value if isinstance(value, str) else None,
        )

    def nearest(self, config: SensorConfig) -> tuple[int, int]:
        """The (setting, rate) indices closest to what a driver reports it applied."""
        rate = min(range(len(self.rates)), key=lambda i: abs(self.rates[i] - config.rate_hz))
        wanted: Setting = config.resolution if config.resolution is not None else config.mode
        if wanted in self.settings:
            return self.settings.index(wanted), rate
        if isinstance(wanted, tuple) and all(isinstance(s, tuple) for s in self.settings):
            area = wanted[0] * wanted[1]
            setting = min(range(len(self.settings)), key=lambda i: abs(_area(self.settings[i]) - area))
            return setting, rate
        return 0, rate


@dataclass(frozen=True, slots=True)
class Move:
    """A moves-mode action: step one slot's rate or setting (slot -1: keep)."""

    slot: int
    kind: str  # "rate" or "setting"
    step: int  # +1 raise, -1 lower


KEEP = Move(-1, "keep", 0)


def _area(setting: Setting) -> int:
    return setting[0] * setting[1] if isinstance(setting, tuple) else 0


def _settings_for(modality: Modality, sensor: DriverConfigBase, config: ActionSpaceConfig) -> tuple[Setting, ...]:
    if modality == "rgb":
        return tuple(config.rgb_resolutions)
    if modality == "thermal":
        return tuple(config.thermal_resolutions)
    if modality == "radar":
        return tuple(config.radar_modes)
    if config.depth_resolutions:
        return tuple(config.depth_resolutions)
    return (tuple(sensor.resolution),) if sensor.resolution else (None,)  # type: ignore[return-value]


def _fit_settings(settings: tuple[Setting, ...], caps: Capabilities | None, modality: Modality) -> tuple[Setting, ...]:
    """Keep the settings the device supports; map the rest to what clamping would give."""
    if caps is None:
        return settings
    fitted: list[Setting] = []
    for setting in settings:
        probe = SensorConfig(
            modality=modality,
            resolution=setting if isinstance(setting, tuple) else None,
            mode=setting if isinstance(setting, str) else None,
        )
        applied = clamp_request(caps, probe)
        value: Setting = applied.resolution if applied.resolution is not None else applied.mode
        if value not in fitted:
            fitted.append(value)
    if len(fitted) > 1 and all(isinstance(s, tuple) for s in fitted):
        fitted.sort(key=_area)
    return tuple(fitted)


def _rate_bounds(caps: Capabilities | None, sync_cap: float) -> tuple[float, float]:
    """The lowest and highest rate a device can run at under the synchroniser's cap."""
    low = max(MIN_RATE_HZ, caps.min_rate_hz if caps else MIN_RATE_HZ)
    return low, min(sync_cap, caps.max_rate_hz if caps else sync_cap)


def _fit_rates(levels: Iterable[float], caps: Capabilities | None, sync_cap: float) -> tuple[float, ...]:
    low, high = _rate_bounds(caps, sync_cap)
    fitted = {min(max(level, low), high) for level in levels if math.isfinite(level)}
    return tuple(sorted(fitted)) or (low,)


def _follower_rates(leader: tuple[float, ...], caps: Capabilities | None, sync_cap: float) -> tuple[float, ...]:
    """The rate a follower runs at for each of its leader's levels: the level, clamped to the device."""
    low, high = _rate_bounds(caps, sync_cap)
    return tuple(min(max(level, low), high) for level in leader)


def build_slots(
    config: ActionSpaceConfig,
    sensors: Iterable[DriverConfigBase],
    capabilities: Mapping[str, Capabilities] | None = None,
    sync_cap_hz: float = 30.0,
    shared_rate: Iterable[Modality] = (),
) -> tuple[Slot, ...]:
    """One slot per enabled sensor whose modality the controller manages, in profile order; the
    sensors of ``shared_rate``'s modalities after the first of them follow its rate."""
    tied = set(shared_rate)
    slots: list[Slot] = []
    leader: int | None = None
    for sensor in sensors:
        if not sensor.enabled or sensor.modality not in config.modalities:
            continue
        caps = (capabilities or {}).get(sensor.name)
        settings = _fit_settings(_settings_for(sensor.modality, sensor, config), caps, sensor.modality)
        if sensor.modality in tied and leader is not None:
            rates = _follower_rates(slots[leader].rates, caps, sync_cap_hz)
            slots.append(Slot(sensor.name, sensor.modality, settings, rates, follows=leader))
            continue
        rates = _fit_rates(config.rate_levels_hz, caps, sync_cap_hz)
        if sensor.modality in tied:
            leader = len(slots)
        slots.append(Slot(sensor.name, sensor.modality, settings, rates))
    return tuple(slots)


class ActionSpace:
    """Actions, positions and their mapping to per-sensor ``SensorConfig`` requests."""

    def __init__(self, slots: tuple[Slot, ...], mode: str = "moves", max_actions: int = 4096) -> None:
        if not slots:
            raise ConfigError("controller: no sensor to control (check controller.actions.modalities)")
        self.slots = slots
        self.mode = mode
        self.follows: tuple[int | None, ...] = tuple(s.follows for s in slots)  # per slot: whose rate it runs at
        self._shared = any(f is not None for f in self.follows)
        self._radix = tuple(s.n_cells for s in slots)
        self.n_configs = math.prod(self._radix)
        self.moves: tuple[Move, ...] = (KEEP, *self._build_moves()) if mode == "moves" else ()
        self.n = len(self.moves) if mode == "moves" else self.n_configs
        # Q-table columns: one per action, or one block of cells per slot in factored mode
        self.blocks: tuple[int, ...] = self._radix if mode == "factored" else (self.n,)
        self.columns = sum(self.blocks)
        # SensorConfig per (slot, setting, rate), built once: requests() sits in the timed step
        self._requests = [
            {(i, j): s.request(i, j) for i in range(len(s.settings)) for j in range(len(s.rates))} for s in slots
        ]
        if self.columns > max_actions:
            raise ConfigError(
                f"controller.actions: {mode} space has {self.columns} actions, more than max_actions={max_actions} "
                "(use mode: moves, or fewer rate levels / resolutions)"
            )

    def _build_moves(self) -> list[Move]:
        moves = []
        for i, slot in enumerate(self.slots):
            if len(slot.rates) > 1 and slot.follows is None:
                moves += [Move(i, "rate", -1), Move(i, "rate", +1)]
            if len(slot.settings) > 1:
                moves += [Move(i, "setting", -1), Move(i, "setting", +1)]
        return moves

    # positions -------------------------------------------------------------------------
    def maximum(self) -> Position:
        """Every sensor at its richest setting and fastest rate (the static baseline)."""
        return tuple((len(s.settings) - 1, len(s.rates) - 1) for s in self.slots)

    def config_id(self, position: Position) -> int:
        """Mixed-radix number of a position (the product-mode action that selects it)."""
        index = 0
        for (setting, rate), slot, radix in zip(position, self.slots, self._radix, strict=True):
            index = index * radix + (setting if slot.follows is not None else setting * len(slot.rates) + rate)
        return index

    def position_of(self, config_id: int) -> Position:
        cells = []
        for slot, radix in zip(reversed(self.slots), reversed(self._radix), strict=True):
            config_id, cell = divmod(config_id, radix)
            cells.append((cell, 0) if slot.follows is not None else divmod(cell, len(slot.rates)))
        return self.tied(tuple(reversed(cells)))

    def tied(self, position: Position) -> Position:
        """``position`` with every follower at its leader's rate level (unchanged without ``shared_rate``)."""
        if not self._shared:
            return position
        return tuple(cell if leader is None else (cell[0], position[leader][1])
                     for cell, leader in zip(position, self.follows, strict=True))

    def nearest(self, applied: Mapping[str, SensorConfig]) -> Position:
        """The position closest to the drivers' current configurations (lowest if unknown)."""
        return self.tied(tuple(
            slot.nearest(applied[slot.name]) if slot.name in applied else (0, 0) for slot in self.slots
        ))

    # actions ---------------------------------------------------------------------------
    def apply(self, position: Position, action: int) -> Position:
        """The position an action leads to (a move past the end of a ladder stays put)."""
        if self.mode != "moves":
            return self.position_of(action)
        move = self.moves[action]
        if move.slot < 0:
            return position
        slot = self.slots[move.slot]
        setting, rate = position[move.slot]
        if move.kind == "rate":
            rate = min(max(rate + move.step, 0), len(slot.rates) - 1)
        else:
            setting = min(max(setting + move.step, 0), len(slot.settings) - 1)
        cells = list(position)
        cells[move.slot] = (setting, rate)
        return self.tied(tuple(cells))

    def hold_action(self, position: Position) -> int:
        """The action that keeps ``position`` (used while the dwell time forbids a switch)."""
        return 0 if self.mode == "moves" else self.config_id(position)

    def requests(self, position: Position) -> tuple[SensorConfig, ...]:
        return tuple(table[cell] for table, cell in zip(self._requests, position, strict=True))

    def describe(self, action: int) -> str:
        if self.mode != "moves":
            return self.describe_position(self.position_of(action))
        move = self.moves[action]
        if move.slot < 0:
            return "keep"
        return f"{self.slots[move.slot].name} {move.kind} {'up' if move.step > 0 else 'down'}"

    def describe_position(self, position: Position) -> str:
        return " ".join(self.describe_cell(i, setting, rate) for i, (setting, rate) in enumerate(position))

    def descriptions(self) -> list[str]:
        """A name per Q-table column: the actions, or in factored mode each slot's cells."""
        if self.mode != "factored":
            return [self.describe(a) for a in range(self.n)]
        return [self.describe_cell(i, setting, rate) for i, slot in enumerate(self.slots)
                for setting in range(len(slot.settings))
                for rate in ((None,) if slot.follows is not None else range(len(slot.rates)))]

    def describe_cell(self, slot_index: int, setting: int, rate: int | None) -> str:
        """``rgb 640x360@5Hz``; a follower's column has no rate of its own: ``thermal 160x120``."""
        slot = self.slots[slot_index]
        value = slot.settings[setting]
        label = f"{value[0]}x{value[1]}" if isinstance(value, tuple) else (value or "")
        if rate is None:
            return f"{slot.name} {label}".rstrip()
        return f"{slot.name} {label}@{slot.rates[rate]:g}Hz".replace(" @", " ")

    def fingerprint_data(self) -> dict[str, Any]:
        """What a saved Q-table must match to be reused."""
        return {
            "mode": self.mode,
            "slots": [
                {"name": s.name, "modality": s.modality, "settings": [list(x) if isinstance(x, tuple) else x
                                                                       for x in s.settings], "rates": list(s.rates)}
                | ({} if s.follows is None else {"follows": self.slots[s.follows].name})
                for s in self.slots
            ],
        }
