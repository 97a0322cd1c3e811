"""Policy training: Q-learning episodes over randomized scenario sequences, on cached outcomes.

An episode is the simulator's scenarios (the paper's six, then behind-curtain) in a random
order, each for a random duration (whole decision periods between ``min_s`` and ``max_s``)
on a world seed drawn from the training pool ``0 .. seeds-1`` (the benchmark uses seeds
from ``EVAL_SEED`` on, never trained on).

One Q-table is shared by all episodes; each episode starts a fresh controller around it
(window, previous state and action reset, as a daemon restart would) and ε keeps decaying
across episodes. The profile's reward, learning rate, discount and ε schedule are used as
they are: the training loop changes how fast outcomes are obtained, not what is learned.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from respecd.control.qlearning import QTable
from respecd.lab.experiment.rollout import Piece, Rollout, controller_for
from respecd.sim.config import SCENARIOS

if TYPE_CHECKING:
    from respecd.config import Profile

EVAL_SEED = 1000  # benchmark worlds start here; training seeds stay below


@dataclass(frozen=True)
class TrainSettings:
    episodes: int = 40
    seeds: int = 4  # training world seeds 0 .. seeds-1
    min_s: float = 10.0
    max_s: float = 30.0
    seed: int = 0  # episode sampling (order, durations, seeds)
    max_minutes: float | None = None  # stop early (the table so far is kept)
    scenarios: tuple[str, ...] = SCENARIOS


@dataclass
class TrainResult:
    table: QTable
    layout: dict[str, Any]
    episode_reward: list[float] = field(default_factory=list)  # mean reward per decision
    episode_epsilon: list[float] = field(default_factory=list)
    decisions: int = 0
    seconds: float = 0.0


def episode_pieces(settings: TrainSettings, rng: np.random.Generator, period: float) -> list[Piece]:
    order = rng.permutation(len(settings.scenarios))
    pieces = []
    for i in order:
        steps = int(rng.integers(int(settings.min_s / period), int(settings.max_s / period) + 1))
        pieces.append(Piece(settings.scenarios[i], int(rng.integers(settings.seeds)), max(1, steps) * period))
    return pieces


def train(profile: Profile, rollout: Rollout, settings: TrainSettings, table: QTable | None = None,
          on_episode: Callable[[int, TrainResult], None] | None = None,
          history: list[float] | None = None) -> TrainResult:
    """Run the episodes; returns the shared table and the learning curve.

    ``history``: mean rewards of earlier episodes of a resumed table (kept on the curve).
    """
    first = controller_for(profile, "learn")
    shared = table if table is not None else first.table
    assert shared is not None
    result = TrainResult(shared, first.layout(), list(history or []), [float("nan")] * len(history or []))
    rng = np.random.default_rng([settings.seed, 17])
    start = time.monotonic()
    for episode in range(settings.episodes):
        controller = controller_for(profile, "learn")
        controller.table = shared
        pieces = episode_pieces(settings, rng, rollout.period)
        records = rollout.run(controller, pieces)
        rewards = [r.decision.reward for r in records[1:]]  # the first step has no previous action to score
        result.episode_reward.append(float(np.mean(rewards)) if rewards else 0.0)
        result.episode_epsilon.append(shared.epsilon)
        result.decisions += len(records)
        result.seconds = time.monotonic() - start
        if on_episode is not None:
            on_episode(episode, result)
        if settings.max_minutes is not None and result.seconds > 60 * settings.max_minutes:
            break
    return result


def conservative(table: QTable, keep: int | None = 0, margin: float = 1.0) -> int:
    """Make exploiting never take an action it has no evidence for; returns entries changed.

    A never-tried (state, action) still holds its initial value (optimistic 1.0), which
    beats every learned value when rewards are negative, so a greedy policy would pick the
    untried action in every state that has one. Here an untried action gets its state's
    lowest learned value minus ``margin``; in a state never visited at all, ``keep`` (the
    moves-mode hold action; None in product mode) is preferred: hold the configuration.
    """
    tried = table.visits > 0
    changed = 0
    for s in np.flatnonzero(~tried.all(axis=1)):
        row = tried[s]
        low = float(table.q[s, row].min()) - margin if row.any() else -margin
        table.q[s, ~row] = low
        changed += int((~row).sum())
        if not row.any() and keep is not None:
            table.q[s, keep] = low + margin / 2
    return changed


def save_curve(result: TrainResult, path: Path, title: str = "respecd train-policy") -> Path:
    """Learning curve: mean reward per decision for each episode, with a moving average."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rewards = np.asarray(result.episode_reward)
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=110)
    x = np.arange(1, len(rewards) + 1)
    ax.plot(x, rewards, ".", color="#7a9cc6", label="episode")
    if len(rewards) >= 3:
        k = max(3, len(rewards) // 10)
        smooth = np.convolve(rewards, np.ones(k) / k, mode="valid")
        ax.plot(x[k - 1:], smooth, "-", color="#1f4e8c", label=f"moving mean ({k})")
    ax.set_xlabel("episode")
    ax.set_ylabel("mean reward per decision")
    ax2 = ax.twinx()
    ax2.plot(x, result.episode_epsilon, "--", color="#c67a3a", lw=1, label="ε")
    ax2.set_ylabel("ε", color="#c67a3a")
    ax.set_title(title)
    handles = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    fig.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.0, 0.9), fontsize=8)  # outside the data
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
    return path
