"""Runtimes besides torch (``perception.runtime``): every shipped checkpoint exported to ONNX gives the
same detections and contributions through ONNX Runtime and OpenVINO as through torch, in f32, on a fixed
set of simulated bundles (each sensor on, thermal off, RGB off, a 1280x720 frame). Each runtime's
tests skip, saying why, where its package is not installed (``pip install -e '.[onnx]'``)."""

from __future__ import annotations

import importlib.util
import json
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from respecd.messages import Frame, Percept
from respecd.perception.config import PerceptionConfig
from respecd.perception.detector import FusionDetector

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHIPPED = sorted(f"builtin:{p.name[:-3]}" for p in (resources.files("respecd.perception") / "weights").iterdir()
                 if p.name.endswith(".pt"))
RUNTIMES = [pytest.param(name, marks=pytest.mark.skipif(importlib.util.find_spec(module) is None,
                                                        reason=f"{name} is not installed (pip install "
                                                               f"-e '.[{extra}]')"))
            for name, module, extra in (("onnxruntime", "onnxruntime", "onnx"), ("openvino", "openvino", "openvino"))]
BOX_PX, SCORE, CONTRIBUTION = 1e-3, 1e-4, 1e-3  # issue 51's tolerances


LLVIP = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "llvip_pairs"  # evaluation-only pairs


def bundles() -> list[tuple[str, dict[str, Frame]]]:
    """The fixed inputs: a lit scene and a dark one with every sensor, the dark one without thermal and
    without RGB (a sensor switched off: zero planes, presence 0), a lit scene at 1280x720 (simulated,
    aligned by the simulator's calibration), and two real LLVIP visible/infrared pairs at 640x512
    (pixel-aligned: ``real_pairs``), the first also with RGB black and with thermal off."""
    from respecd.sim.render import render_lepton, render_radar, render_rgb
    from respecd.sim.world import SimulationConfig, World

    def scene(scenario: str, seed: int, size: tuple[int, int], drop: tuple[str, ...] = ()) -> dict[str, Frame]:
        state = World(SimulationConfig(scenarios=[scenario]), seed).state_at(12.0)
        rng = np.random.default_rng(seed)
        data = {"rgb": render_rgb(state, size, 1 / 30, rng), "thermal": render_lepton(state, (160, 120), rng),
                "radar": render_radar(state, "range", 10.0, rng)}
        return {k: Frame(k, state.t, 0, v) for k, v in data.items() if k not in drop}  # type: ignore[arg-type]

    return [("lit", scene("good-light-static", 21, (640, 360))),
            ("dark", scene("poor-light-static", 22, (640, 360))),
            ("dark, thermal off", scene("poor-light-static", 22, (640, 360), ("thermal",))),
            ("rgb off", scene("poor-light-static", 22, (640, 360), ("rgb",))),
            ("lit 1280x720", scene("good-light-static", 23, (1280, 720)))]


def real_pairs() -> list[tuple[str, dict[str, Frame]]]:
    import cv2

    pairs = []
    for key in ("190001", "190004"):
        rgb = cv2.imread(str(LLVIP / "visible" / f"{key}.jpg"), cv2.IMREAD_COLOR)
        ir = cv2.imread(str(LLVIP / "infrared" / f"{key}.jpg"), cv2.IMREAD_GRAYSCALE)
        assert rgb is not None and ir is not None, f"LLVIP pair {key} missing from {LLVIP}"
        small = [cv2.resize(a, (640, 512), interpolation=cv2.INTER_AREA) for a in (rgb, ir)]
        frames = {"rgb": Frame("rgb", 0.0, 0, small[0]), "thermal": Frame("thermal", 0.0, 0, small[1])}
        pairs.append((f"LLVIP {key}", frames))
    frames = pairs[0][1]  # the first also with each camera off: RGB black takes rgbt's thermal-alone map
    return pairs + [(f"{pairs[0][0]}, {off} off", {k: v for k, v in frames.items() if k != off}) for off in frames]


