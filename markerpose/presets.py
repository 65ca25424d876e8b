"""Named configurations of the whole pipeline: ``MarkerPose(rig, preset=NAME)``.

Each preset is a small diff from the stages' defaults (``"default"`` is the empty diff).
The paper's two configurations stay runnable beside ours, and each ablation preset
switches off one of our improvements, so every gain is measured in the same run on the
same frames. :data:`ORDER` is the order reports list them in.
"""

from __future__ import annotations

import copy

from .nets import BACKENDS
from .stages import STAGES, match, propose, refine, solve, track, verify

PAPER_POSE = {"pose": "paper", "bias_correction": False}
_NO_EDGE = {"edge_refit": False}

PRESETS: dict[str, dict] = {
    # Ours: stage-1 candidates matched across views by the marker's 3D shape (with the
    # transfer fallback), edges fitted from the layout's ellipses (EllipSegNet's masks
    # where that fails) + blur fit, plate check, bias correction, rigid pose, a second
    # look at 640x480 around the best candidates when nothing is found.
    "default": {},
    # The paper's MarkerPose: ID-head decoding, EllipSegNet on fixed 120 px patches,
    # cv2.fitEllipse on the mask, DLT triangulation of the ellipse centres, R = [x y x×y].
    "paper": {
        "match": {"method": "head"},
        "propose": {"second_look": 1.0},
        "refine": {"patch": "fixed", "fit": "ellipse", "edge_refit": False},
        "solve": PAPER_POSE,
    },
    # The paper's classical detector (§3.4): contour ellipses, epipolar pairing.
    "paper-classical": {"detector": "classical", "refine": {"subpixel": False}, "solve": PAPER_POSE},
    # Ablations of the neural pipeline, from the paper's towards ours.
    "neural-layout": {
        "match": {"method": "layout"},
        "propose": {"second_look": 1.0},
        "refine": _NO_EDGE,
        "solve": PAPER_POSE,
    },
    "neural-layout-rigid": {"match": {"method": "layout"}, "propose": {"second_look": 1.0}, "refine": _NO_EDGE},
    "neural-stereo": {"refine": _NO_EDGE},
    "default-no-transfer": {"match": {"transfer": False}},
    "default-no-blur-fit": {"refine": {"blur_fit": False}},
    "default-no-second-look": {"propose": {"second_look": 1.0}},
    "neural-classical-refine": {"refine": {"method": "classical"}},
    "default-masks-first": {"refine": {"layout_seed": False}},
    # Ablations of the classical detector, from the paper's towards ours.
    "classical-subpixel": {"detector": "classical", "solve": PAPER_POSE},
    "classical-subpixel-bias": {"detector": "classical", "solve": {"pose": "paper"}},
    "classical": {"detector": "classical"},
    # The default with its networks in bfloat16 on OpenVINO (the openvino extra): fast on
    # CPUs with AMX.
    "default-bf16": {"backend": "openvino-bf16"},
    # The default with stage 1 in int8 (weights and activations), on ONNX Runtime.
    "default-int8": {"propose": {"int8": True}},
}

ABOUT: dict[str, str] = {
    "default": "ours: stereo-matched candidates, edges fitted from the layout's ellipses (EllipSegNet's masks where that fails), blur fit, bias correction, rigid pose",
    "paper": "the paper's MarkerPose: ID head, EllipSegNet (fixed 120 px, fitEllipse), paper pose",
    "paper-classical": "the paper's classical detector (§3.4) and pose",
    "neural-layout": "paper + IDs from the marker's layout, adaptive patches, sub-pixel mask fit",
    "neural-layout-rigid": "neural-layout + bias correction + rigid pose",
    "neural-stereo": "neural-layout-rigid with candidates matched across views by the 3D shape",
    "default-no-transfer": "default without the transfer fallback",
    "default-no-blur-fit": "default without the blurred-ring fit",
    "default-no-second-look": "default without stage 1's second look",
    "neural-classical-refine": "default with the classical ring fit instead of EllipSegNet",
    "default-masks-first": "default with EllipSegNet's masks seeding every cold detection's edge fit (the former default)",
    "classical-subpixel": "paper-classical + sub-pixel edges",
    "classical-subpixel-bias": "classical-subpixel + bias correction",
    "classical": "classical-subpixel-bias + rigid pose: our best classical (detector='classical')",
    "default-bf16": "default with the networks in bfloat16 on OpenVINO (the openvino extra)",
    "default-int8": "default with stage 1's network in int8 (weights and activations)",
}

