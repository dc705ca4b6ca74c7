"""The Foxglove layout shipped as ``deploy/foxglove/jitterguard.json``: the 3D view, a z-score plot and the state
table, built with the foxglove-sdk's layout types so that it stays in step with the topics :mod:`.scene` writes.

Regenerate after changing a topic: ``python -m jitterguard.services.foxglove.layout > deploy/foxglove/jitterguard.json``
(a test fails while the shipped file differs from this).
"""

from __future__ import annotations

import json

import foxglove.layouts as fl

from .scene import DETECTIONS, EGO_FRAME, GROUNDTRUTH, MOTION, POINTS, TRACKS


def layout() -> fl.Layout:
    three_d = fl.ThreeDeePanel(title="jitterguard 3D", config=fl.ThreeDeeConfig(
        follow_tf=EGO_FRAME,
        follow_mode="follow-pose",
        camera_state=fl.ThreeDeeCameraState(distance=70.0, perspective=True, phi=40.0, theta_offset=0.0,
                                            target_offset=(0.0, 0.0, 0.0)),
        topics={
            POINTS: fl.BaseRendererPointCloudTopicSettings(visible=True, point_size=2.0, color_mode="colormap",
                                                           color_field="intensity", color_map="turbo"),
            DETECTIONS: fl.BaseRendererSceneUpdateTopicSettings(visible=True, show_outlines=True),
            TRACKS: fl.BaseRendererSceneUpdateTopicSettings(visible=True, show_outlines=True),
            GROUNDTRUTH: fl.BaseRendererSceneUpdateTopicSettings(visible=True, show_outlines=True),
        },
    ))
    plot = fl.PlotPanel(title="z per track (dynamic above α)", config=fl.PlotConfig(
        paths=[
            fl.PlotSeries(value=f"{MOTION}.z_by_track", label="z", dynamic_label_field="label",
                          dynamic_value_field="value", show_line=True),
            fl.PlotSeries(value=f"{MOTION}.alpha_max", label="α (largest in the frame)", line_style="dashed",
                          color="#ffffff"),
        ],
        x_axis_val="timestamp", show_legend=True, legend_display="floating", min_y_value=0.0,
    ))
    table = fl.TablePanel(title="tracks: state and statistics", config=fl.TableConfig(topic_path=f"{MOTION}.tracks"))
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d),
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=1, content=plot), fl.SplitItem(proportion=1, content=table)])),
    ]))


def layout_json() -> str:
    """The layout as the pretty-printed JSON file Foxglove imports (Layouts → Import from file)."""
    return json.dumps(json.loads(layout().to_json()), indent=2) + "\n"


if __name__ == "__main__":
    print(layout_json(), end="")
