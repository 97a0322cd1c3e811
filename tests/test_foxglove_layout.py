"""The shipped Foxglove layout is the one the code builds, and it points at topics a
recording of the simulated rover really has."""

from __future__ import annotations

import json
from pathlib import Path

from respecd.lab.foxglove_layout import layout_json

SHIPPED = Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json"


def _topics(node: object) -> set[str]:
    found: set[str] = set()
    if isinstance(node, dict):
        for key, value in node.items():
            if isinstance(value, str) and value.startswith("/") and key in ("imageTopic", "calibrationTopic", "value"):
                found.add(value.split(".")[0].split("{")[0])
            if key in ("annotations", "topics") and isinstance(value, dict):
                found.update(value)
            found |= _topics(value)
    elif isinstance(node, list):
        for item in node:
            found |= _topics(item)
    return found


def test_shipped_layout_is_current() -> None:
    regenerate = "python -m respecd.lab.foxglove_layout > docs/foxglove-layout.json"
    assert SHIPPED.read_text() == layout_json(), f"run: {regenerate}"


def test_layout_topics_are_recorded_channels() -> None:
    recorded = {"/sensors/rgb", "/sensors/rgb/calibration", "/sensors/thermal/colormap", "/sensors/radar",
                "/respecd/detections", "/respecd/percept", "/respecd/decision", "/respecd/config"}
    assert _topics(json.loads(SHIPPED.read_text())) == recorded


def test_percept_plots_read_fields_the_percept_channel_has() -> None:
    """Each plotted ``/respecd/percept.FIELD...`` is a field of respecd.Percept: dependence and sufficiency beside
    the contributions."""
    from respecd.record.schemas import json_schema

    percept = json_schema("respecd.Percept")
    paths = _values(json.loads(SHIPPED.read_text()))
    fields = {path.split(".")[1] for path in paths if path.startswith("/respecd/percept.")}
    assert fields == {"contributions", "dependence", "sufficiency", "conf_agg"} and fields <= set(percept["properties"])


def _values(node: object) -> list[str]:
    if isinstance(node, dict):
        return [v for k, v in node.items() if k == "value" and isinstance(v, str)] + [
            x for v in node.values() for x in _values(v)]
    if isinstance(node, list):
        return [x for item in node for x in _values(item)]
    return []
