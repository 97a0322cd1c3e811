"""The perception stage: bundles in, percepts out, one worker thread, attribution cadence."""

from __future__ import annotations

import asyncio
import os
import sys
import threading

import numpy as np
import pytest
import torch

from respecd.clock import ManualClock
from respecd.messages import Bundle, Frame, Health, SyncStats
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.detector import FusionDetector
from respecd.perception.model import FusionNet
from respecd.perception.stage import PerceptionStage
from respecd.queues import DropOldestQueue

TINY = ModelSpec(rgb_widths=(8, 8, 16, 16, 16), aux_widths=(8, 8, 8, 8, 8), neck_widths=(16, 16, 16))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


SYNC = SyncStats(rate_hz=10.0, jitter_ms=0.0, stale_ratio=0.0, health=Health.GOOD)


class RecordingDetector(FusionDetector):
    """The real detector, noting which thread ran each call and whether it attributed."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.calls: list[tuple[str, bool]] = []

    def infer(self, frames, attribute):
        self.calls.append((threading.current_thread().name, attribute))
        return super().infer(frames, attribute)


def _bundle(t: float, seq: int) -> Bundle:
    rgb = np.random.default_rng(seq).integers(0, 255, (96, 160, 3), dtype=np.uint8)
    thermal = np.full((30, 40), 30000, np.uint16)
    frames = {"rgb": Frame("rgb", t, seq, rgb), "thermal": Frame("thermal", t, seq, thermal)}
    return Bundle(t=t, frames=frames, sync=SYNC, seq=seq)


async def test_stage_runs_detector_in_one_worker_thread_at_the_cadence() -> None:
    torch.manual_seed(0)
    config = PerceptionConfig(model=TINY, score_threshold=0.0, max_detections=5, attribution_every_s=1.0)
    detector = RecordingDetector(FusionNet(TINY), config)
    stage = PerceptionStage(config, calibration=None, clock=ManualClock(), detector=detector)
    bundles: DropOldestQueue[Bundle] = DropOldestQueue(4)
    percepts = DropOldestQueue(8)
    shown = []  # the status line's percept after each inference
    stage.on_inference.append(lambda _: shown.append(stage.last))
    task = asyncio.create_task(stage.run(bundles, percepts), name="perception")
    received = []
    for seq, t in enumerate((0.0, 0.3, 0.6, 1.05, 1.2)):
        if seq == 4:
            stage.request_attribution()  # the controller asks: the next bundle is attributed
        bundles.put(_bundle(t, seq))
        received.append(await asyncio.wait_for(percepts.get(), timeout=30))
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)

    assert [p.bundle.seq for p in received] == [0, 1, 2, 3, 4]
    assert [p.t for p in received] == [0.0, 0.3, 0.6, 1.05, 1.2]
    assert [a for _, a in detector.calls] == [True, False, False, True, True]
    assert {name for name, _ in detector.calls} == {"perception_0"}
    assert received[0].contributions is not None and received[1].contributions is None
    assert stage.last is received[-1] and stage.processed == 5
    assert stage.last.contributions is not None
    # RGB and thermal on (no radar frame): dependence and sufficiency of each come with the contributions
    assert set(received[0].dependence) == set(received[0].sufficiency) == {"rgb", "thermal", "radar"}
    assert received[0].sufficiency["radar"] == 0.0 and received[1].dependence is None
    assert shown[2].dependence == received[0].dependence and shown[2].sufficiency == received[0].sufficiency
    assert all(p.latency > 0 for p in received)
    assert not any(t.name.startswith("perception") for t in threading.enumerate())


async def test_with_a_controller_attribution_runs_only_when_asked() -> None:
    """The controller asks once per decision window: no attribution the cadence would add."""
    config = PerceptionConfig(model=TINY, score_threshold=0.0, max_detections=5, attribution_every_s=0.5)
    detector = RecordingDetector(FusionNet(TINY), config)
    stage = PerceptionStage(config, calibration=None, clock=ManualClock(), detector=detector)
    stage.attribute_on_request()
    bundles: DropOldestQueue[Bundle] = DropOldestQueue(4)
    percepts = DropOldestQueue(8)
    task = asyncio.create_task(stage.run(bundles, percepts), name="perception")
    for seq, t in enumerate((0.0, 0.6, 1.2, 1.8, 2.4, 3.0)):
        if seq == 3:
            stage.request_attribution()
        bundles.put(_bundle(t, seq))
        await asyncio.wait_for(percepts.get(), timeout=30)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert [a for _, a in detector.calls] == [True, False, False, True, False, False]


async def test_stage_with_bad_weights_fails_to_load(tmp_path) -> None:
    from respecd.errors import ConfigError

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not torch")
    stage = PerceptionStage(PerceptionConfig(weights=str(bad)), calibration=None, clock=ManualClock())  # no I/O yet
    with pytest.raises(ConfigError, match="bad.pt"):
        await stage.load()


async def test_bundles_without_a_new_detector_input_are_skipped() -> None:
    """An IMU keeps the synchronizer at 30 Hz; the detector runs only on new RGB/aux frames."""
    config = PerceptionConfig(model=TINY, score_threshold=0.0, max_detections=5)
    detector = RecordingDetector(FusionNet(TINY), config)
    stage = PerceptionStage(config, calibration=None, clock=ManualClock(), detector=detector)
    bundles: DropOldestQueue[Bundle] = DropOldestQueue(8)
    percepts = DropOldestQueue(8)
    first = _bundle(0.0, 0)
    imu = Frame("imu", 0.033, 1, np.zeros(6, np.float32))
    repeat = Bundle(t=0.033, frames={**first.frames, "imu": imu}, sync=SYNC, seq=1)  # same RGB and thermal
    for bundle in (first, repeat, _bundle(0.066, 2)):
        bundles.put(bundle)
    task = asyncio.create_task(stage.run(bundles, percepts), name="perception")
    received = [await asyncio.wait_for(percepts.get(), timeout=30) for _ in range(2)]
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert [p.bundle.seq for p in received] == [0, 2]
    assert len(detector.calls) == 2 and stage.skipped == 1


class NiceNotingDetector(FusionDetector):
    """The real detector, noting the nice value of the thread each call ran on."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.nice: list[int] = []

    def infer(self, frames, attribute):
        self.nice.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))
        return super().infer(frames, attribute)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
