"""The once-per-second status line: what each sensor is asked and really does, sync health,
drops, detections, contributions and the controller's action.

``snapshot`` gathers plain fields (logged as JSON under systemd); ``format_line`` renders
them for a person at a terminal and for systemd's STATUS=.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from respecd.drivers.base import Driver
from respecd.messages import Decision, Percept, SensorConfig, SyncStats

if TYPE_CHECKING:
    from respecd.pipeline import Pipeline

MODALITY_ABBREV = {"rgb": "rgb", "thermal": "th", "radar": "rad", "depth": "dep", "imu": "imu"}


def describe_setting(config: SensorConfig) -> str:
    if not config.enabled:
        return "off"
    if config.resolution is not None:
        return f"{config.resolution[0]}x{config.resolution[1]}"
    if config.mode is not None:
        return config.mode
    return "-"


def sensor_fields(driver: Driver, applied: SensorConfig) -> dict[str, Any]:
    """One sensor's fields: ``applied`` is what it runs (the session's applied configs)."""
    health = driver.health
    measured = health.resolution
    return {
        "setting": describe_setting(applied),
        "measured_resolution": f"{measured[0]}x{measured[1]}" if measured else None,
        "rate_hz": round(applied.rate_hz, 1),
        "measured_hz": round(health.meter.rate_hz, 1),
        "frames": health.frames,
        "errors": health.errors,
        "paused": health.paused,
        "last_error": health.last_error,
    }


def snapshot(
    t: float,
    drivers: Mapping[str, Driver],
    sync: SyncStats,
    drops: Mapping[str, int],
    percept: Percept | None,
    decision: Decision | None,
    action_name: str | None = None,
    applied: Mapping[str, SensorConfig] | None = None,
) -> dict[str, Any]:
    applied = applied if applied is not None else {n: d.applied for n, d in drivers.items()}
    fields: dict[str, Any] = {
        "t": round(t, 1),
        "sensors": {name: sensor_fields(d, applied[name]) for name, d in drivers.items()},
        "sync": {
            "rate_hz": round(sync.rate_hz, 1),
            "health": sync.health.value,
            "jitter_ms": round(sync.jitter_ms, 2),
            "stale": round(sync.stale_ratio, 3),
        },
        "drops": dict(drops),
    }
    if percept is not None:
        fields["detections"] = len(percept.detections)
        fields["conf_agg"] = round(percept.conf_agg, 3)
        fields["latency_ms"] = round(percept.latency * 1000, 1)
        if percept.contributions:
            fields["contributions"] = {k: round(v, 3) for k, v in percept.contributions.items() if k in MODALITY_ABBREV}
    if decision is not None:
        fields["action"] = action_name if action_name is not None else decision.action
        fields["reward"] = round(decision.reward, 3)
        fields["epsilon"] = round(decision.epsilon, 3)
    return fields


def pipeline_fields(pipeline: Pipeline, recorder_dropped: int = 0,
                    recording: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``snapshot`` of a running pipeline, with the recorder's drops and state when there is one."""
    drops = {name: q.dropped for name, q in pipeline.frame_queues.items() if q.dropped}
    drops["bundles"] = pipeline.bundles.dropped
    if recorder_dropped:
        drops["recorder"] = recorder_dropped
    controller = pipeline.controller
    decision = controller.last if controller is not None else None
    action_name = controller.describe_action(decision.action) if controller is not None and decision else None
    fields = snapshot(pipeline.clock.now(), pipeline.drivers, pipeline.synchronizer.last_stats, drops,
                      pipeline.perception.last if pipeline.perception is not None else None, decision,
                      action_name, pipeline.applied)
    if recording is not None:
        fields["recording"] = recording
    unsaved = controller.table_status() if controller is not None and hasattr(controller, "table_status") else None
    if unsaved is not None:  # the state directory refuses the Q-table's saves
        fields["qtable"] = unsaved
    return fields


def format_line(fields: Mapping[str, Any], modalities: Mapping[str, str]) -> str:
    parts = [f"t={fields['t']:.0f}s"]
    for name, s in fields["sensors"].items():
        label = MODALITY_ABBREV.get(modalities.get(name, ""), name)
        state = " PAUSED" if s["paused"] else ""
        errors = f" err={s['errors']}" if s["errors"] else ""
        setting = s["setting"]
        if s["measured_resolution"] and s["measured_resolution"] != setting and setting != "off":
            setting = f"{setting}→{s['measured_resolution']}"  # the device delivers another size
        parts.append(f"{label} {setting} {s['rate_hz']:g}/{s['measured_hz']:.1f}Hz{state}{errors}")
    sync = fields["sync"]
    parts.append(f"sync {sync['rate_hz']:g}Hz {sync['health']} j={sync['jitter_ms']:.1f}ms stale={sync['stale']:.0%}")
    parts.append("drops " + " ".join(f"{k}={v}" for k, v in fields["drops"].items()))
    if "detections" in fields:
        parts.append(f"det={fields['detections']} conf={fields['conf_agg']:.2f} {fields['latency_ms']:.0f}ms")
    if "contributions" in fields:
        contrib = " ".join(
            f"{MODALITY_ABBREV[k]}={v:.2f}" for k, v in fields["contributions"].items() if k in MODALITY_ABBREV
        )
        parts.append(f"contrib {contrib}")
    if "recording" in fields:
        parts.append(_recording(fields["recording"]))
    if "action" in fields:
        parts.append(f"action {fields['action']} r={fields['reward']:+.2f}")
    if "qtable" in fields:
        parts.append(f"qtable UNSAVED {fields['qtable']['since_s']:.0f}s ({fields['qtable']['error']})")
    return " | ".join(parts)


def _recording(r: Mapping[str, Any]) -> str:
    """What the recorder really has on disk, and why it is not recording if it is not."""
    if r["state"] not in ("recording", "paused"):
        return f"rec {r['state']}"
    paused = f" PAUSED ({r['reason']})" if r["state"] == "paused" else ""
    lost = f" lost={r['lost']}" if r.get("lost") else ""
    return f"rec{paused} {r['mib']:g}MiB {r['messages']}msg{lost}"
