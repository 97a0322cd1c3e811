"""Tabular Watkins Q-learning with ε-greedy exploration: pure numpy, seedable.

    Q(s, a) ← Q(s, a) + lr · (r + discount · max_a' Q(s', a') − Q(s, a))

ε decays geometrically after every update down to ``epsilon_min``. Greedy ties are broken
at random (with the seeded generator), so a zero- or optimistically-initialised table does
not always pick action 0. ``visits`` counts updates per (state, action) for ``policy show``.
"""

from __future__ import annotations

import numpy as np

from respecd.control.config import Learning

SMALL_ROW = 64  # actions per state below which plain Python beats numpy per call


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
        return self.q.shape  # type: ignore[return-value]

    def update(self, state: int, action: int, reward: float, next_state: int) -> float:
        """One Watkins update; returns the TD error."""
        target = reward + self.learning.discount * self._row_max(next_state)
        error = target - float(self.q[state, action])
        self.q[state, action] += self.learning.learning_rate * error
        self.visits[state, action] += 1
        self.updates += 1
        self.epsilon = max(self.learning.epsilon_min, self.epsilon * self.learning.epsilon_decay)
        return error

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
