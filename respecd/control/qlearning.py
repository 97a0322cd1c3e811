"""Tabular Watkins Q-learning with ε-greedy exploration: pure numpy, seedable.

    Q(s, a) ← Q(s, a) + lr · (r + discount · max_a' Q(s', a') − Q(s, a))

The step size lr is ``max(learning_rate, 1/n)`` for a cell's n-th update (``step_size:
visits``): the first update replaces the initial value, so an optimistic start drives
exploration without staying in the values a frozen table acts on. ``constant`` keeps
``learning_rate`` throughout.

ε decays geometrically after every update down to ``epsilon_min``. Greedy ties are broken
at random (with the seeded generator), so a zero- or optimistically-initialised table does
not always pick action 0. ``visits`` counts updates per (state, action) for ``policy show``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from respecd.control.config import Learning

SMALL_ROW = 64  # actions per state below which plain Python beats numpy per call


def block_spans(blocks: tuple[int, ...] | list[int]) -> list[tuple[int, int]]:
    """Each block's [start, end) columns in a factored table's row."""
    ends = np.cumsum(blocks).tolist()
    return [(end - size, end) for size, end in zip(blocks, ends, strict=True)]


def updates_per_state(visits: np.ndarray, n_blocks: int) -> np.ndarray:
    """Updates per state from visit counts: an update visits one column of each block."""
    return visits.sum(axis=1) // n_blocks


class QTable:
    """Q-values (n_states × n_actions, float64) plus visit counts and the ε schedule."""

    def __init__(self, n_states: int, n_actions: int, learning: Learning, seed: int = 0) -> None:
        self.learning = learning
        init = learning.optimistic_value if learning.init == "optimistic" else 0.0
        self.q = np.full((n_states, n_actions), init, dtype=np.float64)
        self.visits = np.zeros((n_states, n_actions), dtype=np.int64)
        self.updates = 0
        self.epsilon = learning.epsilon_start
        self.rng = np.random.default_rng(seed)

    @property
    def shape(self) -> tuple[int, int]:
        return self.q.shape

    def state_updates(self) -> np.ndarray:
        """Updates per state (each visits one column here, one per block in a factored table)."""
        return updates_per_state(self.visits, 1)

    def updates_of(self, state: int) -> int:
        """Updates of one state (``state_updates`` for one row)."""
        return int(self.visits[state].sum())

    def update(self, state: int, action: int, reward: float, next_state: int) -> float:
        """One Watkins update; returns the TD error."""
        target = reward + self.learning.discount * self._row_max(next_state)
        error = target - float(self.q[state, action])
        self.visits[state, action] += 1
        self.q[state, action] += self.step(int(self.visits[state, action])) * error
        self.updates += 1
        self.epsilon = max(self.learning.epsilon_min, self.epsilon * self.learning.epsilon_decay)
        return error

    def step(self, n: int) -> float:
        """The step size of a cell's ``n``-th update."""
        rate = self.learning.learning_rate
        return max(rate, 1.0 / n) if self.learning.step_size == "visits" else rate

    def _row_max(self, state: int) -> float:
        row = self.q[state]
        # a few dozen values: Python's max over tolist() beats a numpy reduction's overhead
        return max(row.tolist()) if row.size <= SMALL_ROW else float(row.max())

    def greedy(self, state: int) -> int:
        row = self.q[state]
        if row.size <= SMALL_ROW:
            values = row.tolist()
            best = max(values)
            ties = [i for i, v in enumerate(values) if v == best]
        else:
            ties = np.flatnonzero(row == row.max()).tolist()
        if len(ties) == 1:
            return ties[0]
        return ties[int(self.rng.integers(len(ties)))]

    def greedy_tried(self, state: int) -> int | None:
        """The best action among those ever updated in ``state``; None if none was.

        A frozen policy should act on what it learned: with optimistic init an untried
        action keeps its optimistic value and would otherwise win every argmax.
        """
        tried = np.flatnonzero(self.visits[state])
        if tried.size == 0:
            return None
        values = self.q[state, tried]
        ties = tried[values == values.max()]
        return int(ties[0]) if ties.size == 1 else int(ties[self.rng.integers(ties.size)])

    def choose(self, state: int, epsilon: float) -> int:
        """ε-greedy: a uniformly random action with probability ``epsilon``."""
        if epsilon > 0.0 and self.rng.random() < epsilon:
            return int(self.rng.integers(self.q.shape[1]))
        return self.greedy(state)

    def restore(self, q: np.ndarray, visits: np.ndarray, updates: int, epsilon: float) -> None:
        """Load saved values (shapes must match; checked by the caller)."""
        self.q[...] = q
        self.visits[...] = visits
        self.updates = int(updates)
        self.epsilon = float(epsilon)


