"""Synthetic stereo world: renderer and scene generators with exact ground truth."""

from .background import clutter_background
from .render import Imaging, StereoFrame, ViewTruth, look_at_pose, motion_kernel, render_stereo, render_view, sensor_readout
from .target import render_target_view

__all__ = [
    "Imaging",
    "StereoFrame",
    "ViewTruth",
    "clutter_background",
    "look_at_pose",
    "motion_kernel",
    "render_stereo",
    "render_target_view",
    "render_view",
    "sensor_readout",
]
