"""How one state's values came about: train exactly as ``respecd train-policy`` does, with that state's
updates traced.

For a table whose choice in some state looks wrong (``python -m respecd.lab.experiment.pin``), this runs its
training again — the same profile, episodes, seeds and pinned latency give the same table, bit for bit — and
records every update made in STATE: the cell each sensor's block took, that block's reward, the best value of
the block in the next state, and the next state. Per cell of one block (``--block``) it prints how many updates
the cell got and when (first and last update number of the whole training), their mean reward and next-state
value, and how many of them led into a state with another motion bin (a still state whose people start walking).
With ``--resume`` only this run's updates are traced (the loaded values arrive without any).

usage: python -m respecd.lab.experiment.trace bright/still/dense/medium/good/high/rgb --block rgb \\
           --profile configs/sim-rover-per-sensor-slowest-44-immediate.yaml --episodes 54 --seeds 4 \\
           --min-s 10 --max-s 20 --seed 0 --latency docs/reference-latency.json --out T.npz [--json TRACE]
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from respecd.control.qlearning import FactoredQTable, block_spans
from respecd.control.state import StateSpace
from respecd.errors import ConfigError, InputError, report


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
        self.updates: list[Update] = []
        try:
            self.state = controller.states.index(controller.states.parse(state))
        except ValueError as err:
            raise InputError(str(err)) from None
        names = [slot.name for slot in controller.space.slots]
        if block not in names:
            raise InputError(f"--block {block!r}: expected one of {', '.join(names)}")
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


def main(argv: list[str] | None = None) -> int:
    import json

    from respecd.cli import train_policy
    from respecd.outputs import check_output_file

    parser = argparse.ArgumentParser(prog="python -m respecd.lab.experiment.trace", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("state", help="the traced state, e.g. bright/still/dense/medium/good/high/rgb")
    parser.add_argument("--block", default="rgb", help="the sensor whose cells are summarized (default rgb)")
    parser.add_argument("--json", type=Path, help="write every traced update and the summary here")
    train_policy.add_arguments(parser)
    a = parser.parse_args(argv)
    tracers: list[Tracer] = []

    def watch(table: Any, controller: Any) -> None:
        if not isinstance(table, FactoredQTable):
            raise InputError("the profile's table is not factored (controller.actions.mode)")
        tracers.append(Tracer(table, controller, a.state, a.block))

    try:
        check_output_file("--json", a.json, example="trace.json")  # written after the training; folders are made
        code = train_policy.main(a, on_table=watch)
    except (ConfigError, InputError) as err:
        return report(err, "trace")
    rows = summary(tracers[0].updates, a.state, tracers[0].controller.states)
    if not rows:
        print(f"no update was made in {a.state}")
    for row in rows:
        moved = "" if row["into_other_motion"] is None else f", {row['into_other_motion']} into another motion bin"
        print(f"{row['cell']}: {row['updates']} updates ({row['first']}-{row['last']}), mean reward "
              f"{row['mean_reward']:.3f}, mean next-state value {row['mean_next_value']:.3f}{moved}; "
              f"value {row['value']:.3f}")
    if a.json:
        doc = {"state": a.state, "block": a.block, "summary": rows,
               "updates": [asdict(u) for u in tracers[0].updates]}
        a.json.parent.mkdir(parents=True, exist_ok=True)  # as `respecd bench --json`: a training's trace is not lost
        a.json.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return code


if __name__ == "__main__":
    raise SystemExit(main())