# Reports list the default and the paper's configurations first, then the ablations.
ORDER = (
    "default",
    "paper",
    "paper-classical",
    "classical",
    "neural-layout",
    "neural-layout-rigid",
    "neural-stereo",
    "default-no-transfer",
    "default-no-blur-fit",
    "default-no-second-look",
    "neural-classical-refine",
    "default-masks-first",
    "classical-subpixel",
    "classical-subpixel-bias",
    "default-bf16",
    "default-int8",
)


def is_neural(name: str) -> bool:
    """Whether a preset uses the networks."""
    return PRESETS[name].get("detector", "neural") == "neural"


def check(name: str) -> str:
    """``name`` if it is a preset, else ``ValueError`` listing them."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {list(ORDER)}")
    return name


DETECTORS = ("neural", "classical")

default_conf = {
    "detector": "neural",  # "neural" (the paper's networks) or "classical" (paper §3.4)
    "threads": None,  # the networks' inference threads (None: every core)
    "backend": "onnxruntime",  # what runs the networks: "onnxruntime", "openvino", "openvino-bf16"
    **{name: stage.default_conf for name, stage in zip(STAGES, (propose, match, refine, verify, solve, track))},
}


def resolve(preset: str = "default", detector: str | None = None, **overrides) -> dict:
    """The full configuration: the stages' defaults, the preset's diff, then ``overrides``
    (``detector``, ``threads``, ``backend`` and one dict per stage); ``ValueError`` for
    unknown names."""
    conf = copy.deepcopy(default_conf)
    if detector is not None and preset == "default":
        preset = "classical" if detector == "classical" else "default"  # the shorthand
    for diff in (PRESETS[check(preset)], overrides):
        for key, value in diff.items():
            if key not in conf:
                stage = next((s for s in STAGES if key in default_conf[s]), None)
                hint = f" (now {stage}={{{key!r}: ...}})" if stage else ""
                raise ValueError(f"unknown option {key!r}{hint}; known: {sorted(default_conf)}")
            if key in ("detector", "threads", "backend"):
                conf[key] = value
                continue
            if not isinstance(value, dict):
                raise ValueError(f"{key} takes a dict of settings, got {value!r}")
            unknown = sorted(set(value) - set(default_conf[key]))
            if unknown:
                raise ValueError(f"unknown {key} setting(s) {unknown}; known: {sorted(default_conf[key])}")
            conf[key].update(value)
    if detector is not None:
        conf["detector"] = detector
    if conf["threads"] is not None and not (isinstance(conf["threads"], int) and conf["threads"] >= 1):
        raise ValueError(f"threads must be a whole number >= 1 or None, got {conf['threads']!r}")
    if conf["backend"] not in BACKENDS:
        raise ValueError(f"unknown backend {conf['backend']!r}; choose from {BACKENDS}")
    if conf["detector"] not in DETECTORS:
        raise ValueError(f"unknown detector {conf['detector']!r}; choose from {DETECTORS}")
    if conf["match"]["method"] not in match.METHODS:
        raise ValueError(f"unknown ids method {conf['match']['method']!r}; choose from {match.METHODS}")
    propose.check_conf(conf["propose"])
    solve.check_conf(conf["solve"])
    track.check_conf(conf["track"])
    return conf


__all__ = ["ABOUT", "DETECTORS", "ORDER", "PRESETS", "check", "default_conf", "is_neural", "resolve"]