@pytest.fixture(scope="module")
def exports(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One export cache for the module: each checkpoint is exported once, then reused by every runtime."""
    return tmp_path_factory.mktemp("exported")


def detector(weights: str, runtime: str, exports: Path, simulated: bool = True) -> FusionDetector:
    """The checkpoint's detector on ``runtime``; ``simulated``: aligning by the simulated rover's calibration."""
    from respecd.lab.detector.simdata import sim_calibration
    from respecd.perception import checkpoint

    config = PerceptionConfig(weights=weights, model=checkpoint.spec_of(weights), runtime=runtime)
    return FusionDetector.load(config, sim_calibration() if simulated else None, exports)


def assert_same(want: Percept, got: Percept, what: str) -> None:
    assert len(got.detections) == len(want.detections), what
    for i, (a, b) in enumerate(zip(want.detections, got.detections, strict=True)):
        assert a.label == b.label, f"{what}: detection {i}"
        assert np.abs(np.subtract(a.box, b.box)).max() <= BOX_PX, f"{what}: detection {i} box {a.box} vs {b.box}"
        assert abs(a.confidence - b.confidence) <= SCORE, f"{what}: detection {i} score"
        if a.contributions is not None or b.contributions is not None:
            assert a.contributions is not None and b.contributions is not None, f"{what}: detection {i}"
            for k, v in a.contributions.items():
                assert abs(v - b.contributions[k]) <= CONTRIBUTION, f"{what}: detection {i} contribution of {k}"
    for field in ("contributions", "dependence", "sufficiency"):  # per sensor, whichever the percept carries
        wanted, found = getattr(want, field, None), getattr(got, field, None)
        assert (wanted is None) == (found is None), f"{what}: {field}"
        for k, v in (wanted or {}).items():
            assert abs(v - found[k]) <= CONTRIBUTION, f"{what}: scene {field} of {k}"


@pytest.mark.slow
@pytest.mark.timeout(600)  # rgbt (xl on both cameras) ran past the default 120 s at load 20 on 2 cores
@pytest.mark.parametrize("runtime", RUNTIMES)
@pytest.mark.parametrize("weights", SHIPPED)
def test_every_runtime_gives_torchs_detections_and_contributions(weights: str, runtime: str, exports: Path) -> None:
    found = 0
    for simulated, inputs in ((True, bundles()), (False, real_pairs())):
        reference = detector(weights, "torch", exports, simulated)
        exported = detector(weights, runtime, exports, simulated)
        assert exported.model.engine is not None and reference.model.engine is None
        found += compare(reference, exported, inputs, f"{weights} {runtime}")
    assert found >= 5  # the comparison saw detections (and, attributed, their contributions)


def compare(reference: FusionDetector, exported: FusionDetector, inputs: list[tuple[str, dict[str, Frame]]],
            what: str) -> int:
    """Every input, with and without attribution, through both detectors; how many detections were compared."""
    found = 0
    for name, frames in inputs:
        for attribute in (False, True):
            for d in (reference, exported):
                d.reset_scene_scores()  # each call on its own: no decaying score carried over
            want, got = reference.infer(frames, attribute), exported.infer(frames, attribute)
            assert_same(want, got, f"{what} {name} attribute={attribute}")
            found += len(want.detections)
    return found


@pytest.mark.parametrize("runtime", RUNTIMES)
@pytest.mark.slow
def test_rgbt_with_rgb_black_runs_its_thermal_alone_map_on_the_runtime(runtime: str, exports: Path,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """spec-rover's ``builtin:rgbt`` maps thermal one way alone and another beside RGB (``rgb_aware_fusion``):
    its exported fusion graph takes whether RGB is on as an input, so a real LWIR frame with RGB black gives
    torch's thermal-alone detections on the runtime, and so do the attribution's RGB-off passes."""
    reference, exported = (detector("builtin:rgbt", name, exports, simulated=False) for name in ("torch", runtime))
    folder = next(exports.glob("rgbt-[0-9a-f]*"))  # not rgbt-hituav-*
    manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    assert "rgb_on" in manifest["graphs"]["fuse"]["inputs"]
    frames = dict(real_pairs()[0][1])
    thermal_only = {"thermal": frames["thermal"]}
    want = {}
    for name, inputs in (("both", frames), ("RGB black", thermal_only)):
        for d in (reference, exported):
            d.reset_scene_scores()
        want[name] = reference.infer(inputs, attribute=True)
        assert_same(want[name], exported.infer(inputs, attribute=True), f"rgbt {runtime} {name}")
    assert len(want["RGB black"].detections) >= 2  # LLVIP's people, from thermal alone
    encode_rgb = reference.model.encode_rgb  # the flag matters here: thermal alone through the map beside RGB
    monkeypatch.setattr(reference.model, "encode_rgb", lambda rgb: (*encode_rgb(rgb)[:-1], rgb.new_ones(1, 1, 1, 1)))
    reference.reset_scene_scores()
    with pytest.raises(AssertionError):
        assert_same(want["RGB black"], reference.infer(thermal_only, attribute=True), "rgbt, RGB on forced")


@pytest.mark.parametrize("runtime", RUNTIMES)
def test_a_forward_pass_is_one_graph_and_attribution_runs_the_parts(runtime: str, exports: Path) -> None:
    """The runtime keeps its own layout (ONNX Runtime's NCHWc blocks) from input to head when a forward pass
    is one graph; attribution, which re-runs fusion with sensors off, still runs the parts."""
    exported = detector("builtin:sim-rover", runtime, exports)
    engine, called = exported.model.engine, []
    exported.model.engine = lambda name, *inputs: called.append(name) or engine(name, *inputs)
    frames = bundles()[0][1]
    assert exported.infer(frames, attribute=False).detections and called == ["net"]
    called.clear()
    exported.infer(frames, attribute=True)
    assert {"rgb", "aux", "neck"} <= set(called) and "net" not in called


def test_the_shipped_checkpoints_are_all_compared() -> None:
    assert {"builtin:sim-rover", "builtin:rgbt", "builtin:rgbt-hituav"} <= set(SHIPPED)


@pytest.mark.parametrize("runtime", RUNTIMES)
@pytest.mark.slow
def test_the_inference_bench_times_the_runtime_beside_torch(runtime: str, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """``respecd bench inference --runtime NAME``: CPU ms of forward and forward + attribution per size, and each
    forward's ratio to the FLOP limit (what ``../shared/checks/performance`` reads)."""
    import argparse

    from respecd.lab.bench import inference

    monkeypatch.setattr(inference, "RESOLUTIONS", ((640, 360),))
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))  # the export goes to the default state directory
    args = argparse.Namespace(weights="builtin:sim-rover", repeats=1, threads=1, seed=1, runtime=runtime)
    figures = inference.run(args)
    assert set(figures["runtimes"]) == {"torch", runtime}
    row = figures["runtimes"][runtime]["640x360"]
    assert 0 < row["forward_ms"] < row["attributed_ms"]
    assert row["to_limit"] == pytest.approx(row["forward_ms"] / figures["limit_ms"]["640x360"], rel=0.02)
    assert figures["peak_gflops"] > 1 and set(figures["gflop"]) == {"640x360"}
    assert (tmp_path / "respecd" / "exported").is_dir()
