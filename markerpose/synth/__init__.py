"""Synthetic stereo world: renderer and scene generators with exact ground truth."""

from .background import clutter_background
from .render import (
    Imaging,
    StereoFrame,
    ToolsFrame,
    ToolTruth,
    ViewTruth,
    look_at_pose,
    motion_kernel,
    render_stereo,
    render_tools,
    render_view,
    sensor_readout,
)
from .target import render_target_view

__all__ = [
    "Imaging",
    "StereoFrame",
    "ToolTruth",
    "ToolsFrame",
    "ViewTruth",
    "clutter_background",
    "look_at_pose",
    "motion_kernel",
    "render_stereo",
    "render_target_view",
    "render_tools",
    "render_view",
    "sensor_readout",
]