@pytest.mark.parametrize("lockstep", [False, True], ids=["live", "lockstep-replay"])
async def test_the_detector_yields_to_the_loop_live_but_not_where_the_replay_clock_waits_for_it(lockstep) -> None:
    """Live, the loop keeps time and the detector only has to keep up (nice +10); in a lockstep
    replay (a latency model) the log's clock stands still until the detector is done."""
    from respecd.replay.latency import LatencyModel

    config = PerceptionConfig(model=TINY, score_threshold=0.0, max_detections=5, attribution_every_s=10.0)
    detector = NiceNotingDetector(FusionNet(TINY), config)
    clock = ManualClock()
    stage = PerceptionStage(config, calibration=None, clock=clock, detector=detector,
                            latency_model=LatencyModel() if lockstep else None)
    bundles: DropOldestQueue[Bundle] = DropOldestQueue(4)
    percepts = DropOldestQueue(8)
    task = asyncio.create_task(stage.run(bundles, percepts), name="perception")
    bundles.put(_bundle(0.0, 0))
    while not detector.nice:
        clock.advance(0.05)  # the modelled latency passes on the log's clock
        await asyncio.sleep(0.01)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    own = os.getpriority(os.PRIO_PROCESS, 0)
    assert detector.nice[0] == (own if lockstep else min(19, own + 10))

def test_shared_detectors_load_once_and_start_each_session_afresh(monkeypatch: pytest.MonkeyPatch) -> None:
    """A fleet worker evaluates many logs: one checkpoint load, and no scene score carried over."""
    from respecd.perception.stage import share_detectors

    loads: list[str] = []

    def load(config, calibration=None, exports=None):
        loads.append(config.weights)
        return FusionDetector(FusionNet(TINY), config)

    monkeypatch.setattr(FusionDetector, "load", staticmethod(load))
    config = PerceptionConfig(model=TINY, weights="tiny.pt")
    with share_detectors():
        first = PerceptionStage(config, calibration=None, clock=ManualClock())._load()
        first.scores.update(5.0, {"rgb": 0.9, "thermal": 0.1})  # what one session leaves behind
        second = PerceptionStage(config, calibration=None, clock=ManualClock())._load()
        assert second is first and loads == ["tiny.pt"]
        assert second.scores.value == second.scores.uniform and second.scores.update(1.0, None) == second.scores.uniform
    third = PerceptionStage(config, calibration=None, clock=ManualClock())._load()  # outside: loaded anew
    assert third is not first and len(loads) == 2


