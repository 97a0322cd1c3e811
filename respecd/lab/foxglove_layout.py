"""The Foxglove layout shipped as ``docs/foxglove-layout.json``, built with foxglove-sdk's
own layout types: ``python -m respecd.lab.foxglove_layout > docs/foxglove-layout.json``.

Top row: the RGB image with the detection boxes and texts, the thermal display image, and
the 3D view (``base_link``) with the radar points placed by ``/tf`` and the RGB camera's
frustum from its calibration. Bottom row: plots of the per-modality contributions, of what
each modality's detections depend on (the confidence lost with it off, solid; kept with only
it on, dashed: two sensors that each suffice show high dashed and low solid lines), ConfAgg,
the controller's reward, and the rate each sensor really applied.
"""

from __future__ import annotations

import foxglove.layouts as fl

from respecd.record.topics import TOPIC_CONFIG, TOPIC_DECISION, TOPIC_DETECTIONS, TOPIC_PERCEPT, sensor_topic

MODALITIES = ("rgb", "thermal", "radar", "depth")
REDUNDANCY_LINES = (("dependence", "off", "solid"), ("sufficiency", "alone", "dashed"))  # Percept field, label, line
COLORS = {"rgb": "#e15759", "thermal": "#f28e2b", "radar": "#4e79a7", "depth": "#59a14f"}


def _series(path: str, label: str, **style: str) -> fl.PlotSeries:
    return fl.PlotSeries(value=path, label=label, **style)  # type: ignore[arg-type]


def build(rgb: str = "rgb", thermal: str = "thermal", radar: str = "radar") -> fl.Layout:
    image = fl.ImagePanel(title="RGB + detections", config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
        image_topic=sensor_topic(rgb), calibration_topic=f"{sensor_topic(rgb)}/calibration",
        annotations={TOPIC_DETECTIONS: fl.ImageAnnotationSettings(visible=True)})))
    ir = fl.ImagePanel(title="thermal (inferno over perception.thermal_range_k)", config=fl.ImageConfig(
        image_mode=fl.ImageModeConfig(image_topic=f"{sensor_topic(thermal)}/colormap")))
    scene = fl.ThreeDeePanel(title="3D: radar points in front of the camera", config=fl.ThreeDeeConfig(
        follow_tf="base_link", topics={
            sensor_topic(radar): fl.BaseRendererPointCloudTopicSettings(
                visible=True, point_size=6, color_mode="colormap", color_field="snr", color_map="turbo"),
            f"{sensor_topic(rgb)}/calibration": fl.BaseRendererCameraTopicSettings(visible=True),
        }))
    contributions = fl.PlotPanel(title="contribution per modality", config=fl.PlotConfig(paths=[
        _series(f"{TOPIC_PERCEPT}.contributions.{m}", m) for m in MODALITIES]))
    redundancy = fl.PlotPanel(title="lost with it off (solid) / kept with only it on (dashed)", config=fl.PlotConfig(
        min_y_value=0, max_y_value=1, paths=[
            _series(f"{TOPIC_PERCEPT}.{field}.{m}", f"{m} {word}", color=COLORS[m], line_style=style)
            for m in MODALITIES for field, word, style in REDUNDANCY_LINES]))
    quality = fl.PlotPanel(title="ConfAgg and reward", config=fl.PlotConfig(paths=[
        _series(f"{TOPIC_PERCEPT}.conf_agg", "ConfAgg"), _series(f"{TOPIC_DECISION}.reward", "reward")]))
    rates = fl.PlotPanel(title="applied rate (Hz)", config=fl.PlotConfig(paths=[
        _series(f'{TOPIC_CONFIG}{{sensor=="{m}"}}.rate_hz', m) for m in MODALITIES]))
    top = fl.SplitContainer(direction="row", items=[
        fl.SplitItem(content=image, proportion=2), fl.SplitItem(content=ir), fl.SplitItem(content=scene, proportion=2)])
    bottom = fl.SplitContainer(direction="row", items=[
        fl.SplitItem(content=contributions), fl.SplitItem(content=redundancy), fl.SplitItem(content=quality),
        fl.SplitItem(content=rates)])
    return fl.Layout(content=fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=top, proportion=3), fl.SplitItem(content=bottom, proportion=2)]))


def layout_json() -> str:
    import json

    return json.dumps(json.loads(build().to_json()), indent=2) + "\n"


if __name__ == "__main__":
    print(layout_json(), end="")
