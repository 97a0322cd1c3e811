"""The daemon's control path and the training path decide identically on the same outcomes.

Training (``Rollout``, what ``train-policy`` and ``bench scenarios`` run) feeds cached detector
outcomes into the control loop; the daemon feeds percepts through its ``ControllerStage``,
whose decisions go to real simulated drivers. Here a training rollout is recorded — every
sample the loop was given, when, and the load it read at each decision — and the same
recording is fed to a ``ControllerStage`` built as the session builds it, over ``SimDriver``s,
on a lockstep clock. A learning controller with the same seed must then take every decision
the trainer took: same times, states, actions, rewards, Q-values and applied configurations.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from respecd.config import load_profile
from respecd.control.features import Sample
from respecd.control.loop import ControlLoop
from respecd.control.probe import SystemSample
from respecd.messages import Decision
from respecd.replay.lockstep import LockstepClock, LockstepLoop

TINY_MODEL = {"rgb_widths": [4, 8, 8, 16, 16], "aux_widths": [4, 8, 8, 16, 16], "neck_widths": [8, 16, 16],
              "reg_max": 4}


@dataclass
class Recording:
    """What one training run gave its control loop."""

    samples: list[Sample] = field(default_factory=list)
    loads: list[SystemSample] = field(default_factory=list)
    decisions: list[Decision] = field(default_factory=list)

    def attach(self, loop: ControlLoop) -> None:
        loop.on_sample.append(self.samples.append)
        loop.on_decision.append(self.decisions.append)
        probe = loop.probe
        assert probe is not None

        class Recorded:
            async def read(inner) -> SystemSample:  # noqa: N805 (the probe's own self is the outer one)
                sample = await probe.read()
                self.loads.append(sample)
                return sample

        loop.probe = Recorded()


class Replayed:
    """The recorded load readings, in order: the daemon's probe for this test."""

    def __init__(self, loads: list[SystemSample]) -> None:
        self.loads = list(loads)

    async def read(self) -> SystemSample:
        return self.loads.pop(0)


def _profile(tmp_path: Path) -> Any:
    from importlib import resources

    doc = yaml.safe_load((resources.files("respecd.profiles") / "sim-rover.yaml").read_text())
    doc["perception"] = {"model": TINY_MODEL, "torch_threads": 1}
    doc["controller"] = {"min_dwell_s": 0, "seed": 7,
                         "actions": {"rgb_resolutions": [[640, 360]], "rate_levels_hz": [1, 10, 30]}}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(doc))
    return load_profile(path)


def _train(profile: Any) -> tuple[Recording, dict[str, Any], Any]:
    from respecd.lab.experiment import latency as lat
    from respecd.lab.experiment.rollout import Piece, Rollout, controller_for
    from respecd.lab.experiment.setup import load_detector, make_evaluator

    detector = load_detector(profile, random_init=True)
    rollout = Rollout(profile, make_evaluator(detector, profile, use_cache=False), {}, samples_per_s=2.0)
    pieces = [Piece("good-light-moving", 0, 4.0), Piece("poor-light-static", 1, 3.0)]
    world = rollout.world(pieces[0])
    rollout.latency = lat.measure(detector, lat.sim_frames(world, rollout.evaluator.inputs), [(640, 360)], 1)
    controller = controller_for(profile, "learn")
    recording = Recording()
    records = rollout.run(controller, pieces, attach=recording.attach)
    assert len(records) == len(recording.decisions) == 7
    return recording, rollout.starting(controller_for(profile, "learn")), controller


async def _daemon_path(profile: Any, recording: Recording, tmp_path: Path) -> list[Decision]:
    from respecd.control.stage import ControllerStage
    from respecd.drivers.base import DriverContext
    from respecd.drivers.sim import SimDriver
    from respecd.queues import DropOldestQueue

    clock = LockstepClock(0.0)
    context = DriverContext(seed=0, simulation=profile.simulation)
    drivers = {s.name: SimDriver(s, clock, context) for s in profile.sensors}
    config = profile.controller.model_copy(update={"policy": "learn", "system_probe": False})
    stage = ControllerStage(config, profile, drivers, clock, tmp_path / "state")
    stage.loop.probe = Replayed(recording.loads)
    decisions: list[Decision] = []
    stage.on_decision.append(decisions.append)

    async def percepts_as_recorded() -> None:
        for sample in recording.samples:
            await clock.sleep_until(sample.t)
            stage.loop.add(sample)

    tasks = [asyncio.create_task(stage.run(DropOldestQueue(4, "percepts")), name="controller"),
             asyncio.create_task(percepts_as_recorded(), name="percepts")]
    await clock.run(recording.decisions[-1].t)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    return decisions


@pytest.mark.slow
def test_the_daemon_and_the_trainer_take_the_same_decisions(tmp_path: Path) -> None:
    profile = _profile(tmp_path)
    recording, start, _ = _train(profile)
    # the daemon's sensors start where the trainer's simulated ones did (its profile says so)
    sensors = [s.model_copy(update={"rate_hz": start[s.name].rate_hz, "resolution": start[s.name].resolution,
                                    "mode": start[s.name].mode}) for s in profile.sensors]
    profile = profile.model_copy(update={"sensors": sensors})
    with asyncio.Runner(loop_factory=LockstepLoop) as runner:
        daemon = runner.run(_daemon_path(profile, recording, tmp_path))
    assert len(daemon) == len(recording.decisions)
    for ours, theirs in zip(daemon, recording.decisions, strict=True):
        assert ours.t == pytest.approx(theirs.t, abs=1e-9)
        assert (ours.state, ours.action, ours.reward, ours.q_values) == (theirs.state, theirs.action, theirs.reward,
                                                                         theirs.q_values)
        assert ours.configs == theirs.configs  # what the sim drivers answered = what the trainer's clamp said
    assert len({d.action for d in daemon}) > 1  # the controller moved: the agreement is not trivial
