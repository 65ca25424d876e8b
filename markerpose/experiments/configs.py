"""The configurations the experiments compare: the user presets (:mod:`markerpose.presets`)
and the ablations, each of which switches one of our improvements off (or the paper's
configuration one step towards ours), so that every gain is measured in the same run on
the same frames; which of them can run here; and an experiment's own settings over its
defaults."""

from __future__ import annotations

import importlib.util

from ..nets import default_weights, have_backend, have_onnxruntime, int8_weights
from ..pipeline import MarkerPose
from ..presets import ABOUT as PRESET_ABOUT
from ..presets import ORDER as PRESET_ORDER
from ..presets import PAPER_POSE, PRESETS, is_neural
from ..stages import propose

DEFAULT = "default"
_NO_EDGE = {"edge_refit": False}
_PAPER_NET = propose.PAPER_NETWORK

# name -> (diff over the stages' defaults, what it is)
ABLATIONS: dict[str, tuple[dict, str]] = {
    # the neural pipeline, from the paper's towards ours
    "neural-layout": (
        {"match": {"method": "layout"}, "propose": {"second_look": 1.0, **_PAPER_NET}, "refine": _NO_EDGE, "solve": PAPER_POSE},
        "paper + IDs from the marker's layout, adaptive patches, sub-pixel mask fit",
    ),
    "neural-layout-rigid": (
        {"match": {"method": "layout"}, "propose": {"second_look": 1.0, **_PAPER_NET}, "refine": _NO_EDGE},
        "neural-layout + bias correction + rigid pose",
    ),
    "neural-stereo": (
        {"propose": _PAPER_NET, "refine": _NO_EDGE},
        "neural-layout-rigid with candidates matched across views by the 3D shape",
    ),
    "default-standard-net": (
        {"propose": _PAPER_NET},
        "default with the former default's stage 1: the standard network at the paper's 320x240 input",
    ),
    "default-mid-net": (
        {"propose": {"network": "mid"}},
        "default with the former default's stage-1 network: the mid one, from which the fast one is distilled (its stem at full resolution)",
    ),
    # the default with one part switched off or replaced
    "default-no-transfer": ({"match": {"transfer": False}}, "default without the transfer fallback"),
    "default-transfer-masks": (
        {"match": {"transfer_masks": True}},
        "default with EllipSegNet's masks in the transfer's fits where the layout's seeds do not fit (the former default)",
    ),
    "default-no-blur-fit": ({"refine": {"blur_fit": False}}, "default without the blurred-ring fit"),
    "default-no-plate-edge": ({"refine": {"plate_edge": False}}, "default whose fits take in what the plate's blurred edge reaches"),
    "default-blur-centres": (
        {"refine": {"blur_blocks": False}},
        "default whose blurred-ring fit models its samples (3x3 block means) by their centres alone (the former model)",
    ),
    "default-bare-tangents": (
        {"refine": {"blur_tangents": False}},
        "default whose blurred-ring fit takes its three lines across the motion bare, not smoothed near the rings' tangents",
    ),
    "default-no-long-blur-fit": (
        {"refine": {"blur_long_px": 0.0}},
        "default whose blurred-ring fit takes over at edges 0.4 of the minor semi-axis wide only, not also at 0.3 where they are 7.5 px wide",
    ),
    "default-long-blur-even": (
        {"refine": {"blur_long_even": 1.0}},
        "default whose rule for long blur also takes rings whose edges are widened alike all round (defocus, resampling)",
    ),
    "default-early-blur-fit": (
        {"refine": {"blur_width": 0.3}},
        "default whose blurred-ring fit takes over from the edge fit at edges 0.3 of the minor semi-axis wide (0.4)",
    ),
    "default-no-second-look": ({"propose": {"second_look": 1.0}}, "default without stage 1's second look"),
    "default-unstacked": (
        {"propose": {"stack_views": False}},
        "default with stage 1's two views as a batch of two on two threads, not as two channels of one run",
    ),
    "default-lite-paper-input": (
        {"propose": {"network": "lite", "input": "paper"}},
        "default-lite with stage 1's input at the paper's 320x240 instead of the image's aspect",
    ),
    "neural-classical-refine": ({"refine": {"method": "classical"}}, "default with the classical ring fit instead of EllipSegNet"),
    "default-masks-first": (
        {"refine": {"layout_seed": False}},
        "default with EllipSegNet's masks seeding every cold detection's edge fit (the former default)",
    ),
    # the classical detector, from the paper's towards ours
    "classical-subpixel": ({"detector": "classical", "solve": PAPER_POSE}, "paper-classical + sub-pixel edges"),
    "classical-subpixel-bias": ({"detector": "classical", "solve": {"pose": "paper"}}, "classical-subpixel + bias correction"),
}

