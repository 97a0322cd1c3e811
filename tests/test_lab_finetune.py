"""A short fine-tuning run from pretrained Darknet weights on real thermal images (HIT-UAV, COCO json):
frozen parts stay as they were, backbone 2 learns, validation picks the epoch, the curve is drawn."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from respecd.cli import main as cli_main
from respecd.lab.detector.train import MixedSource
from respecd.perception import checkpoint
from respecd.perception.config import ModelSpec
from respecd.perception.darknet_fusion import from_darknet

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def tiny_hituav(shared_data: Path, tmp_path: Path) -> Path:
    """The first four real HIT-UAV train images with people and two val ones, the dataset's own json spellings."""
    src = shared_data / "hituav_thermal"
    root = tmp_path / "hituav"
    (root / "annotations").mkdir(parents=True)
    for split, count in (("train", 4), ("val", 2)):
        doc = json.loads((src / "annotations" / f"{split}.json").read_text(encoding="utf-8"))
        people = {a["image_id"] for a in doc["annotation"] if a["category_id"] == 0}
        images = [im for im in doc["images"] if im["id"] in people][:count]
        ids = {im["id"] for im in images}
        doc.update(images=images, annotation=[a for a in doc["annotation"] if a["image_id"] in ids])
        (root / "annotations" / f"{split}.json").write_text(json.dumps(doc), encoding="utf-8")
        (root / split).mkdir()
        for im in images:
            shutil.copy(src / split / im["filename"], root / split / im["filename"])
    return root


@pytest.mark.slow
def test_fine_tune_from_darknet_weights(tiny_hituav: Path, shared_data: Path, tmp_path: Path, capsys) -> None:
    weights = shared_data.parent / "pretrained" / "yolo_fastest" / "yolo-fastest-1.1_body.weights"
    out = tmp_path / "rgbt.pt"
    args = ["train", "--data", str(tiny_hituav), "--out", str(out), "--init", str(weights), "--aux", "thermal",
            "--freeze", "rgb,head,fuse", "--epochs", "2", "--steps", "2", "--batch", "2", "--crop", "128x96",
            "--zoom", "1.5,3", "--scale", "0.5", "--threads", "1", "--quiet"]
    assert cli_main(args) == 0
    model, payload = checkpoint.load(str(out))
    assert model.spec.backbone == "darknet:yolo-fastest-1.1_body" and model.spec.aux_modalities == ("thermal",)
    start = from_darknet(ModelSpec(backbone=model.spec.backbone, aux_modalities=("thermal",)), weights)
    for part in ("rgb", "head", "fuse"):  # frozen: weights and batch-norm statistics exactly as imported
        for a, b in zip(getattr(start, part).state_dict().values(), getattr(model, part).state_dict().values(),
                        strict=True):
            assert torch.equal(a, b), part
    assert any(not torch.equal(a, b) for a, b in zip(start.aux.state_dict().values(),
                                                       model.aux.state_dict().values(), strict=True))
    curve = payload["train"]["curve"]
    assert [r["epoch"] for r in curve] == [1, 2] and all(r["val_map50"] is not None for r in curve)
    assert payload["train"]["best_epoch"] in (1, 2)
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["metrics"]["val_map50"] == max(r["val_map50"] for r in curve)
    assert out.with_name("rgbt-curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert cli_main(args + ["--epochs", "3", "--resume"]) == 0  # continues with epoch 3 only
    assert [r["epoch"] for r in checkpoint.read(out)["train"]["curve"]] == [1, 2, 3]
    assert "wrote" in capsys.readouterr().out


@pytest.mark.slow
def test_fine_tune_only_the_fusion_of_a_thermal_backbone_from_another_model(tiny_hituav: Path, shared_data: Path,
                                                                             tmp_path: Path) -> None:
    folder = shared_data.parent / "pretrained" / "yolo_fastest"
    body, xl = folder / "yolo-fastest-1.1_body.weights", folder / "yolo-fastest-1.1-xl.weights"
    out = tmp_path / "mixed.pt"
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", str(out), "--init", f"{body},{xl}",
                     "--aux", "thermal", "--aux-scale", "0.5", "--freeze", "rgb,head,aux,fuse.*.rgb", "--epochs", "1",
                     "--steps", "2", "--batch", "2", "--crop", "128x96", "--zoom", "1.5,3", "--scale", "0.5",
                     "--lr", "0.01", "--threads", "1", "--quiet"]) == 0
    model, _ = checkpoint.load(str(out))
    assert (model.spec.backbone, model.spec.aux_backbone) == ("darknet:yolo-fastest-1.1_body",
                                                               "darknet:yolo-fastest-1.1-xl")
    assert model.spec.aux_scale == 0.5
    start = from_darknet(model.spec, body, xl)
    before, after = start.state_dict(), model.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith("fuse.") and k.endswith(".aux.weight") for k in changed)


