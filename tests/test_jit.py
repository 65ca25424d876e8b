"""The compiled loops type the same under every numpy / numba pair the project allows.

numba types ``np.linalg.eig`` of a real matrix by the numpy it runs beside: before numpy 2.5
real arrays (raising on complex eigenvalues), from 2.5 on always complex arrays. numba reads
that version when it types a call, so a child process that sets numba's idea of the numpy
version to 2.5 (and compiles into an empty cache) types every kernel as under numpy 2.5.
"""

import json
import math
import os
import subprocess
import sys

import numba
import numpy as np
import pytest

import markerpose as mp
from markerpose import edges, jit

# Nearly collinear points: the direct fit's reduced scatter matrix has complex eigenvalues.
COLLINEAR = [
    [7.617325, -11.074389],
    [-5.624674, 8.190656],
    [14.00355, -20.377278],
    [-2.679697, 3.899663],
    [-4.195389, 6.105089],
    [-3.027713, 4.402007],
]
CONF = {"outlier_k": 3.0, "outlier_min_px": 0.15}


def _ring(n=24, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return (np.stack([40 + 12 * np.cos(t), 30 + 7 * np.sin(t)], -1) + rng.normal(0, 0.05, (n, 2)))[None]


def _fits():
    """fit_robust on an ordinary ring and on the collinear set (numpy's fallback path)."""
    out = {}
    for name, P in (("ring", _ring()), ("collinear", np.array([COLLINEAR]))):
        cen, Q, fitted, keep = edges.fit_robust(P, np.ones(P.shape[:2], bool), CONF)
        out[name] = {"cen": cen.tolist(), "Q": Q.tolist(), "fitted": fitted.tolist(), "keep": keep.tolist()}
    return out


def test_real_eigvecs_matches_numpy_and_refuses_complex():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    S = A + A.T  # symmetric: real eigenvalues
    V = np.zeros((3, 3))
    assert edges._real_eigvecs(S, V)
    w = np.real(np.linalg.eig(S)[0])
    np.testing.assert_allclose(S @ V, V * w[None], atol=1e-10)
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # eigenvalues e^{±0.3i}, 1
    V2 = np.full((3, 3), 7.0)
    assert not edges._real_eigvecs(rot, V2)
    assert np.all(V2 == 7.0)


def test_complex_eigenproblem_takes_numpy_path():
    P = np.array([COLLINEAR])
    K, N = P.shape[:2]
    fallback = np.zeros(K, bool)
    out = [np.empty((K, 2)), np.empty((K, 2, 2)), np.empty(K, bool), np.empty((K, N), bool), fallback]
    edges._robust_rows(
        P,
        np.ones((K, N), bool),
        np.ones((K, N)),
        np.zeros(K, bool),
        np.zeros((K, 2)),
        np.tile(np.eye(2), (K, 1, 1)),
        np.zeros((K, 40, 5), np.int64),
        3.0,
        0.15,
        edges._S1,
        edges._S2,
        edges._S3,
        *out,
    )
    assert fallback[0]
    got = edges.fit_robust(P, np.ones((K, N), bool), CONF)
    ref = edges._fit_robust_numpy(P, np.ones((K, N), bool), CONF)
    for a, b in zip(got, ref):
        np.testing.assert_array_equal(a, b)


def test_typing_failure_is_one_clear_error():
    def bad_step():
        edges._harmonics(np.ones((1, 3)), "not an array")  # numba cannot type this call

    with pytest.raises(jit.CompileError, match=rf"numpy {np.__version__} and numba {numba.__version__}.*pip install"):
        jit.warm_up(bad_step)


_CHILD = r"""
import json, sys
import numba.np.numpy_support as support
support.numpy_version = (2, 5)  # numba now types eig (and the rest) as beside numpy 2.5
sys.path.insert(0, {tests!r})
import test_jit
import markerpose as mp
from markerpose.synth import look_at_pose, render_stereo
rig = mp.StereoRig.default()
tracker = mp.MarkerPose(rig)  # warms up (compiles) every kernel
pair = render_stereo(rig, look_at_pose([10, -5, 560], 30, 45, 0), seed=4).images
est = tracker.estimate(*pair)
print(json.dumps({{"T": est.T.tolist(), "fits": test_jit._fits()}}))
"""


def test_kernels_compile_and_agree_as_under_numpy_2_5(tmp_path):
    """Every kernel compiles as numba types it beside numpy 2.5 (eig always complex), and the
    pose and fits (the complex-eigenvalue fallback included) are the ones of this process."""
    from markerpose.synth import look_at_pose, render_stereo

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))  # an empty cache: everything compiled anew
    code = _CHILD.format(tests=os.path.dirname(__file__))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    child = json.loads(run.stdout.strip().splitlines()[-1])
    rig = mp.StereoRig.default()
    est = mp.MarkerPose(rig).estimate(*render_stereo(rig, look_at_pose([10, -5, 560], 30, 45, 0), seed=4).images)
    np.testing.assert_allclose(child["T"], est.T, rtol=0, atol=1e-9)
    assert child["fits"] == _fits()


def _guarded_sum(x):  # pragma: no cover - compiled
    s = 0.0
    for v in x:
        if not v > 0:  # NaN and non-positive values skipped
            continue
        s += math.sqrt(v) * 0.1 + v / 3.0
    return s


def test_fast_math_keeps_nan_tests_and_values():
    """``compiled(fast=True)`` may reorder arithmetic but not drop the NaN tests the loops rely on."""
    plain, fast = jit.compiled(_guarded_sum), jit.compiled(fast=True)(_guarded_sum)
    x = np.random.default_rng(0).normal(size=1000)
    x[::7] = np.nan
    assert np.isfinite(fast(x))
    assert fast(x) == pytest.approx(plain(x), rel=1e-12)
    assert not {"nnan", "ninf"} & jit.FAST_MATH
