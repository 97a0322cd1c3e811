"""``respecd policy show FILE``: the learned policy as a readable table.

One row per visited state (named bins) with its best tried action (what ``--policy exploit``
does there), that action's Q-value, how often the state was updated and how many of its
actions have been tried, plus how much of the state space the robot has seen.
The file carries its own layout (factor bins, action names), so no profile is needed.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from respecd.argtypes import non_negative_int
from respecd.control.qlearning import block_spans, updates_per_state


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="policy_command", metavar="VERB", required=True)
    show = sub.add_parser("show", help="print the learned policy of a Q-table file")
    show.add_argument("file", type=Path, help="Q-table (.npz) from the state directory")
    show.add_argument("--limit", type=non_negative_int, default=40,
                      help="rows to print (default 40; 0 = every visited state)")
    show.add_argument("--sort", choices=("visits", "state", "q"), default="visits", help="row order (default visits)")


def main(args: argparse.Namespace) -> int:
    from respecd.control.persist import read_table

    meta, q, visits = read_table(args.file)
    print("\n".join(render(meta, q, visits, limit=args.limit, sort=args.sort)))
    return 0


def _unindex(index: int, dims: list[int]) -> list[int]:
    bins = []
    for d in reversed(dims):
        index, b = divmod(index, d)
        bins.append(b)
    return bins[::-1]


def render(meta: dict[str, Any], q: np.ndarray, visits: np.ndarray, limit: int = 40, sort: str = "visits") -> list[str]:
    """The lines ``policy show`` prints."""
    layout = meta["layout"]
    factors: list[str] = layout["states"]["factors"]
    bin_names: list[list[str]] = layout["states"]["bins"]
    actions: list[str] = layout["actions"]["names"]
    dims = [len(b) for b in bin_names]
    blocks = layout["actions"].get("blocks")
    state_visits = updates_per_state(visits, len(blocks) if blocks else 1)
    visited = np.flatnonzero(state_visits)
    n_states, n_actions = q.shape
    lines = [
        f"Q-table {meta.get('profile', '?')}: {n_states} states x {n_actions} actions, "
        f"{meta.get('updates', 0)} updates, epsilon {meta.get('epsilon', 0):.3f}, "
        f"fingerprint {meta.get('fingerprint')}",
        f"states visited: {visited.size} of {n_states} ({100 * visited.size / n_states:.1f} %); "
        f"state-action pairs tried: {int((visits > 0).sum())} of {q.size} ({100 * (visits > 0).mean():.1f} %)",
    ]
    followers = _followers(layout["actions"].get("space", {}).get("slots", []))
    if followers:
        lines.append(f"shared rate: {followers}")
    if visited.size == 0:
        return [*lines, "no state visited yet: nothing learned"]
    best_names, best_q = _best_tried(q[visited], visits[visited], actions, blocks)
    order = {"visits": np.argsort(-state_visits[visited], kind="stable"),
             "q": np.argsort(-best_q, kind="stable"),
             "state": np.arange(visited.size)}[sort]
    shown = order if limit <= 0 else order[:limit]
    rows = []
    for i in shown:
        bins = _unindex(int(visited[i]), dims)
        names = [bin_names[f][b] for f, b in enumerate(bins)]
        tried = int((visits[visited[i]] > 0).sum())
        rows.append([*names, best_names[i], f"{best_q[i]:.3f}", str(int(state_visits[visited[i]])),
                     f"{tried}/{n_actions}"])
    header = [*factors, "best action", "Q", "visits", "tried"]
    widths = [max(len(h), *(len(r[c]) for r in rows)) for c, h in enumerate(header)]
    lines.append("  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)).rstrip())
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    if len(shown) < visited.size:
        lines.append(f"({len(shown)} of {visited.size} visited states shown, sorted by {sort}; --limit 0 shows all)")
    return lines


def _followers(slots: list[dict[str, Any]]) -> str:
    """'flir, radar at cam's rate' for a table learned with ``actions.shared_rate`` ('' without)."""
    leaders: dict[str, list[str]] = {}
    for slot in slots:
        if "follows" in slot:
            leaders.setdefault(slot["follows"], []).append(slot["name"])
    return "; ".join(f"{', '.join(names)} at {leader}'s rate" for leader, names in leaders.items())


def _best_tried(q: np.ndarray, visits: np.ndarray, names: list[str],
                blocks: list[int] | None) -> tuple[list[str], np.ndarray]:
    """What exploit does per row: the best *tried* action (an untried one only has its initial
    value); in a factored table the best tried cell of each block, Q their mean."""
    masked = np.where(visits > 0, q, -np.inf)
    spans = block_spans(blocks) if blocks else [(0, q.shape[1])]
    picks = [masked[:, a:b].argmax(axis=1) + a for a, b in spans]
    labels = [" ".join(names[p[i]] for p in picks) for i in range(q.shape[0])]
    values = np.mean([q[np.arange(q.shape[0]), p] for p in picks], axis=0)
    return labels, values
