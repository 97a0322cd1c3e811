"""Topic names of a respecd log (MCAP file and live view alike)."""

from __future__ import annotations

TOPIC_PERCEPT = "/respecd/percept"
TOPIC_DECISION = "/respecd/decision"
TOPIC_CONFIG = "/respecd/config"
TOPIC_SYNC = "/respecd/sync"
TOPIC_DETECTIONS = "/respecd/detections"  # ImageAnnotations over the RGB channel, for Foxglove
TOPIC_TF = "/tf"  # foxglove.FrameTransforms from the profile's extrinsics
OWN_TOPICS = (TOPIC_PERCEPT, TOPIC_DECISION, TOPIC_CONFIG, TOPIC_SYNC)


def sensor_topic(sensor: str) -> str:
    return f"/sensors/{sensor}"


def raw_topic(sensor: str) -> str:
    """Radar UART bytes of a frame."""
    return f"/sensors/{sensor}/raw"


def meta_topic(sensor: str) -> str:
    """respecd.FrameMeta: exact time, sequence and driver meta of each frame."""
    return f"/sensors/{sensor}/meta"


def colormap_topic(sensor: str) -> str:
    """A thermal camera's display image (colormapped JPEG), beside the raw one."""
    return f"/sensors/{sensor}/colormap"


def calibration_topic(sensor: str) -> str:
    return f"/sensors/{sensor}/calibration"