def test_bad_fine_tune_arguments(tiny_hituav: Path, tmp_path: Path, capsys) -> None:
    out = str(tmp_path / "x.pt")
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", out, "--init", "missing.weights"]) == 2
    assert "no such Darknet weights file" in capsys.readouterr().err
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", out, "--freeze", "wings", "--steps", "1"]) == 2
    assert "the net has no part 'wings'" in capsys.readouterr().err
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", out, "--freeze", "fuse.*.x", "--steps", "1"]) == 2
    assert "the net has no part 'fuse.*.x'" in capsys.readouterr().err
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", out, "--crop", "100x64"]) == 2
    assert "multiples of 32" in capsys.readouterr().err


@pytest.mark.slow
def test_fine_tune_on_a_folder_mixed_with_the_simulator(tiny_hituav: Path, shared_data: Path, tmp_path: Path) -> None:
    weights = shared_data.parent / "pretrained" / "yolo_fastest" / "yolo-fastest-1.1_body.weights"
    out = tmp_path / "mix.pt"
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", str(out), "--init", str(weights), "--aux", "thermal",
                     "--freeze", "rgb,head,fuse", "--epochs", "1", "--steps", "4", "--batch", "2", "--crop", "128x96",
                     "--zoom", "1.5,3", "--scale", "0.5", "--sim-mix", "0.5", "--threads", "1", "--quiet"]) == 0
    train = checkpoint.read(out)["train"]
    assert train["sim_mix"] == 0.5 and train["pool"] == 4  # the folder's four train images
    assert {"good-light-static", "poor-light-static"} <= set(train["scenario_weights"])  # the sim draw, on the card
    assert train["curve"][0]["val_map50"] is not None  # validated on the folder's val split, never the sim


class _Tagged:
    def __init__(self, tag: str) -> None:
        self.tag = tag

    def draw(self, rng: np.random.Generator) -> tuple[str, tuple[int, int]]:
        return self.tag, (32, 32)


def test_mixed_source_draws_the_simulator_at_its_share() -> None:
    source = MixedSource(_Tagged("folder"), _Tagged("sim"), 0.3)
    rng = np.random.default_rng(0)
    share = sum(source.draw(rng)[0] == "sim" for _ in range(2000)) / 2000
    assert 0.27 <= share <= 0.33


@pytest.mark.slow
@pytest.mark.parametrize("share", ["1.0", "-0.1"])
def test_bad_sim_mix_is_refused(tiny_hituav: Path, tmp_path: Path, capsys, share: str) -> None:
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", str(tmp_path / "x.pt"), "--sim-mix", share]) == 2
    assert "--sim-mix" in capsys.readouterr().err


def test_sim_mix_needs_folder_data(tmp_path: Path, capsys) -> None:
    assert cli_main(["train", "--data", "sim", "--out", str(tmp_path / "x.pt"), "--sim-mix", "0.5"]) == 2
    assert "with --data a folder" in capsys.readouterr().err


