"""The two baselines the paper compares against, run through the same loop as the agent.

* **static**: every sensor at its richest setting and fastest rate, always.
* **heuristic**: hand-written rules over the named state bins (applied in this order, later
  rules win where they touch the same knob):

  1. start from the middle of every ladder (middle setting, middle rate);
  2. illumination **dark** → thermal to its richest setting and top rate, RGB to its
     cheapest resolution and a low rate; **bright** → RGB richest, thermal cheapest and
     low rate;
  3. motion **fast** → every rate to the top; **still** → every rate to the low level
     (the second rung, not the 1 Hz floor, so a change is still seen quickly);
  4. radar density **dense** → radar range mode, top rate; otherwise motion **fast** →
     velocity mode; otherwise range mode;
  5. confidence **low** and a dominant modality known → that modality to its richest
     setting and top rate (feed what the detector relies on);
  6. load **high** → every rate one rung down and RGB one resolution down;
     sync **poor** → no rate above the middle rung (fewer stale frames).

  ``controller.heuristic`` (``HeuristicRules``) adds what an engineer who knows the pipeline
  would write, all off by default: the still and fast rates and the bright-light RGB size
  as chosen values instead of fixed rungs (steps 2–3), then

  7. a sensor the detector does not read → its cheapest setting at its lowest rate;
  8. the radar no faster than the fastest camera, unless it is the dominant modality at
     low confidence (the detector runs on every new input frame: a fast radar would set
     its rate).
"""

from __future__ import annotations

from collections.abc import Mapping

from respecd.control.actions import ActionSpace, Position, Slot
from respecd.control.config import HeuristicRules
from respecd.messages import Resolution

DOCUMENTED = HeuristicRules()
CAMERAS = ("rgb", "thermal")


def static_position(space: ActionSpace) -> Position:
    return space.maximum()


def _mid(n: int) -> int:
    return (n - 1) // 2 if n > 2 else n // 2


def _low(slot: Slot) -> int:
    return min(1, len(slot.rates) - 1)


def _setting_index(slot: Slot, value: str) -> int | None:
    return slot.settings.index(value) if value in slot.settings else None


def _rung(slot: Slot, rate_hz: float) -> int:
    """The index of the slot's rate nearest ``rate_hz``."""
    return min(range(len(slot.rates)), key=lambda i: abs(slot.rates[i] - rate_hz))


def _size(slot: Slot, resolution: Resolution) -> int:
    """The index of the slot's resolution nearest ``resolution`` in pixels."""
    area = resolution[0] * resolution[1]
    return min(range(len(slot.settings)),
               key=lambda i: abs(_pixels(slot.settings[i]) - area))


def _pixels(setting: object) -> int:
    return setting[0] * setting[1] if isinstance(setting, tuple) else 0


def heuristic_position(space: ActionSpace, names: Mapping[str, str], rules: HeuristicRules = DOCUMENTED,
                       read: tuple[str, ...] | None = None) -> Position:
    """The rule-based target position for a state given as named bins; ``read``: the
    modalities the detector reads (rule 7; None: every one)."""
    cells = [[_mid(len(s.settings)), _mid(len(s.rates))] for s in space.slots]
    top = [len(s.rates) - 1 for s in space.slots]
    for i, slot in enumerate(space.slots):
        cell = cells[i]
        _light_rule(slot, cell, names.get("illumination"), top[i], rules)
        motion = names.get("motion")
        if motion == "fast":
            cell[1] = top[i] if rules.fast_rate_hz is None else _rung(slot, rules.fast_rate_hz)
        elif motion == "still":
            cell[1] = min(cell[1], _low(slot) if rules.still_rate_hz is None else _rung(slot, rules.still_rate_hz))
        if slot.modality == "radar":
            _radar_rule(slot, cell, names, top[i])
        if names.get("confidence") == "low" and names.get("dominant") == slot.modality:
            cell[:] = [len(slot.settings) - 1, top[i]]
        if names.get("load") == "high":
            cell[1] = max(cell[1] - 1, 0)
            if slot.modality == "rgb":
                cell[0] = max(cell[0] - 1, 0)
        if names.get("sync") == "poor":
            cell[1] = min(cell[1], _mid(len(slot.rates)))
    if rules.unread_floor and read is not None:
        for slot, cell in zip(space.slots, cells, strict=True):
            if slot.modality not in read:
                cell[:] = [0, 0]
    if rules.radar_follows_cameras:
        _radar_follows(space, cells, names)
    return tuple((s, r) for s, r in cells)


def _light_rule(slot: Slot, cell: list[int], light: str | None, top: int, rules: HeuristicRules) -> None:
    """Rule 2: dark → thermal up, RGB down; bright → RGB up (to ``bright_rgb``), thermal down."""
    if slot.modality == "thermal" and light == "dark":
        cell[:] = [len(slot.settings) - 1, top]
    elif slot.modality == "rgb" and light == "bright":
        richest = len(slot.settings) - 1
        cell[:] = [richest if rules.bright_rgb is None else _size(slot, rules.bright_rgb), top]
    elif slot.modality == "rgb" and light == "dark" or slot.modality == "thermal" and light == "bright":
        cell[:] = [0, _low(slot)]


def _radar_follows(space: ActionSpace, cells: list[list[int]], names: Mapping[str, str]) -> None:
    """Rule 8: the radar's rate at most the fastest camera's, unless the detector leans on it."""
    if names.get("confidence") == "low" and names.get("dominant") == "radar":
        return
    cameras = [s.rates[c[1]] for s, c in zip(space.slots, cells, strict=True) if s.modality in CAMERAS]
    if not cameras:
        return
    for slot, cell in zip(space.slots, cells, strict=True):
        if slot.modality == "radar":
            allowed = [i for i, r in enumerate(slot.rates) if r <= max(cameras) + 1e-9]
            cell[1] = min(cell[1], max(allowed, default=0))


def _radar_rule(slot: Slot, cell: list[int], names: Mapping[str, str], top: int) -> None:
    ranged = _setting_index(slot, "range")
    velocity = _setting_index(slot, "velocity")
    if names.get("radar_density") == "dense":
        cell[1] = top
        if ranged is not None:
            cell[0] = ranged
    elif names.get("motion") == "fast" and velocity is not None:
        cell[0] = velocity
    elif ranged is not None:
        cell[0] = ranged
