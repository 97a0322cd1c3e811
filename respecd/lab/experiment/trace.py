"""How one state's values came about: ``respecd train-policy --trace STATE`` trains exactly as without it,
with that state's updates traced.

For a table whose choice in some state looks wrong (``respecd experiment pin``), the same training again
— the same profile, episodes, seeds and pinned latency give the same table, bit for bit — records every
update made in STATE: the cell each sensor's block took, that block's reward, the best value of the block in
the next state, and the next state. Per cell of one block (``--trace-block``) it prints how many updates the
cell got and when (first and last update number of the whole training), their mean reward and next-state
value, and how many of them led into a state with another motion bin (a still state whose people start
walking). With ``--resume`` only this run's updates are traced (the loaded values arrive without any).

usage: respecd train-policy --trace bright/still/dense/medium/good/high/rgb --trace-block rgb \\
           --profile respecd/lab/profiles/sim-rover-per-sensor-slowest-44-immediate.yaml --episodes 54 --seeds 4 \\
           --min-s 10 --max-s 20 --seed 0 --latency cpu --out T.npz [--trace-json TRACE]
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from respecd.control.qlearning import FactoredQTable, block_spans
from respecd.control.state import StateSpace
from respecd.errors import InputError


@dataclass(frozen=True)
class Update:
    """One update of the traced state, as its block of interest saw it."""

    number: int  # the table's update count after it
    cell: str  # the block's cell that was updated
    reward: float  # the block's reward (per-sensor credit: its own share)
    next_value: float  # the block's best value in the next state, before the update
    next_state: str
    value_after: float


class Tracer:
    """Wraps one table's ``update`` (the instance, not the class) to record the updates of ``state``."""

    def __init__(self, table: FactoredQTable, controller: Any, state: str, block: str) -> None:
        self.table, self.controller = table, controller
        self.state_text, self.block_name = state, block
        self.updates: list[Update] = []
        try:
            self.state = controller.states.index(controller.states.parse(state))
        except ValueError as err:
            raise InputError(str(err)) from None
        names = [slot.name for slot in controller.space.slots]
        if block not in names:
            raise InputError(f"--trace-block {block!r}: expected one of {', '.join(names)}")
        self.block = names.index(block)
        self.span = block_spans(table.blocks)[self.block]
        self.columns = controller.space.descriptions()
        self._update = table.update
        table.update = self._traced  # type: ignore[method-assign]

    def _traced(self, state: int, action: int, reward: float, next_state: int,
                block_rewards: Sequence[float] | None = None, immediate: Sequence[bool] | None = None) -> float:
        if state != self.state:
            return self._update(state, action, reward, next_state, block_rewards, immediate)
        start, end = self.span
        column = start + self.table.cells(action)[self.block]
        next_value = float(self.table.q[next_state, start:end].max())
        error = self._update(state, action, reward, next_state, block_rewards, immediate)
        own = reward if block_rewards is None else block_rewards[self.block]
        describe = self.controller.states.describe
        self.updates.append(Update(self.table.updates, self.columns[column], float(own), next_value,
                                   describe(self.controller.states.unindex(next_state)),
                                   float(self.table.q[state, column])))
        return error


def summary(updates: list[Update], state: str, states: StateSpace) -> list[dict[str, Any]]:
    """Per cell, in order of first update: count, first and last update number, mean reward, mean next-state
    value, how many led into a state with another motion bin than ``state``'s, and the cell's last value."""
    motion = states.factors.index("motion") if "motion" in states.factors else None
    own = None if motion is None else states.parse(state)[motion]
    rows = []
    for cell in dict.fromkeys(u.cell for u in updates):
        mine = [u for u in updates if u.cell == cell]
        rows.append({"cell": cell, "updates": len(mine), "first": mine[0].number, "last": mine[-1].number,
                     "mean_reward": round(float(np.mean([u.reward for u in mine])), 4),
                     "mean_next_value": round(float(np.mean([u.next_value for u in mine])), 4),
                     "into_other_motion": None if motion is None else
                     sum(states.parse(u.next_state)[motion] != own for u in mine),
                     "value": round(mine[-1].value_after, 4)})
    return rows


def tracer_for(table: Any, controller: Any, state: str, block: str) -> Tracer:
    """A tracer on ``table`` (``respecd train-policy --trace``); InputError for a table that is not factored."""
    if not isinstance(table, FactoredQTable):
        raise InputError("--trace: the profile's table is not factored (controller.actions.mode)")
    return Tracer(table, controller, state, block)


def print_and_write(tracer: Tracer, json_path: Path | None) -> None:
    """Per cell of the traced block, one line; every update and the summary to ``json_path`` when given."""
    import json

    rows = summary(tracer.updates, tracer.state_text, tracer.controller.states)
    if not rows:
        print(f"no update was made in {tracer.state_text}")
    for row in rows:
        moved = "" if row["into_other_motion"] is None else f", {row['into_other_motion']} into another motion bin"
        print(f"{row['cell']}: {row['updates']} updates ({row['first']}-{row['last']}), mean reward "
              f"{row['mean_reward']:.3f}, mean next-state value {row['mean_next_value']:.3f}{moved}; "
              f"value {row['value']:.3f}")
    if json_path:
        doc = {"state": tracer.state_text, "block": tracer.block_name, "summary": rows,
               "updates": [asdict(u) for u in tracer.updates]}
        json_path.parent.mkdir(parents=True, exist_ok=True)  # as `respecd bench --json`: a training's trace is kept
        json_path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