# Reports list the default and the paper's configurations first, then the ablations.
ORDER = (*PRESET_ORDER[:4], *ABLATIONS, *PRESET_ORDER[4:])
ABOUT = {**PRESET_ABOUT, **{name: about for name, (_, about) in ABLATIONS.items()}}


def diff(name: str) -> dict:
    """The settings a configuration changes from the stages' defaults."""
    if name in PRESETS:
        return PRESETS[name]
    if name in ABLATIONS:
        return ABLATIONS[name][0]
    raise ValueError(f"unknown configuration {name!r}; known: {list(ORDER)}")


def build(name: str, rig, marker=None, **opts) -> MarkerPose:
    """The MarkerPose of a configuration (a preset or an ablation), with ``opts`` (e.g.
    ``threads``) over it."""
    if name in PRESETS:
        return MarkerPose(rig, marker, preset=name, **opts)
    d = {k: ({**v, **opts.get(k, {})} if isinstance(v, dict) else v) for k, v in diff(name).items()}
    return MarkerPose(rig, marker, preset=DEFAULT, **{**opts, **d})


def available(names=None, require: bool = False) -> list[str]:
    """Configuration names, in report order, whose networks are present and can run here
    (all by default, or those in ``names``); ``ValueError`` for an unknown name, and with
    ``require`` when none can run (before an experiment's work)."""
    unknown = [n for n in (names or ()) if n not in ORDER]
    if unknown:
        raise ValueError(f"unknown configuration(s) {unknown}; known: {list(ORDER)}")
    runtime = have_onnxruntime() or importlib.util.find_spec("torch") is not None

    def stem(name):  # the file stem of the configuration's stage-1 network
        return propose.NETWORKS[diff(name).get("propose", {}).get("network", propose.default_conf["network"])]

    def runs(name):  # OpenVINO runs the .onnx files only, and so does int8
        if not (runtime and default_weights(stem(name)).is_file() and default_weights("ellipses").is_file()):
            return False
        backend = diff(name).get("backend", "onnxruntime")
        if diff(name).get("propose", {}).get("int8"):
            return have_backend(backend) and int8_weights(stem(name)).is_file()
        return backend == "onnxruntime" or (have_backend(backend) and default_weights(stem(name)).suffix == ".onnx")

    out = [n for n in ORDER if (names is None or n in names) and (not is_neural(diff(n)) or runs(n))]
    if require and not out:
        raise ValueError(f"none of the configurations {list(names or ORDER)} can run here (their networks or runtime are missing)")
    return out


def settings(conf: dict | None, defaults: dict, what: str) -> dict:
    """``defaults`` with ``conf`` over them; ``ValueError`` naming any key ``defaults`` lacks
    (``what``: the experiment, for the message)."""
    unknown = set(conf or {}) - set(defaults)
    if unknown:
        raise ValueError(f"unknown {what} settings {sorted(unknown)}; known: {sorted(defaults)}")
    return {**defaults, **(conf or {})}


__all__ = ["ABLATIONS", "ABOUT", "DEFAULT", "ORDER", "available", "build", "diff", "settings"]
