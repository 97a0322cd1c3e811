"""``fleet eval``: ``evaluate`` on every log, a report per log and one pooled over them.

``eval_log`` is the per-log task a backend runs; it never raises: a damaged, foreign or
mismatched log comes back as one line of why (its path replaced by its name, so two runs
compare equal wherever the logs were). ``pooled`` gives each of the replay's metrics as mean,
spread, min and max over the logs that ran, and the detections matched over all of them;
what this machine's speed decides is under ``timing``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import structlog

from respecd.control.persist import StoredTable
from respecd.errors import ConfigError, InputError
from respecd.lab.fleet import worker
from respecd.lab.fleet.backends import WorkerLost
from respecd.lab.fleet.logs import LogRef, local_copy

log = structlog.get_logger(__name__)

# (label, path into a replay result): the metrics pooled over logs
METRICS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("f1", ("quality", "f1")),
    ("precision", ("quality", "precision")),
    ("recall", ("quality", "recall")),
    ("mean_conf_agg", ("quality", "mean_conf_agg")),
    ("sensor_w", ("energy", "mean_w")),
    ("sensor_j", ("energy", "total_j")),
    ("percepts", ("compute", "percepts")),
    ("pixels_per_s", ("compute", "pixels_per_s")),
    ("switches", ("actions", "switches")),
    ("decisions", ("n_decisions",)),
    ("unserved_s", ("n_unserved_s",)),
    ("replayed_s", ("replayed_s",)),
)


@dataclass(frozen=True)
class EvalSpec:
    """What every log is evaluated with (sent to each worker once)."""

    policy: str | None = None
    profile: dict[str, Any] | None = None  # None: each log's recorded profile
    table: StoredTable | None = None
    seed: int = 0
    duration: float | None = None
    topics: str | None = None
    allow_no_table: bool = False


@dataclass(frozen=True)
class Outcome:
    """One log's answer: its report, or why there is none."""

    name: str
    error: str | None
    report: dict[str, Any] | None
    timing: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {"log": self.name, "error": self.error, "report": self.report, "timing": self.timing}


def eval_log(spec: EvalSpec, ref: LogRef) -> Outcome:
    """``evaluate`` one log (a backend's task): never raises, an error is the outcome's reason."""
    from respecd.replay.evaluate import evaluate

    began = time.perf_counter()
    error, report = None, None
    try:
        with local_copy(ref) as path:
            try:
                result = evaluate(path, spec.profile, spec.policy, spec.table, spec.seed, duration=spec.duration,
                                  topics=spec.topics, allow_no_table=spec.allow_no_table)
            except (InputError, ConfigError) as err:
                error = _reason(err, path, ref)
            except Exception as err:  # noqa: BLE001 - one log's failure, whatever it is, must not stop the fleet
                log.exception("fleet.log_failed", log=ref.name)
                error = f"{type(err).__name__}: {_reason(err, path, ref)}"
            else:
                error = _damage(result.result)
                if error is None:
                    result = replace(result, log={**result.log, "name": ref.name})
                    report = {"log": result.log, **result.entry()}
    except InputError as err:  # an object store's log that could not be fetched
        error = str(err)
    timing = {"task_s": round(time.perf_counter() - began, 4), "worker": worker.task_done()}
    return Outcome(ref.name, error, report, timing)


def _damage(result: dict[str, Any]) -> str | None:
    """Why a log that replayed only in part is no result of the fleet's (its numbers would skew the pool)."""
    if result.get("truncated"):
        return (f"damaged: cut short (no summary); only its first {result['replayed_s']:.2f} s could be read "
                "(respecd --replay replays that part)")
    if result.get("damage"):
        return f"damaged: {len(result['damage'])} stretch(es) unreadable, skipped: {'; '.join(result['damage'])}"
    return None


def _reason(err: BaseException, path: Any, ref: LogRef) -> str:
    problems = getattr(err, "problems", None) or [str(err)]
    text = "; ".join(str(p) for p in problems)
    return text.replace(str(path), ref.name).replace(ref.location, ref.name)


def outcome_of(ref: LogRef, answer: Any) -> Outcome:
    """A backend's answer for ``ref``: the outcome, or a lost worker as that log's error."""
    if isinstance(answer, WorkerLost):
        return Outcome(ref.name, answer.reason, None, {})
    return answer


def pooled(outcomes: Sequence[Outcome]) -> dict[str, Any]:
    """The metrics over the logs that ran: mean, spread (population SD), min, max; and the
    detections matched over all of them (micro precision, recall, F1). In name order."""
    ran = sorted((o for o in outcomes if o.report is not None), key=lambda o: o.name)
    failed = sorted(o.name for o in outcomes if o.report is None)
    metrics = {label: _spread([_metric(o.report, path) for o in ran]) for label, path in METRICS}
    tp, fp, fn = (sum(o.report["quality"][k] for o in ran) for k in ("tp", "fp", "fn"))  # type: ignore[index]
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    policies = sorted({o.report["policy"] for o in ran})  # type: ignore[index]
    references = sorted({o.report["reference"] for o in ran})  # type: ignore[index]
    timing = {"task_s": _spread([o.timing.get("task_s", 0.0) for o in ran]),
              "wall_s": _spread([o.report["timing"].get("wall_s", 0.0) for o in ran])}  # type: ignore[index]
    return {
        "logs": len(outcomes), "ran": len(ran), "failed": failed, "policy": policies, "reference": references,
        "metrics": metrics,
        "matched": {"tp": tp, "fp": fp, "fn": fn, "precision": round(precision, 4), "recall": round(recall, 4),
                    "f1": round(f1, 4)},
        "timing": timing,
    }


def strip_timing(value: Any) -> Any:
    """``value`` without any ``timing`` key at any depth: what two runs must agree on."""
    if isinstance(value, dict):
        return {k: strip_timing(v) for k, v in value.items() if k != "timing"}
    if isinstance(value, list):
        return [strip_timing(v) for v in value]
    return value


def _metric(report: dict[str, Any] | None, path: tuple[str, ...]) -> float:
    assert report is not None
    if path == ("n_decisions",):
        return float(len(report.get("decisions", [])))
    if path == ("n_unserved_s",):
        return float(sum(u["seconds"] for u in (report.get("unserved") or {}).values()))
    value: Any = report
    for key in path:
        value = value[key]
    return float(value)


def _spread(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"mean": None, "sd": None, "min": None, "max": None}
    mean = math.fsum(values) / len(values)
    sd = math.sqrt(math.fsum((v - mean) ** 2 for v in values) / len(values))
    return {"mean": round(mean, 6), "sd": round(sd, 6), "min": min(values), "max": max(values)}
