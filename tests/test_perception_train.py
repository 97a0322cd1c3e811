"""Training: a one-epoch run on tiny data (LLVIP layout and the simulator), resume, augmentation."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from respecd.cli import main as cli_main
from respecd.lab.detector.augment import AugmentConfig, augment, collate
from respecd.lab.detector.data import LlvipSource, Sample, read_voc
from respecd.lab.detector.train import TrainConfig, train
from respecd.perception import checkpoint
from respecd.perception.config import ModelSpec, PerceptionConfig

TINY = ModelSpec(rgb_widths=(8, 8, 16, 16, 16), aux_widths=(8, 8, 8, 8, 8), neck_widths=(16, 16, 16))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def llvip_tiny(shared_data, tmp_path: Path) -> Path:
    """Two annotated real LLVIP pairs in the LLVIP layout."""
    src = shared_data / "llvip_pairs"
    root = tmp_path / "llvip"
    for sub, ext in (("visible", "jpg"), ("infrared", "jpg"), ("Annotations", "xml")):
        (root / sub).mkdir(parents=True)
        for pair in ("010005", "190004"):
            shutil.copy(src / sub / f"{pair}.{ext}", root / sub / f"{pair}.{ext}")
    return root


def test_voc_reader_reads_llvip_boxes(shared_data) -> None:
    boxes, labels = read_voc(shared_data / "llvip_pairs" / "Annotations" / "010005.xml", ("person",))
    assert boxes.shape == (3, 4) and labels.tolist() == [0, 0, 0]
    assert boxes[0].tolist() == [849, 405, 961, 663]


@pytest.mark.slow
def test_one_epoch_on_llvip_layout_then_resume(llvip_tiny: Path, tmp_path: Path) -> None:
    pcfg = PerceptionConfig(model=TINY)
    source = LlvipSource(llvip_tiny, pcfg, scale=0.25)
    sample = source[0]
    assert sample.planes.shape == (5, 256, 320) and sample.presence.tolist() == [1.0, 0.0]
    assert sample.boxes.shape == (3, 4)
    out = tmp_path / "model.pt"
    cfg = TrainConfig(data=str(llvip_tiny), out=out, epochs=1, batch=2, steps_per_epoch=2, threads=1,
                      progress=False, augment=AugmentConfig(size=(128, 96)))
    summary = train(cfg, pcfg)
    assert summary["steps"] == 2 and out.is_file()
    model, payload = checkpoint.load(str(out), expected=TINY)
    assert payload["data"] == str(llvip_tiny)
    resume = out.with_name(out.name + ".resume")
    assert checkpoint.read(resume)["epoch"] == 1
    second = train(TrainConfig(**{**cfg.__dict__, "epochs": 2, "resume": True}), pcfg)  # runs epoch 2 only
    resumed = checkpoint.read(resume)
    assert resumed["epoch"] == 2 and [r["epoch"] for r in resumed["curve"]] == [1, 2]
    assert any(not torch.equal(a, b) for a, b in zip(model.state_dict().values(),  # epoch 2 trained
                                                       resumed["ema"].values(), strict=True))
    kept = checkpoint.load(str(out))[0].state_dict()  # the best epoch's EMA (a tie keeps epoch 1)
    unchanged = all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), kept.values(), strict=True))
    assert unchanged == (second["best_epoch"] == 1)


@pytest.mark.slow
def test_bf16_training_keeps_fp32_weights_and_a_loss_close_to_fp32(llvip_tiny: Path, tmp_path: Path) -> None:
    from respecd.lab.detector.finetune import initial_model
    from respecd.lab.detector.train import _as_float, net_loss

    pcfg = PerceptionConfig(model=TINY)
    torch.manual_seed(0)
    model = initial_model(None, pcfg.model).train()
    samples = [augment(LlvipSource(llvip_tiny, pcfg, scale=0.25), np.random.default_rng(i), AugmentConfig(
        size=(128, 96)), pcfg.model.aux_modalities) for i in range(4)]
    x, presence, boxes, labels, mask = collate(samples)
    full, _ = net_loss(model, model(x, presence), (96, 128), boxes, labels, mask)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        raw = model(x, presence)
    half, _ = net_loss(model, _as_float(raw), (96, 128), boxes, labels, mask)
    assert half.dtype == torch.float32 and torch.isfinite(half)
    full_v, half_v = float(full.detach()), float(half.detach())
    assert abs(half_v - full_v) < 0.05 * full_v  # bf16 keeps ~3 significant digits

    out = tmp_path / "bf16.pt"
    summary = train(TrainConfig(data=str(llvip_tiny), out=out, epochs=1, batch=2, steps_per_epoch=2, threads=1,
                                progress=False, augment=AugmentConfig(size=(128, 96)), precision="bf16"), pcfg)
    assert summary["precision"] == "bf16"
    trained = checkpoint.load(str(out), expected=TINY)[0].state_dict()
    assert all(v.dtype in (torch.float32, torch.int64) for v in trained.values())
    torch.manual_seed(0)  # train() seeds torch with cfg.seed (0) before it builds the net
    start = initial_model(None, pcfg.model).state_dict()
    assert any(not torch.equal(a, b) for a, b in zip(start.values(), trained.values(), strict=True))


def test_batches_of_an_epoch_do_not_depend_on_the_epochs_before_it() -> None:
    """What --resume relies on: epoch 2 alone draws what epoch 2 drew after epoch 1."""
    from respecd.lab.detector.train import draw_batches

    class Draws:
        def draw(self, rng: np.random.Generator) -> float:
            return float(rng.random())

    both = list(draw_batches(Draws(), 7, 0, 2, 3))
    assert list(draw_batches(Draws(), 7, 1, 2, 3)) == both[3:] and both[:3] != both[3:]


def test_ema_steps_toward_the_net_and_copies_its_counters() -> None:
    """The average follows the training net, also after the net was moved to another memory layout (new storage)
    and its state loaded in place (--resume)."""
    import math

    from respecd.lab.detector.train import EMA
    from respecd.perception.model import FusionNet

    torch.manual_seed(0)
    net = FusionNet(TINY)
    ema = EMA(net, decay=0.9, tau=1.0)
    before = {k: v.clone() for k, v in ema.model.state_dict().items()}
    net = net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stub lacks it
    with torch.no_grad():
        net.load_state_dict({k: v + 1 if v.dtype.is_floating_point else v + 5 for k, v in net.state_dict().items()})
    ema.update(net)
    d = 0.9 * (1 - math.exp(-1.0))
    after, source = ema.model.state_dict(), net.state_dict()
    for name, old in before.items():
        if old.dtype.is_floating_point:
            torch.testing.assert_close(after[name], d * old + (1 - d) * source[name])
        else:
            assert torch.equal(after[name], source[name])  # batch-norm step counters are copied, not averaged
    assert ema.updates == 1


@pytest.mark.slow
def test_train_command_on_the_simulator(tmp_path: Path, capsys) -> None:
    out = tmp_path / "sim.pt"
    code = cli_main(["train", "--data", "sim", "--out", str(out), "--epochs", "1", "--steps", "1", "--batch", "2",
                     "--eval-frames", "0", "--threads", "1", "--quiet"])
    assert code == 0
    card = out.with_suffix(".json")
    assert out.is_file() and card.is_file()
    assert '"data": "sim"' in card.read_text()
    assert "wrote" in capsys.readouterr().out
    assert (tmp_path / "sim-curve.png").stat().st_size > 0  # the loss curve beside the checkpoint


def test_train_command_rejects_bad_input(tmp_path: Path, capsys) -> None:
    assert cli_main(["train", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "x.pt")]) == 2
    assert "expected 'sim' or a dataset folder" in capsys.readouterr().err
    assert cli_main(["train", "--data", "sim", "--out", str(tmp_path / "x.pt"), "--epochs", "0"]) == 2


@pytest.mark.slow
def test_train_recipe_flags_reach_the_training_config(tmp_path: Path, capsys) -> None:
    import json

    out = tmp_path / "sim.pt"
    code = cli_main(["train", "--data", "sim", "--out", str(out), "--epochs", "1", "--steps", "1", "--batch", "2",
                     "--eval-frames", "0", "--quiet", "--strip-zoom", "0.7,1.8", "--strip-zoom", "640x360=0.9,1.1",
                     "--keep-cut", "0.4",
                     "--radar-alone", "0.2", "--scenario-weight", "behind-curtain=3",
                     "--resolution-weight", "640x360=3"])
    assert code == 0
    train = json.loads(out.with_suffix(".json").read_text())["train"]
    assert train["augment"]["zoom"] == [0.7, 1.8] and train["augment"]["keep_cut"] == 0.4
    assert train["lr"] == 0.002  # the default peak learning rate, recorded so a stage can be re-run
    assert train["augment"]["zoom_at"] == [[[640, 360], [0.9, 1.1]]]
    assert [list(s) for s, w in train["augment"]["keep"] if w == 0.2] == [["radar"]]
    weights = train["scenario_weights"]
    assert weights["behind-curtain"] == 3.0 and weights["occlusion-partial"] == 2.0  # the others keep theirs
    assert train["resolution_weights"] == {"640x360": 3.0, "960x540": 1.0, "1280x720": 1.0}
    capsys.readouterr()
    assert cli_main(["train", "--data", "sim", "--out", str(out), "--resolution-weight", "800x600=2"]) == 2
    assert "expected WxH=W with WxH one of 640x360" in capsys.readouterr().err
    assert cli_main(["train", "--data", "sim", "--out", str(out), "--resolution-weight", "640x360=0,960x540=0,"
                     "1280x720=0"]) == 2
    assert "at least one resolution" in capsys.readouterr().err
    assert cli_main(["train", "--data", "sim", "--out", str(out), "--scenario-weight", "fog=2"]) == 2
    assert "expected NAME=W" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exited:  # refused while parsing
        cli_main(["train", "--data", "sim", "--out", str(out), "--radar-alone", "1.5"])
    assert exited.value.code == 2 and "--radar-alone: expected a number in [0, 1]" in capsys.readouterr().err
    assert cli_main(["train", "--data", "sim", "--out", str(out), "--strip-zoom", "800x600=0.7,1.4"]) == 2
    assert "expected LO,HI or WxH=LO,HI with WxH one of 640x360" in capsys.readouterr().err
    assert cli_main(["train", "--data", "sim", "--out", str(out), "--strip-zoom", "640x360=1.4,0.7"]) == 2
    assert "with LO <= HI" in capsys.readouterr().err


def test_a_strip_zooms_by_the_range_of_its_rgb_size() -> None:
    """A per-size range replaces the default one only for frames of that size."""
    from respecd.lab.detector.augment import strip

    cfg = AugmentConfig(zoom=(1.0, 1.0), zoom_at=(((640, 360), (2.0, 2.0)),), target_bias=1.0)
    assert cfg.zoom_for((640, 360)) == (2.0, 2.0) and cfg.zoom_for((1280, 720)) == (1.0, 1.0)
    sample = Sample(np.zeros((5, 360, 640), np.float32), np.ones(2, np.float32),
                    np.array([[300, 40, 330, 140]], np.float32), np.array([False]))  # 100 px tall
    rng = np.random.default_rng(0)
    for size, height in (((640, 360), 200.0), ((1280, 720), 100.0)):
        s = strip(sample, 320, 736, rng, cfg, cfg.zoom_for(size))
        assert len(s.boxes) == 1 and float(s.boxes[0, 3] - s.boxes[0, 1]) == pytest.approx(height)


def test_resolution_draw_is_uniform_by_default_and_follows_weights_when_given() -> None:
    from respecd.lab.detector.simdata import RESOLUTIONS, draw_resolution

    a, b = np.random.default_rng(3), np.random.default_rng(3)
    assert [draw_resolution(a) for _ in range(20)] == [RESOLUTIONS[int(b.integers(3))] for _ in range(20)]
    rng = np.random.default_rng(0)
    draws = [draw_resolution(rng, np.array([0.6, 0.2, 0.2])) for _ in range(2000)]
    share = draws.count((640, 360)) / len(draws)
    assert 0.56 < share < 0.64
    assert (640, 360) not in {draw_resolution(rng, np.array([0.0, 0.5, 0.5])) for _ in range(200)}


def _sample(w: int = 320, h: int = 180) -> Sample:
    planes = np.full((5, h, w), 100, np.uint8)
    boxes = np.array([[100, 40, 140, 160], [10, 10, 20, 20]], np.float32)
    return Sample(planes, np.ones(2, np.float32), boxes, np.array([False, True]))


def test_augment_keeps_boxes_inside_and_drops_modalities() -> None:
    rng = np.random.default_rng(0)
    cfg = AugmentConfig(size=(128, 96))
    pool = [_sample() for _ in range(4)]
    kept = set()
    for _ in range(120):
        s = augment(pool, rng, cfg)
        assert s.planes.shape == (5, 96, 128)
        assert (s.boxes[:, [0, 2]] >= 0).all() and (s.boxes[:, [0, 2]] <= 128).all()
        assert (s.boxes[:, [1, 3]] >= 0).all() and (s.boxes[:, [1, 3]] <= 96).all()
        on = (bool(s.planes[:3].any()), *(bool(v) for v in s.presence))
        assert any(on) and all(bool(s.planes[3 + i].any()) == bool(s.presence[i]) for i in range(2))
        kept.add(on)
    assert len(kept) == 7  # all on, RGB / thermal / radar alone and each pair
    x, presence, boxes, labels, mask = collate([augment(pool, rng, AugmentConfig(size=(128, 96))) for _ in range(3)])
    assert x.shape == (3, 5, 96, 128) and presence.shape == (3, 2)
    assert boxes.shape[:2] == labels.shape == mask.shape and float(x.max()) <= 1.0


def test_a_box_the_window_cuts_is_ignored_not_trained_on_half() -> None:
    from respecd.lab.detector.augment import strip

    planes = np.zeros((5, 360, 640), np.float32)
    boxes = np.array([[100, 0, 160, 300]], np.float32)  # 60 px wide, cut by the frame's top already
    sample = Sample(planes, np.ones(2, np.float32), boxes, np.array([False]))
    rng = np.random.default_rng(1)
    cfg = AugmentConfig(zoom=(1.0, 1.0), target_bias=0.0)  # windows anywhere: some cut the person
    seen = set()
    for _ in range(60):
        s = strip(sample, 160, 384, rng, cfg)
        assert s.planes.shape == (5, 384, 160) and s.planes.dtype == np.float32
        for box, ignored in zip(s.boxes, s.ignore, strict=True):
            width = float(box[2] - box[0])
            assert bool(ignored) == (width < 0.9 * 60)  # a whole person is a target, a cut one is not
            assert box[1] == 0 and box[3] == 300  # full frame height: nothing more is cut at top or bottom
            seen.add(bool(ignored))
    assert seen == {True, False}


def test_labels_follow_the_evidence_when_a_sensor_is_dropped() -> None:
    """Behind a curtain only the radar sees: with it off the person is no target. In the dark
    a person seen by RGB alone is ignored (a hint, not evidence), by day a target."""
    from respecd.lab.detector.augment import drop_modalities

    def sample(rgb_signal: float) -> Sample:
        boxes = np.array([[10, 10, 50, 90], [100, 10, 140, 90]], np.float32)
        seen = np.array([[0.0, 0.005], [1.0, 1.0]], np.float32)  # behind a curtain; in the open
        return Sample(np.ones((5, 100, 160), np.float32), np.ones(2, np.float32), boxes, np.zeros(2, bool),
                      meta={"rgb_signal": rgb_signal}, seen=seen)

    def after(keep: tuple[str, ...], rgb_signal: float = 1.0) -> Sample:
        s = sample(rgb_signal)
        drop_modalities(s, np.random.default_rng(0), AugmentConfig(keep=((keep, 1.0),)))
        return s

    assert after(("rgb", "thermal", "radar")).ignore.tolist() == [False, False]
    only_cameras = after(("rgb", "thermal"))
    assert only_cameras.presence.tolist() == [1.0, 0.0] and only_cameras.boxes.tolist() == [[100, 10, 140, 90]]
    assert after(("radar",)).ignore.tolist() == [False, False] and not after(("radar",)).planes[:4].any()
    assert after(("rgb",), rgb_signal=0.01).ignore.tolist() == [True]  # dark: the open person is a hint
    assert after(("rgb",), rgb_signal=0.5).ignore.tolist() == [False]
    assert after(("thermal",), rgb_signal=0.01).ignore.tolist() == [False]


def test_tall_people_are_assigned_to_the_heads_that_can_draw_them() -> None:
    """The DFL head reaches reg_max - 1 strides: 240 px at P3, 480 at P4; taller goes to P5."""
    from respecd.lab.detector.loss import LossGains, assign
    from respecd.perception.model import anchor_grid

    points, strides = anchor_grid(736, 320)
    for height, levels in ((60, {8, 16, 32}), (300, {16, 32}), (560, {32})):
        gt = torch.tensor([[[100.0, 10.0, 100.0 + 0.35 * height, 10.0 + height]]])
        n = len(points)
        for bias in (8, 16, 32):  # whichever level the scores favour, only reachable ones may win
            scores = torch.where(strides[None] == bias, 0.9, 0.1).expand(1, n, 1)
            _, _, fg = assign(scores, gt.expand(1, n, 4).clone(), points, strides, gt,
                              torch.zeros(1, 1, dtype=torch.long), torch.ones(1, 1, dtype=torch.bool), LossGains(), 16)
            assert fg.any() and {int(s) for s in strides[fg[0], 0].tolist()} <= levels


def test_training_frames_are_aligned_as_the_daemon_aligns_them() -> None:
    """The same Aligner and calibration as the perception stage of builtin:sim-rover, not a resize."""
    from respecd.config import load_profile
    from respecd.lab.detector.simdata import SimFrames
    from respecd.perception.align import Aligner
    from respecd.perception.stage import calibration_from_profile

    frames = SimFrames(PerceptionConfig(), seed=3)
    daemon = Aligner(PerceptionConfig(), calibration_from_profile(load_profile("builtin:sim-rover")))
    assert frames.aligner.calibration == daemon.calibration and frames.aligner.calibration["thermal"] is not None
    sample = frames.sample(frames.time_in(2, 0.5), (1280, 720), np.random.default_rng(0), randomize=False)
    assert sample.planes.shape == (5, 720, 1280) and sample.planes.dtype == np.float32
    assert sample.presence.tolist() == [1.0, 1.0] and len(sample.boxes) == len(sample.seen)