async def test_a_shared_detector_waits_for_the_last_sessions_inference(monkeypatch: pytest.MonkeyPatch) -> None:
    """A stopped session's inference may still run (a loaded machine, past the stop's grace): the
    next session on the shared detector starts only once it is done, from a fresh scene score."""
    import respecd.perception.stage as stage_module
    from respecd.perception.stage import share_detectors

    release, running = threading.Event(), threading.Event()

    class SlowDetector(FusionDetector):
        def infer(self, frames, attribute):
            running.set()
            release.wait(30)
            self.scores.update(5.0, {"rgb": 0.9, "thermal": 0.1})  # what its attribution leaves behind
            return super().infer(frames, attribute)

    config = PerceptionConfig(model=TINY, weights="tiny.pt", score_threshold=0.0)
    monkeypatch.setattr(FusionDetector, "load",
                        staticmethod(lambda c, calibration=None, exports=None: SlowDetector(FusionNet(TINY), c)))
    monkeypatch.setattr(stage_module, "SHUTDOWN_TIMEOUT_S", 0.05)
    with share_detectors():
        first = PerceptionStage(config, calibration=None, clock=ManualClock())
        bundles: DropOldestQueue[Bundle] = DropOldestQueue(4)
        bundles.put(_bundle(0.0, 0))
        task = asyncio.create_task(first.run(bundles, DropOldestQueue(4)), name="perception")
        await asyncio.to_thread(running.wait, 30)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)  # stopped; its inference runs on
        second = PerceptionStage(config, calibration=None, clock=ManualClock())
        loading = asyncio.ensure_future(asyncio.to_thread(second._load))
        try:
            await asyncio.sleep(0.3)
            assert not loading.done()  # waiting for the straggler
        finally:
            release.set()
        detector = await asyncio.wait_for(loading, 30)
    assert detector.scores.value == detector.scores.uniform


def test_an_input_prepared_ahead_is_used_only_for_the_very_frames_it_was_made_from() -> None:
    """The same frame numbers are not enough (a frame re-made at another resolution keeps them):
    only the frame objects prepared ahead get that input, which is what the detector would make."""
    from respecd.perception.ahead import InputPreparer

    config = PerceptionConfig(model=TINY, score_threshold=0.0)
    detector = FusionDetector(FusionNet(TINY), config)
    stage = PerceptionStage(config, calibration=None, clock=ManualClock(), detector=detector)
    stage._preparer = preparer = InputPreparer(detector.prepare, stage._inputs)
    queued: DropOldestQueue[Bundle] = DropOldestQueue(4)
    bundle = _bundle(0.1, 1)
    queued.put(bundle)
    try:
        stage._prepare_next(queued)
        prepared = preparer.take(dict(bundle.frames))
        assert prepared is not None and preparer.take(dict(bundle.frames)) is None  # taken once
        here, ahead = detector.prepare(dict(bundle.frames)), prepared.result()
        assert ahead.size == here.size and ahead.tensor.tobytes() == here.tensor.tobytes()
        assert ahead.presence.tobytes() == here.presence.tobytes()
        rgb = bundle.frames["rgb"]
        resized = Frame("rgb", rgb.t, rgb.seq, np.zeros((48, 80, 3), np.uint8))
        for taken in ({**bundle.frames, "rgb": resized}, {"rgb": rgb}, dict(_bundle(0.2, 2).frames)):
            stage._prepare_next(queued)
            assert preparer.take(taken) is None
    finally:
        preparer.shutdown()


class _GridSpy(FusionDetector):
    """Records the grid of every input it prepares (in whichever thread)."""

    def __init__(self, *args, **kwargs) -> None:  # noqa: ANN002, ANN003
        super().__init__(*args, **kwargs)
        self.grids: list[tuple[int, int]] = []

    def prepare(self, frames, rgb_size=None):  # noqa: ANN001, ANN201
        aligned = super().prepare(frames, rgb_size)
        self.grids.append(aligned.size)
        return aligned


def test_a_bundle_without_rgb_is_detected_on_the_grid_of_the_bundles_before_it() -> None:
    """The preparer's thread and the detector's both run the aligner; that the preparer aligned the
    next bundle's RGB frame first must not move an earlier RGB-less bundle onto that frame's grid
    (one log replayed twice at --speed max gave two timelines)."""
    from respecd.perception.ahead import InputPreparer

    config = PerceptionConfig(model=TINY, score_threshold=0.0)
    detector = _GridSpy(FusionNet(TINY), config)
    stage = PerceptionStage(config, calibration=None, clock=ManualClock(), detector=detector)
    stage._preparer = preparer = InputPreparer(detector.prepare, stage._inputs)
    stage._rgb_grid = first = detector.first_rgb_size()
    no_rgb = {"thermal": _bundle(0.1, 1).frames["thermal"]}
    later = dict(_bundle(0.2, 2).frames)  # RGB at 160x96
    assert first != (160, 96)
    try:
        preparer.start(later, stage._grid_for(later))
        preparer._ahead.input.result()  # the race's bad order: the later RGB frame aligned first
        grid = stage._rgb_grid = stage._grid_for(no_rgb)
        stage._infer(no_rgb, False, None, grid)
        assert detector.grids == [(160, 96), first]
        grid = stage._rgb_grid = stage._grid_for(later)
        stage._infer(later, False, preparer.take(later), grid)
        grid = stage._rgb_grid = stage._grid_for(no_rgb)
        stage._infer(no_rgb, False, None, grid)
        assert detector.grids[-1] == (160, 96)  # after an RGB frame, its size
    finally:
        preparer.shutdown()