@pytest.fixture
def tiny_tdp(shared_data: Path, tmp_path: Path) -> Path:
    """Three real ground-level thermal images with people from thermal_dogs_people's train split (YOLO txt)."""
    src = shared_data / "thermal_dogs_people" / "gray"
    root = tmp_path / "tdp"
    (root / "images" / "train").mkdir(parents=True)
    (root / "labels" / "train").mkdir(parents=True)
    shutil.copy(src / "data.yaml", root / "data.yaml")
    people = [p for p in sorted((src / "labels" / "train").glob("*.txt"))
              if any(line.split()[:1] == ["1"] for line in p.read_text().splitlines())][:3]
    for label in people:
        shutil.copy(label, root / "labels" / "train" / label.name)
        shutil.copy(src / "images" / "train" / f"{label.stem}.png", root / "images" / "train" / f"{label.stem}.png")
    return root


@pytest.mark.slow
def test_fine_tune_with_crops_from_another_folder(tiny_hituav: Path, tiny_tdp: Path, shared_data: Path,
                                                  tmp_path: Path) -> None:
    weights = shared_data.parent / "pretrained" / "yolo_fastest" / "yolo-fastest-1.1_body.weights"
    out = tmp_path / "two.pt"
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", str(out), "--init", str(weights), "--aux", "thermal",
                     "--freeze", "rgb,head,aux,fuse.*.rgb", "--epochs", "1", "--steps", "2", "--batch", "2",
                     "--crop", "128x96", "--scale", "0.5", "--extra-data", f"{tiny_tdp}=0.4@0.5,1",
                     "--threads", "1", "--quiet"]) == 0
    train = checkpoint.read(out)["train"]
    extra = json.loads(json.dumps(train["extra_data"]))
    assert extra == [{"path": str(tiny_tdp), "share": 0.4, "zoom": [0.5, 1.0], "pool": 3}]
    assert train["pool"] == 4 + 3 and train["curve"][0]["val_map50"] is not None  # validated on --data's val only


class _Pool:
    def __init__(self, tag: str) -> None:
        self.tag = tag

    def __len__(self) -> int:
        return 1


def test_crops_come_from_each_folder_at_its_share(monkeypatch) -> None:
    from respecd.lab.detector import train as train_mod
    from respecd.lab.detector.augment import AugmentConfig

    monkeypatch.setattr(train_mod, "augment", lambda pool, rng, cfg, aux: (pool.tag, cfg.scale))
    wide, near = AugmentConfig(), AugmentConfig(scale=(1.5, 4.0))
    cfg = train_mod.TrainConfig(data="x", out=Path("x.pt"), batch=1000)
    source = train_mod.CropSource([(_Pool("street"), wide, 0.7), (_Pool("drone"), near, 0.3)], cfg, ("thermal",))
    batch, _ = source.draw(np.random.default_rng(0))
    drone = [scale for tag, scale in batch if tag == "drone"]
    assert 0.26 <= len(drone) / len(batch) <= 0.34 and set(drone) == {(1.5, 4.0)}  # each folder its own zoom


@pytest.mark.parametrize(("spec", "message"), [("{d}=1.2", "0 < SHARE < 1"), ("{d}", "DIR=SHARE"),
                                               ("{d}=0.6 --extra-data {d}=0.5", "add up to 1.1"),
                                               ("/nonexistent=0.3", "expected a dataset folder"),
                                               ("{d}=0.3@2,1", "LO <= HI")])
def test_bad_extra_data_is_refused(tiny_hituav: Path, tmp_path: Path, capsys, spec: str, message: str) -> None:
    extra = spec.format(d=tiny_hituav).split(" --extra-data ")
    flags = [f for e in extra for f in ("--extra-data", e)]
    assert cli_main(["train", "--data", str(tiny_hituav), "--out", str(tmp_path / "x.pt"), *flags]) == 2
    assert message in capsys.readouterr().err
