"""``--replay LOG --record OUT.mcap`` and ``--replay LOG --foxglove [HOST:]PORT``: what the controller
would have done, as a log and live — the replayed sensors' frames as they would have been
configured, the percepts, the decisions and applied configurations.

The daemon's own recorder and live view do it, attached to the replay's session as an observer,
so the counterfactual log is a respecd log like any other (``log info``, ``--replay``, ``log
export``, Foxglove). It records the replay's profile (its sensors are replay drivers of the
source log) and an ``respecd.replay`` metadata record naming the source, the policy and the
seed, and it keeps the source's log times, so the two logs line up in Foxglove. At ``--speed
max`` the replay's clock is the log's and can run ahead of the encoder: the recorder then waits
for room instead of dropping a frame, so the log is complete.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import structlog

log = structlog.get_logger(__name__)


def observer(source: Any, record: str | None, foxglove: str | None, *, speed: str, seed: int,
             then: Callable[[Any], None] | None = None) -> Callable[[Any], None] | None:
    """What ``replay(observe=...)`` calls with the session: attach the recorder (log and/or live
    view), then ``then`` (another observer). None when neither output is asked for."""
    if record is None and foxglove is None:
        return then

    def attach(session: Any) -> None:
        from respecd.record import make_recorder

        profile = session.profile
        metadata = {"respecd.replay": {"source": source.path.name, "source_start_ns": str(source.start_ns),
                                       "policy": profile.controller.policy, "seed": str(seed), "speed": speed}}
        recorder = make_recorder(profile, record, session.clock, foxglove, lossless=speed == "max",
                                 origin=time_origin(source), metadata=metadata)
        assert recorder is not None  # a path or an address was given
        session.attach(recorder)
        if then is not None:
            then(session)

    return attach


def time_origin(source: Any) -> tuple[float, int] | None:
    """(session time, its log time in ns) of the source: a respecd log's recorded origin; a bag's
    first message (its frames' times count from there); None when the log did not record one."""
    if getattr(source, "topic_map", None) is not None:
        return 0.0, int(source.start_ns)
    recorded = (getattr(source, "metadata", None) or {}).get("respecd.session") or {}
    try:
        return float(recorded["clock_t0"]), int(recorded["epoch_ns_at_t0"])
    except (KeyError, ValueError):
        return None