class FactoredQTable(QTable):
    """One block of columns per sensor: each sensor picks its own (setting, rate) cell and
    every block learns from the shared reward (independent learners on a factored action).

    An action is absolute, so its value does not depend on a configuration the state cannot
    see (the aliasing of relative moves), and the table holds Σ|cells| columns per state
    where the full product would hold Π|cells|. An action id is the mixed-radix number of the
    cells, first block most significant: the number ``ActionSpace.config_id`` gives the
    position, so decisions, logs and the dwell hold read as in product mode.
    """

    def __init__(self, n_states: int, blocks: tuple[int, ...], learning: Learning, seed: int = 0) -> None:
        if not blocks or min(blocks) < 1:
            raise ValueError(f"blocks must be positive sizes, got {blocks}")
        super().__init__(n_states, sum(blocks), learning, seed)
        self.blocks = tuple(blocks)
        self._spans = block_spans(self.blocks)
        self._columns = [list(range(a, b)) for a, b in self._spans]

    def state_updates(self) -> np.ndarray:
        return updates_per_state(self.visits, len(self.blocks))

    def updates_of(self, state: int) -> int:
        return int(self.visits[state].sum()) // len(self.blocks)

    def cells(self, action: int) -> list[int]:
        """Each block's cell in an action id."""
        out = []
        for size in reversed(self.blocks):
            action, cell = divmod(action, size)
            out.append(cell)
        return out[::-1]

    def encode(self, cells: list[int]) -> int:
        action = 0
        for cell, size in zip(cells, self.blocks, strict=True):
            action = action * size + cell
        return action

    def update(self, state: int, action: int, reward: float, next_state: int,
               block_rewards: Sequence[float] | None = None, immediate: Sequence[bool] | None = None) -> float:
        """The Watkins update of every block's chosen cell; returns the mean TD error. ``block_rewards``:
        one reward per block (per-sensor credit) instead of ``reward`` for all; ``immediate``: per block,
        learn the reward alone (discount 0) instead of bootstrapping from the next state."""
        discount = self.learning.discount
        row, following, visits = self.q[state], self.q[next_state].tolist(), self.visits[state]
        rewards = [reward] * len(self.blocks) if block_rewards is None else list(block_rewards)
        myopic = [False] * len(self.blocks) if immediate is None else list(immediate)
        if len(rewards) != len(self.blocks) or len(myopic) != len(self.blocks):
            raise ValueError(f"{len(rewards)} block rewards, {len(myopic)} immediate flags "
                             f"for {len(self.blocks)} blocks")
        total = 0.0
        for (start, end), cell, r, now in zip(self._spans, self.cells(action), rewards, myopic, strict=True):
            column = start + cell
            future = 0.0 if now else discount * max(following[start:end])
            error = r + future - float(row[column])
            visits[column] += 1
            row[column] += self.step(int(visits[column])) * error
            total += error
        self.updates += 1
        self.epsilon = max(self.learning.epsilon_min, self.epsilon * self.learning.epsilon_decay)
        return total / len(self.blocks)

    def _best(self, values: list[float], candidates: list[int]) -> int:
        best = max(values[i] for i in candidates)
        ties = [i for i in candidates if values[i] == best]
        return ties[0] if len(ties) == 1 else ties[int(self.rng.integers(len(ties)))]

    def greedy(self, state: int) -> int:
        values = self.q[state].tolist()
        spans = zip(self._spans, self._columns, strict=True)
        return self.encode([self._best(values, columns) - a for (a, _), columns in spans])

    def greedy_tried(self, state: int) -> int | None:
        """Each block's best cell among those updated in ``state``; None if the state was never
        updated (every update visits all blocks, so either all have tried cells or none)."""
        values, visits = self.q[state].tolist(), self.visits[state].tolist()
        cells = []
        for a, b in self._spans:
            tried = [i for i in range(a, b) if visits[i]]
            if not tried:
                return None
            cells.append(self._best(values, tried) - a)
        return self.encode(cells)

    def choose(self, state: int, epsilon: float) -> int:
        """ε-greedy per block: each sensor explores on its own with probability ``epsilon``."""
        values = self.q[state].tolist()
        cells = []
        for (a, b), columns in zip(self._spans, self._columns, strict=True):
            if epsilon > 0.0 and self.rng.random() < epsilon:
                cells.append(int(self.rng.integers(b - a)))
            else:
                cells.append(self._best(values, columns) - a)
        return self.encode(cells)
