"""Where a table has learned, and the nearest learned state to one it has not.

``exploit`` (and ``learn`` on a loaded table, between its epsilon draws) acts on what the
table learned; in a state with fewer than ``min_updates`` updates it acts as in the nearest
learned state (``StateSpace.distances``; the most updated among equals). A trained table has
learned in a few percent of the 3645 states, and a world it was not trained on reaches
combinations it never saw: holding the configuration there froze whatever the previous scene
had left (issue #7).
"""

from __future__ import annotations

import numpy as np

from respecd.control.qlearning import QTable
from respecd.control.state import StateSpace


class LearnedStates:
    """The learned states of one table version (its update count), built once; the nearest
    learned state is remembered per state asked about, so a decision pays a set lookup."""

    def __init__(self, table: QTable, states: StateSpace, min_updates: int) -> None:
        self.version = table.updates
        self._states = states
        updates = table.state_updates()
        self._rows = np.flatnonzero(updates >= min_updates)
        self._updates = updates[self._rows]
        self._known = frozenset(self._rows.tolist())
        self._grid = np.array([states.unindex(int(s)) for s in self._rows], dtype=np.int64).reshape(
            len(self._rows), len(states.dims))
        self._nearest: dict[int, int | None] = {}

    def at(self, version: int) -> LearnedStates:
        """The same learned states, valid for a later table version (an update that left them as they were)."""
        self.version = version
        return self

    def __contains__(self, state: int) -> bool:
        return state in self._known

    def nearest(self, state: int) -> int | None:
        """The learned state closest to ``state``; None when nothing is learned."""
        if state not in self._nearest:
            if self._rows.size == 0:
                self._nearest[state] = None
            else:
                distance = self._states.distances(self._states.unindex(state), self._grid)
                closest = distance == distance.min()
                self._nearest[state] = int(self._rows[closest][np.argmax(self._updates[closest])])
        return self._nearest[state]
