"""What a log teaches without a replay: the transitions its controller recorded.

Each decision the robot logged (``/respecd/decision``) holds the state it saw (bins), the
action it took, the reward of the previous action and that reward's terms. Consecutive
decisions of one log are the transitions ``(s, a, r', s')`` its learner made: what ``fleet
learn`` replays through one learner, and what ``fleet sweep`` re-weighs.

The layout (state and action spaces) is the one a replay of the log builds — the profile's,
with each sensor as its own driver offers it — so a log's transitions fit a table of any log
of the same profile; a log of another layout is reported, not learned from.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

from respecd.control.persist import fingerprint
from respecd.errors import ConfigError, InputError
from respecd.lab.fleet import worker
from respecd.lab.fleet.logs import LogRef, local_copy

DECISIONS = "/respecd/decision"


@dataclass(frozen=True)
class Step:
    """One logged decision: its state's index, the action taken, the reward it was given (of
    the previous action), that reward's terms, and per-sensor rewards where it recorded them."""

    state: int
    action: int
    reward: float
    terms: dict[str, float]
    motion: int | None  # the state's motion bin, when motion is a factor
    credit: tuple[float, ...] | None


@dataclass(frozen=True)
class LogSteps:
    """A log's decisions and what they are decisions of; ``error`` when it has none to give."""

    name: str
    start_ns: int = 0
    error: str | None = None
    profile: dict[str, Any] = field(default_factory=dict)
    layout: dict[str, Any] = field(default_factory=dict)
    steps: tuple[Step, ...] = ()
    timing: dict[str, Any] = field(default_factory=dict)

    @property
    def fingerprint(self) -> str:
        return fingerprint(self.layout)


def controller_for(session: Any, profile: dict[str, Any] | None) -> tuple[Any, Any]:
    """(the replay profile, a learning Controller with its layout) for an opened log, as a replay builds them."""
    from respecd.replay.profile import first_frames, replay_profile
    from respecd.replay.source import base_profile

    firsts = first_frames(session)
    if not firsts:
        raise InputError(f"{session.path}: the log holds no sensor frames")
    replayed = replay_profile(base_profile(profile, session), session, firsts, seed=0, lockstep=True, policy="learn")
    return replayed, learner(replayed)


def learner(replayed: Any) -> Any:
    """A learning Controller for a replay profile (a model, or its JSON): the layout its replay has."""
    from respecd.clock import ManualClock
    from respecd.config import Profile
    from respecd.control.controller import Controller
    from respecd.drivers import driver_class

    if isinstance(replayed, dict):
        replayed = Profile.model_validate(replayed)
    capabilities = {s.name: driver_class(s.driver)(s, ManualClock()).capabilities for s in replayed.sensors}
    return Controller.from_profile(replayed.controller, replayed, capabilities)


def steps_of(profile: dict[str, Any] | None, ref: LogRef) -> LogSteps:
    """A log's recorded decisions (a backend's task): never raises, an error is its reason."""
    from respecd.record.reader import open_log

    began = time.perf_counter()
    try:
        with local_copy(ref) as path:
            session = open_log(path, warn=False)
            replayed, controller = controller_for(session, profile)
            steps = tuple(_steps(session, controller))
            result = LogSteps(ref.name, session.start_ns, None, replayed.model_dump(mode="json"),
                              controller.layout(), steps)
    except (InputError, ConfigError, ValueError, KeyError) as err:
        text = "; ".join(str(p) for p in getattr(err, "problems", None) or [str(err)])
        result = LogSteps(ref.name, error=text.replace(ref.location, ref.name))
    timing = {"task_s": round(time.perf_counter() - began, 4), "worker": worker.task_done()}
    return replace(result, timing=timing)


def _steps(session: Any, controller: Any) -> list[Step]:
    states = controller.states
    motion = states.factors.index("motion") if "motion" in states.factors else None
    slots = [slot.name for slot in controller.space.slots]
    out = []
    for decision in session.json_messages(DECISIONS):
        bins = tuple(int(b) for b in decision["state"])
        terms = {k: float(v) for k, v in (decision.get("terms") or {}).items()}
        credit = tuple(terms[f"credit.{n}"] for n in slots) if all(f"credit.{n}" in terms for n in slots) else None
        out.append(Step(states.index(bins), int(decision["action"]), float(decision["reward"]), terms,
                        bins[motion] if motion is not None else None, credit))
    return out
