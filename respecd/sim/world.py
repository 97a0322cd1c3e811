"""The seeded world: scenarios in sequence, each a segment of ``scenario_duration_s``.

``World.state_at(t)`` is a pure function of (config, seed, t): segment ``i`` draws its
parameters from ``numpy.random.default_rng([seed, i])`` and is then evaluated in closed
form, so any sensor can ask for any time in any order and all see the same scene.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import OrderedDict
from dataclasses import replace

import numpy as np

from respecd.sim.config import SCENARIOS, SimulationConfig
from respecd.sim.scenarios import Segment, draw_segment
from respecd.sim.state import Occluder, Room, SceneState, Target

__all__ = [
    "SCENARIOS",
    "Occluder",
    "Room",
    "SceneState",
    "SimulationConfig",
    "Target",
    "World",
    "make_world",
]


class World:
    """Scripted scenes for one (config, seed); thread-safe, cheap per query."""

    def __init__(self, config: SimulationConfig, seed: int) -> None:
        self.config = config
        self.seed = int(config.seed if config.seed is not None else seed)
        self._segment = functools.lru_cache(maxsize=16)(self._draw)

    @property
    def duration_s(self) -> float:
        """Length of one pass through the scenario list (the world repeats after it when looping)."""
        return len(self.config.scenarios) * self.config.scenario_duration_s

    def locate(self, t: float) -> tuple[int, float]:
        """(segment index, seconds into that segment) for time ``t``."""
        d = self.config.scenario_duration_s
        t = max(0.0, t)
        index = int(t // d)
        if not self.config.loop:
            index = min(index, len(self.config.scenarios) - 1)
        return index, t - index * d

    def scenario_at(self, t: float) -> str:
        index, _ = self.locate(t)
        return self.config.scenarios[index % len(self.config.scenarios)]

    def _draw(self, index: int) -> Segment:
        name = self.config.scenarios[index % len(self.config.scenarios)]
        rng = np.random.default_rng([self.seed, index])
        return draw_segment(name, self.config, rng)

    def state_at(self, t: float) -> SceneState:
        """The scene at ``t`` seconds (t < 0 is treated as 0)."""
        index, local_t = self.locate(t)
        segment = self._segment(index)
        shift, ego_v, ego_a = segment.ego(local_t)
        floor_y = self.config.camera_height_m
        targets = []
        for w in segment.walkers:
            x, z, vx, vz = w.at(local_t)
            targets.append(
                Target(
                    id=w.id,
                    position=(x, floor_y - w.size[1] / 2, z - shift),
                    velocity=(vx, 0.0, vz - ego_v),
                    size=w.size,
                    temperature_k=w.temperature_k,
                    color=w.color,
                    speed_mps=math.hypot(vx, vz),
                )
            )
        occluders = tuple(_shifted(o, shift) for o in segment.occluders)
        room = segment.room
        return SceneState(
            t=max(0.0, t),
            scenario=segment.name,
            segment=index,
            scenario_t=local_t,
            light=segment.light,
            targets=tuple(targets),
            occluders=occluders,
            ego_speed=abs(ego_v),
            ego_accel=ego_a,
            camera_height=floor_y,
            room=room,
            intrinsics=self.config.rgb_intrinsics,
        )


def _shifted(occluder: Occluder, shift: float) -> Occluder:
    if shift == 0.0:
        return occluder
    x, y, z = occluder.center
    return replace(occluder, center=(x, y, z - shift))


_WORLDS: OrderedDict[tuple[str, int], World] = OrderedDict()
_WORLDS_LOCK = threading.Lock()
_WORLDS_KEPT = 16  # training samples many seeds; keep the cache bounded


def make_world(config: SimulationConfig | None, seed: int) -> World:
    """The shared world for (config, seed): every simulated sensor of a daemon gets the same one."""
    config = config if config is not None else SimulationConfig()
    key = (config.model_dump_json(), int(config.seed if config.seed is not None else seed))
    with _WORLDS_LOCK:
        world = _WORLDS.get(key)
        if world is None:
            world = World(config, seed)
            _WORLDS[key] = world
            while len(_WORLDS) > _WORLDS_KEPT:
                _WORLDS.popitem(last=False)
        _WORLDS.move_to_end(key)
        return world
