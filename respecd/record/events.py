"""respecd's own channels (percepts, decisions, applied configs, sync ticks) as JSON, and
detections as a ``foxglove.ImageAnnotations`` overlay for the RGB image they came from."""

from __future__ import annotations

from typing import Any

import foxglove.messages as fox

from respecd.messages import Bundle, Decision, Percept, SensorConfig
from respecd.record.codec import dumps, timestamp

_BOX_COLOR = fox.Color(r=0.1, g=0.9, b=0.2, a=1.0)
_TEXT_BG = fox.Color(r=0.0, g=0.0, b=0.0, a=0.6)
_WHITE = fox.Color(r=1.0, g=1.0, b=1.0, a=1.0)
LABEL_FONT_PX = 12.0


def config_dict(config: SensorConfig) -> dict[str, Any]:
    return {
        "modality": config.modality,
        "enabled": config.enabled,
        "rate_hz": config.rate_hz,
        "resolution": list(config.resolution) if config.resolution else None,
        "mode": config.mode,
        "notes": list(config.notes),
    }


def encode_config(sensor: str, t: float, config: SensorConfig) -> bytes:
    return dumps({"t": t, "sensor": sensor, **config_dict(config)})


def encode_percept(p: Percept) -> bytes:
    rgb = p.bundle.frames.get("rgb") if p.bundle is not None else None
    return dumps({
        "t": p.t,
        "conf_agg": p.conf_agg,
        "latency_s": p.latency,
        "contributions": p.contributions,
        "dependence": p.dependence,
        "sufficiency": p.sufficiency,
        "detections": [
            {"box": list(d.box), "confidence": d.confidence, "label": d.label} for d in p.detections
        ],
        "pixels": int(rgb.data.shape[0] * rgb.data.shape[1]) if rgb is not None else 0,
    })


def encode_annotations(p: Percept, log_ns: int) -> bytes:
    """Boxes and "person 0.87" texts (bottom-left anchored, just above each box) over the RGB
    image, stamped like that image."""
    ts = timestamp(log_ns)
    points, texts = [], []
    for d in p.detections:
        x1, y1, x2, y2 = (float(v) for v in d.box)
        corners = [fox.Point2(x=x1, y=y1), fox.Point2(x=x2, y=y1), fox.Point2(x=x2, y=y2), fox.Point2(x=x1, y=y2)]
        points.append(fox.PointsAnnotation(timestamp=ts, type=fox.PointsAnnotationType.LineLoop, points=corners,
                                           outline_color=_BOX_COLOR, thickness=2.0))
        texts.append(fox.TextAnnotation(timestamp=ts, position=fox.Point2(x=x1, y=max(LABEL_FONT_PX, y1 - 2.0)),
                                        text=f"{d.label} {d.confidence:.2f}", font_size=LABEL_FONT_PX,
                                        text_color=_WHITE, background_color=_TEXT_BG))
    return fox.ImageAnnotations(timestamp=ts, points=points, texts=texts).encode()


def encode_decision(d: Decision) -> bytes:
    return dumps({
        "t": d.t,
        "state": list(d.state),
        "action": d.action,
        "reward": d.reward,
        "epsilon": d.epsilon,
        "q_values": list(d.q_values),
        "terms": d.terms,
        "configs": [config_dict(c) for c in d.configs],
    })


def encode_bundle(b: Bundle) -> bytes:
    return dumps({
        "t": b.t,
        "seq": b.seq,
        "rate_hz": b.sync.rate_hz,
        "jitter_ms": b.sync.jitter_ms,
        "stale_ratio": b.sync.stale_ratio,
        "health": b.sync.health.value,
        "frames": {m: [f.t, f.seq] for m, f in b.frames.items()},
    })
