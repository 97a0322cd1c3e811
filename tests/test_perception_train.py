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


def test_train_command_on_the_simulator(tmp_path: Path, capsys) -> None:
    out = tmp_path / "sim.pt"
    code = cli_main(["train", "--data", "sim", "--out", str(out), "--epochs", "1", "--steps", "1", "--batch", "2",
                     "--segments", "2", "--eval-frames", "0", "--threads", "1", "--quiet"])
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


def _sample(w: int = 320, h: int = 180) -> Sample:
    planes = np.full((5, h, w), 100, np.uint8)
    boxes = np.array([[100, 40, 140, 160], [10, 10, 20, 20]], np.float32)
    return Sample(planes, np.ones(2, np.float32), boxes, np.array([False, True]))


def test_augment_keeps_boxes_inside_and_drops_modalities() -> None:
    rng = np.random.default_rng(0)
    cfg = AugmentConfig(size=(128, 96), drop_aux_all=1.0)  # always drop every non-RGB modality
    pool = [_sample() for _ in range(4)]
    for _ in range(20):
        s = augment(pool, rng, cfg)
        assert s.planes.shape == (5, 96, 128)
        assert (s.boxes[:, [0, 2]] >= 0).all() and (s.boxes[:, [0, 2]] <= 128).all()
        assert (s.boxes[:, [1, 3]] >= 0).all() and (s.boxes[:, [1, 3]] <= 96).all()
        assert s.presence.tolist() == [0.0, 0.0] and not s.planes[3:].any()
    x, presence, boxes, labels, mask = collate([augment(pool, rng, AugmentConfig(size=(128, 96))) for _ in range(3)])
    assert x.shape == (3, 5, 96, 128) and presence.shape == (3, 2)
    assert boxes.shape[:2] == labels.shape == mask.shape and float(x.max()) <= 1.0
