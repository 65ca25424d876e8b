"""Named configurations of the whole pipeline, and the one resolver of its settings.

``MarkerPose(rig, preset=NAME)`` picks one of :data:`PRESETS`: each is a small diff from
the stages' defaults (``"default"`` is the empty diff), described once in :data:`ABOUT`.
The paper's two configurations stay runnable beside ours. The ablations that switch off
one of our improvements at a time live with the experiments that measure them
(:mod:`markerpose.experiments.configs`).

:func:`resolve` merges the defaults, a preset and a caller's overrides and checks every
value against its stage's rules (:mod:`markerpose.settings`); the API and the command
line's ``--set`` both go through it.
"""

from __future__ import annotations

import copy
import math

from . import detectors, settings
from .nets import BACKENDS
from .settings import Rule, choice, number
from .stages import STAGES, match, propose, refine, solve, track, verify

PAPER_POSE = {"pose": "paper", "bias_correction": False}

PRESETS: dict[str, dict] = {
    "default": {},
    "paper": {
        "match": {"method": "head"},
        "propose": {"second_look": 1.0, **propose.PAPER_NETWORK},
        "refine": {"patch": "fixed", "fit": "ellipse", "edge_refit": False},
        "solve": PAPER_POSE,
        "verify": {"max_residual_px": math.inf},  # the paper gives every pose it solves
    },
    "paper-classical": {
        "detector": "classical",
        "refine": {"subpixel": False},
        "solve": PAPER_POSE,
        "verify": {"max_residual_px": math.inf},
    },
    "classical": {"detector": "classical"},
    "default-bf16": {"backend": "openvino-bf16"},
    "default-float32": {"propose": {"int8": False}},
    "default-lite": {"propose": {"network": "lite"}},
}

ABOUT: dict[str, str] = {
    "default": "ours: stage-1 candidates (the fast network at the image's aspect, int8 in its wide layers) of both views matched by the marker's 3D shape, the rings' edges fitted from the "
    "ellipses the three points predict (EllipSegNet's masks where that fails), blurred-ring fit (of the sampled blocks' means), plate check, "
    "perspective-bias correction, rigid pose; a second look at twice the input's size when nothing is found",
    "paper": "the paper's MarkerPose: ring IDs from the ID head, EllipSegNet on fixed 120 px patches with cv2.fitEllipse, "
    "DLT of the ellipse centres, R = [x y x×y]",
    "paper-classical": "the paper's classical detector (§3.4): binarisation, contours, concentric ellipses, epipolar pairing; paper pose",
    "classical": "the classical detector with our sub-pixel edges, blurred-ring fit, bias correction and rigid pose",
    "default-float32": "default with stage 1's network in float32 throughout (the former default)",
    "default-bf16": "default with the networks in bfloat16 on OpenVINO (the openvino extra): faster on CPUs with AMX",
    "default-lite": "default with the lite stage-1 network (a quarter of the paper's widths, an eighth in the first four "
    "convolutions; the default's fast network has three eighths)",
}

ORDER = tuple(PRESETS)  # the order reports list them in

_STAGE_MODULES = dict(zip(STAGES, (propose, match, refine, verify, solve, track)))
TOP_RULES: dict[str, Rule] = {
    # "neural" (stage 1: the stereo or the decoded detector), "classical" (paper §3.4), or
    # the name of any other detector in markerpose.detectors.DETECTORS
    "detector": Rule(lambda v: None if v in ("neural", *detectors.DETECTORS) else f"one of {['neural', *detectors.DETECTORS]}"),
    "threads": Rule(lambda v: None if v is None else number(1, integer=True).test(v)),  # the networks' threads (None: every core)
    "backend": choice(*BACKENDS),  # what runs the networks
}
default_conf = {
    "detector": "neural",
    "threads": None,
    "backend": "onnxruntime",
    **{name: module.default_conf for name, module in _STAGE_MODULES.items()},
}


def is_neural(diff: dict) -> bool:
    """Whether a preset's (or an ablation's) diff uses the networks."""
    return diff.get("detector", "neural") == "neural"


def check(name: str) -> str:
    """``name`` if it is a preset, else ``ValueError`` listing them."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {list(ORDER)}")
    return name


def resolve(preset: str = "default", detector: str | None = None, **overrides) -> dict:
    """The full configuration: the stages' defaults, the preset's diff, then ``overrides``
    (``detector``, ``threads``, ``backend`` and one dict per stage), every value checked
    (``ValueError`` naming the stage, the key and what it takes)."""
    conf = copy.deepcopy(default_conf)
    if detector is not None and preset == "default":
        preset = "classical" if detector == "classical" else "default"  # the shorthand
    for diff in (PRESETS[check(preset)], overrides):
        for key, value in diff.items():
            if key not in conf:
                stage = next((s for s in STAGES if key in default_conf[s]), None)
                hint = f" (now {stage}={{{key!r}: ...}})" if stage else ""
                raise ValueError(f"unknown option {key!r}{hint}; known: {sorted(default_conf)}")
            if key in TOP_RULES:
                conf[key] = value
            elif not isinstance(value, dict):
                raise ValueError(f"{key} takes a dict of settings, got {value!r}")
            else:
                conf[key].update(settings.check(key, value, _STAGE_MODULES[key].RULES))
    if detector is not None:
        conf["detector"] = detector
    settings.check("MarkerPose", {k: conf[k] for k in TOP_RULES}, TOP_RULES)
    return conf


__all__ = ["ABOUT", "ORDER", "PAPER_POSE", "PRESETS", "TOP_RULES", "check", "default_conf", "is_neural", "resolve"]
