"""The Foxglove layout for a hand, built with the SDK's layout classes.

``docs/foxglove/handctl_layout.json`` is this module's output for the default hand (a test
keeps the two equal); ``handctl layout HAND.yaml -o OUT.json`` writes the layout of any
other hand. One plot per finger, the joints in the same three colours in every
finger, and for each joint its desired (dashed), applied (solid) and measured (dotted, the TDT)
torque, with thin lines at +-tau_max, the host limit.
"""

from __future__ import annotations

import foxglove.layouts as fl

from handctl.config import FingerConfig, HandConfig
from handctl.foxglove.derived import JOINTS, LOG, SCENE
from handctl.foxglove.scene import WORLD
from handctl.recording import channels as ch

#: By a joint's place in its finger: proximal, middle, distal, then more if a finger has them.
JOINT_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")


def _finger_plot(finger: FingerConfig) -> fl.PlotPanel:
    series = []
    for k, joint in enumerate(finger.joints):
        colour = JOINT_COLOURS[k % len(JOINT_COLOURS)]
        base = f"{JOINTS}.{joint.name}"
        series += [
            fl.PlotSeries(
                value=f"{base}.desired_nm",
                label=f"{joint.name} desired",
                color=colour,
                line_style="dashed",
                line_size=1.0,
            ),
            fl.PlotSeries(
                value=f"{base}.applied_nm",
                label=f"{joint.name} applied",
                color=colour,
                line_style="solid",
                line_size=1.5,
            ),
            fl.PlotSeries(
                value=f"{base}.tdt_torque_nm",
                label=f"{joint.name} measured",
                color=colour,
                line_style="dotted",
                line_size=1.0,
            ),
            fl.PlotSeries(
                value=f"{base}.tau_max_nm",
                label=f"{joint.name} +tau_max",
                color=colour,
                line_style="solid",
                line_size=0.5,
            ),
            fl.PlotSeries(
                value=f"{base}.tau_max_nm.@negative",
                label=f"{joint.name} -tau_max",
                color=colour,
                line_style="solid",
                line_size=0.5,
            ),
        ]
    return fl.PlotPanel(
        title=f"{finger.name} torque (N·m)",
        config=fl.PlotConfig(paths=series, show_legend=True, legend_display="top", is_synced=True),
    )


def build_layout(hand: HandConfig) -> fl.Layout:
    scene = fl.ThreeDeePanel(
        title="hand (hand plane: x right, y up)",
        config=fl.ThreeDeeConfig(
            follow_tf=WORLD, topics={SCENE: fl.BaseRendererSceneUpdateTopicSettings(visible=True)}
        ),
    )
    state = fl.StateTransitionsPanel(
        title="phase and safety state",
        config=fl.StateTransitionsConfig(
            paths=[
                fl.StateTransitionsSeries(value=f"{ch.PHASE}.phase", label="phase"),
                fl.StateTransitionsSeries(value=f"{ch.SAFETY}.state", label="safety"),
            ],
            is_synced=True,
        ),
    )
    log = fl.LogPanel(title="events and faults", config=fl.LogConfig(topic_to_render=LOG))
    plots = [fl.SplitItem(content=_finger_plot(f)) for f in hand.fingers]
    left = fl.SplitContainer(
        direction="column",
        items=[
            fl.SplitItem(proportion=3, content=scene),
            fl.SplitItem(proportion=1, content=state),
            fl.SplitItem(proportion=1, content=log),
        ],
    )
    return fl.Layout(
        content=fl.SplitContainer(
            direction="row",
            items=[
                fl.SplitItem(proportion=1, content=left),
                fl.SplitItem(
                    proportion=1, content=fl.SplitContainer(direction="column", items=plots)
                ),
            ],
        )
    )


#: the top-level keys of every layout ``layout_json`` writes (the SDK's layout JSON): what
#: tells an earlier layout, which ``handctl layout -o`` may replace, from other JSON
LAYOUT_KEYS = frozenset({"version", "content"})


def layout_json(hand: HandConfig) -> str:
    import json

    return json.dumps(json.loads(build_layout(hand).to_json()), indent=2) + "\n"
