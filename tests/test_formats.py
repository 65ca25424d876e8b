"""Strict JSON everywhere (markerpose.formats)."""

import json

import numpy as np
import pytest

from markerpose.formats import dumps, jsonable, write_json


def _strict(text):
    def reject(token):
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=reject)


def test_non_finite_becomes_null_and_numpy_becomes_python(tmp_path):
    obj = {"a": float("nan"), "b": np.float32(np.inf), "c": np.arange(3), "d": (np.int64(2), np.bool_(True)), 4: -np.inf}
    assert jsonable(obj) == {"a": None, "b": None, "c": [0, 1, 2], "d": [2, True], "4": None}
    assert _strict(write_json(tmp_path / "x.json", obj).read_text())["a"] is None
    with pytest.raises(ValueError, match="non-standard"):
        _strict(json.dumps({"a": float("nan")}))  # what the standard library writes by default
    assert _strict(dumps({"m": np.eye(2)}, None)) == {"m": [[1.0, 0.0], [0.0, 1.0]]}


def test_bench_json_is_strict(tmp_path):
    """The benchmark's figures hold NaN where a set is empty; its JSON must still parse strictly."""
    from markerpose.experiments import bench

    out = tmp_path / "bench.json"
    bench.main({"pairs": 1, "blurred_pairs": 0, "empty_pairs": 0, "repeats": 2, "configs": ["paper-classical"]}, out, progress=False)
    res = _strict(out.read_text())
    assert res["configs"]["paper-classical"]["blur_25_ms"] is None
