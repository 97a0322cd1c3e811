"""Real dataset folders: LLVIP/VOC pairs, COCO json (HIT-UAV's spellings and the standard ones), YOLO txt."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from respecd.errors import InputError
from respecd.lab.detector.datasets import FolderSource, image_modality, open_folder
from respecd.perception.config import ModelSpec, PerceptionConfig

RGBT = PerceptionConfig(model=ModelSpec(aux_modalities=("thermal",)))
FEW = ("0_100_30_0_03306.jpg", "0_100_30_0_08087.jpg", "0_100_40_0_03329.jpg")


@pytest.fixture
def hituav(shared_data: Path) -> Path:
    return shared_data / "hituav_thermal"


def _hituav_annotations(hituav: Path) -> tuple[dict, list[dict]]:
    doc = json.loads((hituav / "annotations" / "val.json").read_text(encoding="utf-8"))
    images = [im for im in doc["images"] if im["filename"] in FEW]
    ids = {im["id"] for im in images}
    return doc, images + [a for a in doc["annotation"] if a["image_id"] in ids]  # type: ignore[list-item]


@pytest.fixture
def small_coco(hituav: Path, tmp_path: Path) -> Path:
    """Three real HIT-UAV val images in the standard COCO spellings (file_name, annotations)."""
    doc, rows = _hituav_annotations(hituav)
    images = [{"id": r["id"], "file_name": r["filename"], "width": r["width"], "height": r["height"]}
              for r in rows if "filename" in r]
    anns = [r for r in rows if "bbox" in r]
    root = tmp_path / "coco"
    (root / "annotations").mkdir(parents=True)
    (root / "images" / "train").mkdir(parents=True)
    for im in images:
        shutil.copy(hituav / "val" / im["file_name"], root / "images" / "train" / im["file_name"])
    (root / "annotations" / "train.json").write_text(
        json.dumps({"images": images, "annotations": anns, "categories": doc["categories"]}), encoding="utf-8")
    return root


def test_hituav_coco_with_its_own_spellings(hituav: Path) -> None:
    folder = open_folder(hituav, ("person",))
    assert folder.kind == "coco" and folder.modalities == {"thermal"}
    assert (len(folder.train), len(folder.val)) == (2029, 290)  # its own splits, no hold-out
    persons = sum(int((~it.ignore).sum()) for it in folder.val)
    assert persons == 1168  # SOURCE.md: 1168 Person boxes in val
    assert sum(int(it.ignore.sum()) for it in folder.val) > 0  # DontCare boxes are kept as ignore regions
    assert all(it.rgb is None for it in folder.val)


def test_standard_coco_gives_the_same_boxes(hituav: Path, small_coco: Path) -> None:
    ours = {it.key: it for it in open_folder(small_coco, ("person",), hold_out=False).train}
    theirs = {it.key: it for it in open_folder(hituav, ("person",)).val if it.key in ours}
    assert len(ours) == len(FEW)
    for key, item in ours.items():
        np.testing.assert_array_equal(item.boxes, theirs[key].boxes)


def test_yolo_txt_from_the_same_images(hituav: Path, small_coco: Path, tmp_path: Path) -> None:
    coco = {it.key: it for it in open_folder(small_coco, ("person",), hold_out=False).train}
    root = tmp_path / "yolo"
    (root / "images" / "val").mkdir(parents=True)
    (root / "labels" / "val").mkdir(parents=True)
    (root / "data.yaml").write_text("names: [Person, Car]\n", encoding="utf-8")
    for key, item in coco.items():
        shutil.copy(hituav / "val" / f"{key}.jpg", root / "images" / "val" / f"{key}.jpg")
        lines = [f"0 {(x1 + x2) / 1280} {(y1 + y2) / 1024} {(x2 - x1) / 640} {(y2 - y1) / 512}"
                 for (x1, y1, x2, y2), ign in zip(item.boxes, item.ignore, strict=True) if not ign]
        lines.append("1 0.5 0.5 0.1 0.1")  # a car: not a model class, skipped
        (root / "labels" / "val" / f"{key}.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    folder = open_folder(root, ("person",))
    assert folder.kind == "yolo" and not folder.train and len(folder.val) == len(FEW)
    for item in folder.val:
        np.testing.assert_allclose(item.boxes, coco[item.key].boxes[~coco[item.key].ignore], atol=1e-3)
    bad = root / "labels" / "val" / f"{FEW[0][:-4]}.txt"
    bad.write_text("0 0.5 0.5\n", encoding="utf-8")
    with pytest.raises(InputError, match=rf"{bad.name}:1: expected 'class cx cy w h'"):
        open_folder(root, ("person",))


def test_llvip_pairs_are_voc_with_both_modalities(shared_data: Path) -> None:
    folder = open_folder(shared_data / "llvip_pairs", ("person",), hold_out=False)
    assert folder.kind == "voc" and folder.modalities == {"rgb", "thermal"}
    assert sorted(it.key for it in folder.train) == ["010005", "190001", "190002", "190003", "190004", "190005"]
    assert sum(len(it.boxes) for it in folder.train) == 13
    held = open_folder(shared_data / "llvip_pairs", ("person",), seed=1)
    assert len(held.val) == 1 and len(held.train) == 5 and held.notes


def test_a_thermal_only_sample_has_no_rgb_and_thermal_present(hituav: Path) -> None:
    folder = open_folder(hituav, ("person",))
    sample = FolderSource(folder.val[:1], RGBT, scale=0.5)[0]
    assert sample.planes.shape == (4, 256, 320)
    assert sample.planes[:3].max() == 0 and sample.planes[3].max() > 0
    assert sample.presence.tolist() == [1.0] and sample.meta["rgb"] is False
    assert image_modality(hituav / "val" / FEW[0]) == "thermal"


def test_an_rgb_only_folder_has_its_thermal_absent(shared_data: Path, tmp_path: Path) -> None:
    root = tmp_path / "voc"
    (root / "Annotations").mkdir(parents=True)
    (root / "visible").mkdir()
    shutil.copy(shared_data / "llvip_pairs" / "Annotations" / "190003.xml", root / "Annotations")
    shutil.copy(shared_data / "llvip_pairs" / "visible" / "190003.jpg", root / "visible")
    folder = open_folder(root, ("person",), hold_out=False)
    assert folder.modalities == {"rgb"}
    sample = FolderSource(folder.train, RGBT, scale=0.25)[0]
    assert sample.presence.tolist() == [0.0] and sample.planes[3].max() == 0 and sample.planes[:3].max() > 0
    assert len(sample.boxes) == 5


def test_bad_folders_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not a dataset folder"):
        open_folder(tmp_path, ("person",))
    (tmp_path / "annotations").mkdir()
    (tmp_path / "annotations" / "train.json").write_text("{not json", encoding="utf-8")
    with pytest.raises(InputError, match=r"train.json: not readable COCO json"):
        open_folder(tmp_path, ("person",))
    (tmp_path / "annotations" / "train.json").write_text('{"images": [{"id": 1, "file_name": "x.jpg"}], '
                                                         '"annotations": []}', encoding="utf-8")
    with pytest.raises(InputError, match=r"image x.jpg not found"):
        open_folder(tmp_path, ("person",))
