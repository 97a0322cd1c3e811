"""Simulated sensors: one driver instance per modality, all looking at one shared, seeded world.

Frames come on the grid k / rate of the injected clock (no drift, independent of start
time) and are stamped with their grid time, so a run on a ``ManualClock`` is deterministic.
Each frame's noise comes from ``default_rng([seed, modality, seq])``. Rendering runs inline when it is measured to be
tiny (< 0.2 ms CPU: the IMU) and in the driver's own worker thread otherwise, so the event
loop never waits on a render or on a scenario's background being built.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Literal

import numpy as np
import structlog
from pydantic import Field

from respecd.clock import Clock
from respecd.drivers.base import Capabilities, Driver, DriverConfigBase, DriverContext, clamp_request
from respecd.errors import DriverError
from respecd.messages import MODALITIES, Frame, SensorConfig
from respecd.priority import lower_thread_priority
from respecd.sim.camera import ground_truth
from respecd.sim.radar_model import radar_figures
from respecd.sim.render import (
    LEPTON_NATIVE,
    render_depth,
    render_imu,
    render_lepton,
    render_radar,
    render_rgb,
    rgb_exposure,
)
from respecd.sim.state import SceneState
from respecd.sim.world import World, make_world

log = structlog.get_logger(__name__)

# renders above this go to the worker thread (a hand-off costs the loop ~0.1 ms). Not more: an
# inline render's numpy calls each let another thread take the GIL, and the loop then waits
# up to the switch interval to get it back, a few times per render (bench pipeline's stalls)
INLINE_BUDGET_S = 0.0002
_COST_SMOOTHING = 0.2  # EWMA weight of the newest render time

# The FLIR One Pro's Lepton: 160x120 at about 8-9 frames per second (SENSORS.md section 3);
# its 320x240 is an upscale. The simulated camera keeps to the same limits.
THERMAL_MAX_RATE_HZ = 9.0

CAPABILITIES: dict[str, Capabilities] = {
    "rgb": Capabilities("rgb", resolutions=((1280, 720), (960, 540), (640, 360))),
    "thermal": Capabilities("thermal", resolutions=((320, 240), LEPTON_NATIVE), max_rate_hz=THERMAL_MAX_RATE_HZ,
                            upscaled=((320, 240),)),
    "depth": Capabilities("depth", resolutions=((848, 480), (640, 480), (424, 240))),
    "radar": Capabilities("radar", modes=("range", "velocity")),
    "imu": Capabilities("imu"),
}


class SimConfig(DriverConfigBase):
    driver: Literal["sim"] = Field(description="Simulated sensor looking at the profile's `simulation:` world.")
    render_in_thread: Literal["auto", "always", "never"] = Field(
        "auto", description="Render in a worker thread: auto = when a render is measured to take over 1 ms of CPU."
    )


class SimDriver(Driver):
    """A simulated sensor that honours every setter (rate, resolution, radar mode, enable)."""

    key = "sim"

    def __init__(self, config: SimConfig, clock: Clock, context: DriverContext | None = None) -> None:
        super().__init__(config, clock, context)
        self.sim_config = config
        self.applied = clamp_request(self.capabilities, config.initial_request())
        self._world: World | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._stopped = asyncio.Event()
        self._wake = asyncio.Event()  # set by apply() and stop(): a sleeping frames() re-reads the setting
        self._cost_s: dict[tuple, float] = {}  # measured render time per setting
        self._segment = -1  # the scenario segment last rendered (a new one builds backgrounds)
        self._modality_index = MODALITIES.index(self.modality)

    @property
    def capabilities(self) -> Capabilities:
        return CAPABILITIES[self.modality]

    @property
    def world(self) -> World:
        if self._world is None:
            raise DriverError(f"{self.name}: start() the simulated sensor before reading frames")
        return self._world

    async def start(self) -> None:
        if self._world is not None and not self._stopped.is_set():
            return
        self._world = make_world(self.context.simulation, self.context.seed)
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"sim-{self.name}",
                                            initializer=lower_thread_priority)
        self._stopped = asyncio.Event()
        log.info("sim_start", sensor=self.name, modality=self.modality, seed=self._world.seed)

    async def stop(self) -> None:
        if self._stopped.is_set():
            return
        self._stopped.set()
        self._wake.set()
        if self._executor is not None:
            self._executor.shutdown(wait=False)  # the worker ends after its render; frames() then returns
            self._executor = None
        if self._world is not None:
            log.info("sim_stop", sensor=self.name, frames=self.health.frames)

    async def apply(self, request: SensorConfig) -> SensorConfig:
        applied = clamp_request(self.capabilities, replace(request, modality=self.modality))
        if applied != self.applied:
            log.info(
                "sim_apply",
                sensor=self.name,
                rate_hz=applied.rate_hz,
                resolution=applied.resolution,
                mode=applied.mode,
                enabled=applied.enabled,
                notes=list(applied.notes),
            )
        self.applied = applied
        self._wake.set()
        return applied

    async def frames(self) -> AsyncIterator[Frame]:
        world = self.world
        seq, last_t, last_rate = 0, None, 0.0
        waker: asyncio.Future | None = None  # one waiter on _wake, kept across frames until it fires
        sleeper: asyncio.Future | None = None
        try:
            while not self._stopped.is_set():
                if waker is None or waker.done():
                    self._wake.clear()
                    waker = asyncio.ensure_future(self._wake.wait())
                if not self.applied.enabled:
                    await waker  # until apply() or stop()
                    last_t = None  # a re-enabled sensor starts on the next slot from now
                    continue
                due = self._next_due(last_t, last_rate, self.applied.rate_hz)
                sleeper = asyncio.ensure_future(self.clock.sleep_until(due))
                await asyncio.wait((sleeper, waker), return_when=asyncio.FIRST_COMPLETED)
                if not sleeper.done() or self._stopped.is_set():
                    continue  # woken by apply() or stop(): re-read the setting
                frame = await self._frame(world, due, seq, self.applied)
                if frame is None or self._stopped.is_set():
                    return  # stopped while the frame rendered
                yield frame  # the supervisor counts it in health
                seq, last_t, last_rate = seq + 1, due, self.applied.rate_hz
        finally:
            for future in (waker, sleeper):
                if future is not None and not future.done():
                    future.cancel()

    def _next_due(self, last_t: float | None, last_rate: float, rate: float) -> float:
        """The next slot k / rate of the world-time grid after the last frame.

        Slots are anchored at t = 0, so a sensor's frame times never drift and do not depend
        on when it started (the newest frame at time t is floor(t * rate) / rate). After a
        rate change, the first slot of the new grid from now. A consumer that fell a whole
        period behind skips to the newest slot (the skipped ones count as drops).
        """
        now = self.clock.now()
        from_now = math.ceil(now * rate - 1e-9)
        if last_t is None:
            return from_now / rate
        k = math.floor(last_t * rate + 1e-9) + 1
        if rate != last_rate:
            return max(k, from_now) / rate
        newest = math.floor(now * rate + 1e-9)
        if newest > k:
            self.health.drops += newest - k
            k = newest
        return k / rate

    async def _frame(self, world: World, t: float, seq: int, applied: SensorConfig) -> Frame | None:
        state = world.state_at(t)
        rng = np.random.default_rng([world.seed, self._modality_index, seq])
        key = self._key(applied)
        job = self._job(state, applied, rng)
        if self._use_thread(key, state):
            executor = self._executor
            if executor is None:
                return None
            data, meta, cost = await asyncio.get_running_loop().run_in_executor(executor, _timed, job)
        else:
            data, meta, cost = _timed(job)
        previous = self._cost_s.get(key, cost)
        self._cost_s[key] = previous + _COST_SMOOTHING * (cost - previous)
        self._segment = state.segment
        meta.update(scenario=state.scenario, light=state.light, segment=state.segment, render_s=cost)
        return Frame(self.modality, t, seq, data, meta)

    def _key(self, applied: SensorConfig) -> tuple:
        """What a render's cost depends on: resolution or mode (and the rate, for the radar's chirp)."""
        return applied.resolution, applied.mode, applied.rate_hz if self.modality == "radar" else None

    @property
    def render_cost_s(self) -> float | None:
        """Moving average of a render's CPU time at the current setting; None before the first."""
        return self._cost_s.get(self._key(self.applied))

    def _use_thread(self, key: tuple, state: SceneState) -> bool:
        mode = self.sim_config.render_in_thread
        if mode != "auto":
            return mode == "always"
        if state.segment != self._segment or key not in self._cost_s:
            return True  # a new scenario or setting builds cached backgrounds first: tens of ms
        return self._cost_s[key] > INLINE_BUDGET_S

    def _job(self, state: SceneState, applied: SensorConfig, rng: np.random.Generator) -> Callable[[], tuple]:
        """A closure that renders this modality (pure: safe in a worker thread)."""
        modality, res = self.modality, applied.resolution
        sim = self.world.config
        if modality == "rgb":
            assert res is not None, "an imager always has a resolution"
            max_exposure = min(1.0 / applied.rate_hz, sim.max_exposure_s)
            return lambda: (
                render_rgb(state, res, max_exposure, rng),
                {"gt": ground_truth(state, res), **rgb_exposure(state, res, max_exposure)},
            )
        if modality == "thermal":
            assert res is not None, "an imager always has a resolution"
            return lambda: _thermal_frame(state, res, rng)
        if modality == "depth":
            assert res is not None, "an imager always has a resolution"
            return lambda: (
                render_depth(state, res, rng),
                {"gt": ground_truth(state, res), "units": "mm", "valid_m": (0.3, 3.0)},
            )
        gt_res = (sim.rgb_intrinsics.width, sim.rgb_intrinsics.height)  # radar/IMU boxes: the RGB calibration
        if modality == "radar":
            figures = radar_figures(applied.mode, applied.rate_hz).as_dict()
            return lambda: (
                render_radar(state, applied.mode or "range", applied.rate_hz, rng),
                {"gt": ground_truth(state, gt_res), "gt_resolution": gt_res, "mode": applied.mode, "figures": figures},
            )
        return lambda: (
            render_imu(state, rng),
            {"gt": ground_truth(state, gt_res), "gt_resolution": gt_res, "ego_speed": state.ego_speed},
        )


def _thermal_frame(state: SceneState, size: tuple[int, int], rng: np.random.Generator) -> tuple:
    """The Lepton's 160x120 centikelvin frame, upscaled bilinearly when a larger size is set (as the FLIR driver)."""
    meta: dict = {"gt": ground_truth(state, size), "units": "cK", "kelvin_per_count": 0.01}
    if tuple(size) != LEPTON_NATIVE:
        meta["upscaled_from"] = LEPTON_NATIVE
    return render_lepton(state, size, rng), meta


def _timed(job: Callable[[], tuple]) -> tuple:
    start = time.thread_time()  # CPU time of this thread: preemption by other processes is not render cost
    data, meta = job()
    return data, meta, time.thread_time() - start
