"""Fit and check a detector's confidence calibration per RGB size on simulated validation worlds.

Every detection at each of the controller's RGB sizes (every sensor on, scored down to 0.01) is
matched to the ground truth as AP@0.5 matches it (a box on a person hidden behind a solid occluder
is neither); Platt scaling is fitted per size on (raw confidence, matched or not)
(``respecd.perception.calibration``). The report says per size what the map does at the
daemon's operating point: the raw confidence that now reaches the threshold, the calibration
error before and after, and mAP@0.5 of the boxes the daemon would deliver.
"""

from __future__ import annotations

import torch

from respecd.errors import InputError
from respecd.lab.detector.evaluate import OPERATING_THRESHOLD, Evaluation, delivered, sim_instants
from respecd.lab.detector.metrics import ImageResult, ap_parts, average_precision
from respecd.lab.detector.simdata import RESOLUTIONS
from respecd.perception.calibration import (
    ScoreCalibration,
    expected_calibration_error,
    fit_platt,
    platt,
    raw_confidence_for,
)
from respecd.perception.detector import FusionDetector

MIN_TRUE = 20  # fewer matched boxes than this at a size and its fit is noise: refuse


def resolution_images(detector: FusionDetector, per_scenario: int, seed: int,
                      progress: bool = False) -> dict[str, list[ImageResult]]:
    """Per RGB size ("WxH"), one result per held-out instant of world ``seed``, every sensor on."""
    evaluation = Evaluation(detector)
    for _, sample, conditions in sim_instants(detector, per_scenario, seed, list(RESOLUTIONS), progress):
        evaluation.add_resolution(sample, conditions[:1])  # "all" only
    return {size: by["all"] for size, by in evaluation.by_resolution.items()}


def fit(images: dict[str, list[ImageResult]]) -> ScoreCalibration:
    """Platt parameters per size; InputError when a size has too few matched boxes to fit."""
    table = {}
    for size, results in images.items():
        scores, tp, _ = ap_parts(results, 0.5)
        if tp.sum() < MIN_TRUE or (~tp).sum() < MIN_TRUE:
            raise InputError(f"calibration at {size}: {int(tp.sum())} matched and {int((~tp).sum())} false boxes; "
                             f"need at least {MIN_TRUE} of each (more --frames)")
        a, b = fit_platt(scores, tp)
        if a <= 0:
            raise InputError(f"calibration at {size}: fitted slope {a:.3f} <= 0: confidence does not predict a "
                             "match at this size; not calibrated")
        table[size] = (a, b)
    return ScoreCalibration(table)


def measure(images: dict[str, list[ImageResult]], calibration: ScoreCalibration,
            threshold: float = OPERATING_THRESHOLD) -> dict[str, dict[str, float]]:
    """Per size, raw against calibrated: the raw confidence that maps to ``threshold``, calibration
    error (10 bins) and mAP@0.5 of the boxes at or above ``threshold``."""
    out = {}
    for size, results in images.items():
        a, b = calibration.by_size[size]
        mapped = [_mapped(r, a, b) for r in results]
        scores, tp, _ = ap_parts(results, 0.5)
        cal_scores, cal_tp, _ = ap_parts(mapped, 0.5)
        out[size] = {
            "a": a, "b": b, "boxes": int(len(scores)), "matched": int(tp.sum()),
            "raw_confidence_at_threshold": raw_confidence_for(threshold, a, b),
            "ece_raw": expected_calibration_error(scores, tp),
            "ece_calibrated": expected_calibration_error(cal_scores, cal_tp),
            "delivered_map50_raw": average_precision(delivered(results, threshold), 0.5),
            "delivered_map50_calibrated": average_precision(delivered(mapped, threshold), 0.5),
        }
    return out


def _mapped(result: ImageResult, a: float, b: float) -> ImageResult:
    scores = platt(torch.from_numpy(result.pred_scores), a, b).numpy()
    return ImageResult(result.pred_boxes, scores, result.gt_boxes, result.gt_ignore)
