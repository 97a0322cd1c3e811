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
"""

from __future__ import annotations

from collections.abc import Mapping

from respecd.control.actions import ActionSpace, Position, Slot


def static_position(space: ActionSpace) -> Position:
    return space.maximum()


def _mid(n: int) -> int:
    return (n - 1) // 2 if n > 2 else n // 2


def _low(slot: Slot) -> int:
    return min(1, len(slot.rates) - 1)


def _setting_index(slot: Slot, value: str) -> int | None:
    return slot.settings.index(value) if value in slot.settings else None


def heuristic_position(space: ActionSpace, names: Mapping[str, str]) -> Position:
    """The rule-based target position for a state given as named bins."""
    cells = [[_mid(len(s.settings)), _mid(len(s.rates))] for s in space.slots]
    top = [len(s.rates) - 1 for s in space.slots]
    for i, slot in enumerate(space.slots):
        cell = cells[i]
        light = names.get("illumination")
        if slot.modality == "thermal" and light == "dark" or slot.modality == "rgb" and light == "bright":
            cell[:] = [len(slot.settings) - 1, top[i]]
        elif slot.modality == "rgb" and light == "dark" or slot.modality == "thermal" and light == "bright":
            cell[:] = [0, _low(slot)]
        motion = names.get("motion")
        if motion == "fast":
            cell[1] = top[i]
        elif motion == "still":
            cell[1] = min(cell[1], _low(slot))
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
    return tuple((s, r) for s, r in cells)


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
