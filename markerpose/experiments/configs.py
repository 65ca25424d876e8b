"""The presets the experiments compare (:mod:`markerpose.presets`), those that can run here,
and an experiment's own settings over its defaults."""

from __future__ import annotations

import importlib.util

from ..nets import default_weights, have_backend, have_onnxruntime, int8_weights
from ..presets import ORDER, PRESETS, is_neural

DEFAULT = "default"


def available(names=None, require: bool = False) -> list[str]:
    """Preset names, in report order, whose networks are present and can run here (all by
    default, or those in ``names``); ``ValueError`` for an unknown name, and with
    ``require`` when none can run (before an experiment's work)."""
    unknown = [n for n in (names or ()) if n not in PRESETS]
    if unknown:
        raise ValueError(f"unknown preset(s) {unknown}; known: {list(ORDER)}")
    runtime = have_onnxruntime() or importlib.util.find_spec("torch") is not None
    nets = runtime and default_weights("keypoints").is_file() and default_weights("ellipses").is_file()

    def runs(name):  # OpenVINO runs the .onnx files only, and so does int8
        backend = PRESETS[name].get("backend", "onnxruntime")
        if PRESETS[name].get("propose", {}).get("int8"):
            return have_backend(backend) and int8_weights("keypoints").is_file()
        return backend == "onnxruntime" or (have_backend(backend) and default_weights("keypoints").suffix == ".onnx")

    out = [n for n in ORDER if (names is None or n in names) and (not is_neural(n) or (nets and runs(n)))]
    if require and not out:
        raise ValueError(f"none of the presets {list(names or ORDER)} can run here (their networks or runtime are missing)")
    return out


def settings(conf: dict | None, defaults: dict, what: str) -> dict:
    """``defaults`` with ``conf`` over them; ``ValueError`` naming any key ``defaults`` lacks
    (``what``: the experiment, for the message)."""
    unknown = set(conf or {}) - set(defaults)
    if unknown:
        raise ValueError(f"unknown {what} settings {sorted(unknown)}; known: {sorted(defaults)}")
    return {**defaults, **(conf or {})}


__all__ = ["DEFAULT", "available", "settings"]
