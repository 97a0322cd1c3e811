"""mAP computation, the eval command on the real LLVIP pairs, the report files, the bench."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from respecd.cli import main as cli_main
from respecd.lab.detector.metrics import ImageResult, average_precision, detection_f1, mean_ap
from respecd.messages import conf_agg
from respecd.perception import checkpoint
from respecd.perception.config import ModelSpec
from respecd.perception.model import FusionNet

TINY = ModelSpec(rgb_widths=(8, 8, 16, 16, 16), aux_widths=(8, 8, 8, 8, 8), neck_widths=(16, 16, 16))


pytestmark = pytest.mark.usefixtures("one_torch_thread")
GT = np.array([[10, 10, 50, 90], [100, 20, 140, 100]], np.float32)


def test_perfect_detections_score_one() -> None:
    images = [ImageResult(GT.copy(), np.array([0.9, 0.8]), GT)]
    assert mean_ap(images) == {"map50": pytest.approx(1.0), "map50_95": pytest.approx(1.0)}


def test_misses_false_positives_and_loose_boxes_cost_precision() -> None:
    loose = GT + np.array([4, 4, 4, 4], np.float32)  # IoU ~0.7: counts at 0.5, not at 0.9
    images = [ImageResult(loose, np.array([0.9, 0.8]), GT)]
    scores = mean_ap(images)
    assert scores["map50"] == pytest.approx(1.0) and scores["map50_95"] < 0.6
    half = [ImageResult(np.vstack([GT[:1], [[200, 200, 240, 260]]]), np.array([0.5, 0.9]), GT)]
    # the false positive ranks first, then one of two boxes is found: precision 1/2 at recall 1/2
    assert average_precision(half, 0.5) == pytest.approx(51 / 101 * 0.5, abs=1e-6)
    assert average_precision([ImageResult(np.zeros((0, 4)), np.zeros(0), GT)], 0.5) == 0.0


def test_ignored_ground_truth_is_neither_hit_nor_miss() -> None:
    ignore = np.array([False, True])
    only_first = [ImageResult(GT[:1].copy(), np.array([0.9]), GT, ignore)]
    assert average_precision(only_first, 0.5) == pytest.approx(1.0)  # the hidden person is not a miss
    both = [ImageResult(GT.copy(), np.array([0.9, 0.95]), GT, ignore)]
    assert average_precision(both, 0.5) == pytest.approx(1.0)  # nor is a detection on it a false positive


def test_a_missed_person_lowers_the_f1_but_not_the_confidence() -> None:
    """What the truth quality of training is for: ConfAgg (mean of the top scores) is the same
    whether the detector found one person of two or both, F1 is not."""
    one = ImageResult(GT[:1].copy(), np.array([0.9]), GT)
    both = ImageResult(GT.copy(), np.array([0.9, 0.9]), GT)
    assert conf_agg(one.pred_scores.tolist()) == conf_agg(both.pred_scores.tolist())
    assert detection_f1(both) == 1.0 and detection_f1(one) == pytest.approx(2 / 3)
    extra = ImageResult(np.vstack([GT, [[200, 200, 240, 260]]]), np.array([0.9, 0.9, 0.3]), GT)
    assert detection_f1(extra) == pytest.approx(4 / 5)  # a false box costs as a miss does
    assert detection_f1(ImageResult(np.zeros((0, 4)), np.zeros(0), np.zeros((0, 4)))) == 1.0  # nothing, nothing
    ignored = ImageResult(GT.copy(), np.array([0.9, 0.9]), GT, np.array([False, True]))
    assert detection_f1(ignored) == 1.0  # a box on a hidden person counts neither way


def _responsive(net: FusionNet) -> FusionNet:
    """An untrained net whose scores depend on its input: with fresh BatchNorm statistics (mean 0,
    variance 1) its class scores sit at the bias prior whatever the image, so switching a sensor
    off changes nothing and no frame gets a contribution."""
    for module in net.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_var.fill_(0.01)
    return net


@pytest.mark.slow
def test_eval_command_on_real_llvip_pairs(shared_data, tmp_path: Path, capsys) -> None:
    torch.manual_seed(0)
    weights = tmp_path / "tiny.pt"
    checkpoint.save(weights, _responsive(FusionNet(TINY)))
    out = tmp_path / "eval"
    code = cli_main(["eval", "--data", str(shared_data / "llvip_pairs"), "--weights", str(weights),
                     "--out", str(out), "--scale", "0.25", "--threads", "1", "--quiet",
                     "--attribution-threshold", "0.0"])  # an untrained net: attribute whatever it finds
    assert code == 0
    report = json.loads((out / "eval.json").read_text())
    assert report["frames"]["llvip_pairs"] == 6  # the six annotated pairs
    assert set(report["map"]["llvip_pairs"]) == {"none", "no_rgb", "no_thermal", "no_radar", "rgb_only",
                                                 "thermal_only", "radar_only"}
    assert set(report["ablation"]["llvip_pairs"]) == set(report["map"]["llvip_pairs"])
    assert report["map50"] == report["map"]["all"]["none"]["map50"]  # the real-folder top-level keys
    assert isinstance(report["detections"], int) and isinstance(report["detections_without_rgb"], int)
    assert set(report["contributions"]) >= {"rgb", "thermal"}  # flat: the mean scene scores
    assert report["contributions_by_condition"]["all"] == report["contributions"]
    for key in ("dependence", "sufficiency", "shapley"):  # per sensor, beside the contributions
        assert set(report[key]) == {"rgb", "thermal", "radar"} and report[key]["radar"] == 0.0  # LLVIP: no radar
        assert report[f"{key}_by_condition"]["all"] == report[key]
    assert all(0 <= report[key][m] <= 1 for key in ("dependence", "sufficiency") for m in ("rgb", "thermal"))
    assert report["sufficiency"]["rgb"] + report["sufficiency"]["thermal"] > 0  # the net does find things alone
    a, c, s = report["ablation"]["all"], report["contributions"], report["sufficiency"]  # perception-real's reads
    assert {"none", "no_rgb", "no_thermal"} <= set(a) and "thermal" in c and {"rgb", "thermal"} <= set(s)
    assert (out / "contributions.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = (out / "eval.md").read_text()
    assert "| llvip_pairs | 6 |" in text and "mAP@0.5" in text
    assert "kept with only it on (sufficiency)" in text
    assert "wrote" in capsys.readouterr().out


@pytest.mark.slow
def test_eval_command_on_the_simulator_writes_every_key(tmp_path: Path) -> None:
    """The keys the acceptance check reads, for every condition and resolution (a tiny net, 1 run each)."""
    torch.manual_seed(0)
    weights = tmp_path / "tiny.pt"
    checkpoint.save(weights, FusionNet(TINY))
    out = tmp_path / "eval"
    assert cli_main(["eval", "--data", "sim", "--weights", str(weights), "--out", str(out), "--frames", "2",
                     "--seed", "7", "--threads", "1", "--quiet"]) == 0
    report = json.loads((out / "eval.json").read_text())
    assert report["world_seed"] == 7 and "world seed 7" in (out / "eval.md").read_text()
    conditions = {"good-light", "dark", "occlusion", "smoke", "radar-only", "motion"}
    assert set(report["by_resolution"]) == {"640x360", "960x540", "1280x720"}
    for row in report["by_resolution"].values():
        assert 0 <= row["map50"] <= 1 and set(row["by_condition"]) == conditions
        assert set(row["levels"]) == {"P3", "P4", "P5"}
        assert set(row["recall_by_height"]["all"]) == {"0-0.1", "0.1-0.2", "0.2-0.4", "0.4-0.7", ">=0.7"}
        assert set(row["false_boxes"]) == {"all", *conditions}
        assert set(row["false_boxes"]["all"]) == {"second", "misplaced", "clutter"}
        assert set(row["delivered_map50"]) == {"all", *conditions}
        assert 0 <= row["delivered_map50"]["all"] <= 1
    assert set(report["ablation"]) == {"all", *conditions}
    assert set(report["ablation"]["radar-only"]) == {"none", "no_rgb", "no_thermal", "no_radar", "rgb_only",
                                                     "thermal_only", "radar_only"}
    assert report["frames"]["radar-only"] == 2 and report["frames"]["all"] == 14  # 7 scenarios x 2 instants
    assert report["attribution"] == {"method": "ablation", "rgb": "640x360", "score_threshold": 0.25, "targets": 5}
    assert all(k in report for k in ("dependence", "sufficiency", "shapley", "lost_when_off"))  # {} if none attributed
    for cond, row in report["contributions"].items():  # whatever the untrained net detects
        assert set(row) == {"rgb", "thermal", "radar"} and sum(row.values()) == pytest.approx(1.0)
        assert 0 <= report["faithfulness"][cond] <= 1


def test_faithfulness_compares_the_top_two_ranked_sensors() -> None:
    from respecd.lab.detector.evaluate import _faithful, _matched_confidence

    ranking = np.array([[0.5, 0.3, 0.2], [0.1, 0.6, 0.3]])
    drops = np.array([[0.4, 0.1, 0.0], [0.5, 0.2, 0.1]])  # box 1: its top (thermal) costs less than rgb
    assert _faithful(ranking, drops) == [True, True]  # box 1 compares thermal (0.2) with radar (0.1)
    assert _faithful(ranking, np.array([[0.1, 0.4, 0.0], [0.5, 0.2, 0.3]])) == [False, False]
    targets = np.array([[0, 0, 10, 10], [50, 50, 60, 60]], np.float32)
    found = np.array([[1, 1, 10, 10], [0, 0, 5, 5], [20, 20, 30, 30]], np.float32)
    assert _matched_confidence(targets, found, np.array([0.7, 0.9, 0.8])).tolist() == pytest.approx([0.7, 0.0])


def test_recall_by_height_bins_people_by_their_share_of_the_frame() -> None:
    from respecd.lab.detector.evaluate import recall_by_height
    from respecd.lab.detector.metrics import ImageResult

    people = np.array([[0, 0, 10, 30], [50, 0, 60, 150], [100, 0, 140, 300], [200, 0, 210, 20]], np.float32)
    found = np.array([[0, 0, 10, 30], [50, 0, 60, 150], [100, 0, 140, 160]], np.float32)  # the third: IoU 0.53
    image = ImageResult(found, np.array([0.9, 0.2, 0.8]), people, np.array([False, False, False, True]))
    assert recall_by_height([image], 300) == {
        "0-0.1": [0, 0],  # the 20 px person is ignored
        "0.1-0.2": [1, 1],  # 30 px: found
        "0.2-0.4": [0, 0],
        "0.4-0.7": [0, 1],  # 150 px: boxed, but at 0.2 < the daemon's 0.25
        ">=0.7": [1, 1],  # 300 px: IoU 0.53 >= 0.5 counts
    }


def test_delivered_keeps_only_the_boxes_the_daemon_hands_on() -> None:
    from respecd.lab.detector.evaluate import delivered
    from respecd.lab.detector.metrics import ImageResult, average_precision

    people = np.array([[0, 0, 10, 30], [50, 0, 60, 150]], np.float32)
    found = np.array([[0, 0, 10, 30], [50, 0, 60, 150]], np.float32)
    image = ImageResult(found, np.array([0.9, 0.2], np.float32), people, np.zeros(2, bool))
    kept = delivered([image])[0]
    assert kept.pred_scores.tolist() == pytest.approx([0.9]) and kept.gt_boxes is image.gt_boxes
    assert average_precision([image], 0.5) == pytest.approx(1.0)  # ranked down to 0.2: both found
    assert average_precision([kept], 0.5) == pytest.approx(51 / 101)  # delivered: the 0.2 person is missed (101 points)


def test_false_boxes_are_split_into_second_misplaced_and_clutter() -> None:
    from respecd.lab.detector.metrics import ImageResult, false_box_kinds

    people = np.array([[0, 0, 40, 100], [200, 0, 240, 100], [400, 0, 440, 100]], np.float32)
    boxes = np.array([
        [0, 0, 40, 100],  # finds person 0
        [20, 0, 60, 100],  # same height, half a width aside: IoU 1/3 with person 0, already found -> second
        [215, 0, 255, 100],  # IoU 0.45 with person 1, whom nothing finds -> misplaced
        [600, 0, 640, 100],  # on nobody -> clutter
        [300, 0, 340, 100],  # also on nobody, but under the threshold: not counted
        [400, 0, 440, 100],  # on the ignored person 2: neither a hit nor a false box
    ], np.float32)
    scores = np.array([0.9, 0.8, 0.7, 0.6, 0.2, 0.9])
    image = ImageResult(boxes, scores, people, np.array([False, False, True]))
    assert false_box_kinds([image], 0.25) == {"second": 1, "misplaced": 1, "clutter": 1}
    # the weaker of two boxes on one person is the second, whichever comes first in the list
    swapped = ImageResult(boxes[[1, 0]], np.array([0.5, 0.9]), people[:1])
    assert false_box_kinds([swapped], 0.25) == {"second": 1, "misplaced": 0, "clutter": 0}
    assert false_box_kinds([ImageResult(boxes[3:4], scores[3:4], np.zeros((0, 4)))], 0.25)["clutter"] == 1


def test_eval_command_rejects_a_negative_world_seed(capsys) -> None:
    with pytest.raises(SystemExit) as stopped:  # argparse refuses it before the checkpoint loads
        cli_main(["eval", "--data", "sim", "--seed", "-1"])
    assert stopped.value.code == 2
    assert "argument --seed: expected an integer >= 0, got '-1'" in capsys.readouterr().err


def test_eval_command_rejects_a_bad_checkpoint(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00" * 10)
    assert cli_main(["eval", "--weights", str(bad), "--out", str(tmp_path)]) == 2
    assert "bad.pt: not a torch checkpoint: it looks like" in capsys.readouterr().err


def test_each_sensor_alone_is_an_ablation_and_one_pass_serves_equal_subsets() -> None:
    from respecd.lab.detector.data import Sample
    from respecd.lab.detector.evaluate import Evaluation, ablations
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.detector import FusionDetector

    three = ablations(("thermal", "radar"))
    assert three["thermal_only"] == ("rgb", "radar") and three["radar_only"] == ("rgb", "thermal")
    assert three["rgb_only"] == ("thermal", "radar")
    assert ablations(("thermal",))["thermal_only"] == ablations(("thermal",))["no_rgb"] == ("rgb",)
    spec = ModelSpec(**{**TINY.model_dump(), "aux_modalities": ("thermal",)})
    detector = FusionDetector(FusionNet(spec), PerceptionConfig(model=spec, score_threshold=0.01))
    evaluation = Evaluation(detector, 0.0)
    sample = Sample(np.random.default_rng(0).integers(0, 255, (4, 64, 96), dtype=np.uint8), np.ones(1, np.float32),
                    np.array([[10, 10, 40, 60]], np.float32), np.zeros(1, bool))
    evaluation.add_attributed(sample, ["all"])
    assert evaluation.ablation["all"]["thermal_only"][0] is evaluation.ablation["all"]["no_rgb"][0]
