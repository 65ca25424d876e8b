"""Ring evidence: the compiled evidence against numpy's, its sampler against OpenCV's."""

import numpy as np

import markerpose as mp
from markerpose import evidence as evidence_mod
from markerpose import geometry as geo


def _ring_evidence_reference(image, triples, marker, min_pairs=8):
    """ring_evidence in numpy, as it was written before it was compiled: OpenCV's remap
    for the samples, numpy's NaN-aware statistics."""
    import warnings

    import cv2

    z = evidence_mod._zones(marker)
    P = np.asarray(triples, np.float64)
    A = geo.layout_affine(P, marker.centers2d)
    t = P[:, 0] - A @ marker.centers2d[0]
    h, w = image.shape

    def sample(pts):
        q = np.einsum("tij,...j->t...i", A, pts) + t.reshape((-1,) + (1,) * (pts.ndim - 1) + (2,))
        flat = q.reshape(-1, 2).astype(np.float32)
        v = cv2.remap(image, flat[None, :, 0].copy(), flat[None, :, 1].copy(), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
        inside = (flat[:, 0] >= 0) & (flat[:, 0] <= w - 1) & (flat[:, 1] >= 0) & (flat[:, 1] <= h - 1)
        return np.where(inside, v, np.nan).reshape(q.shape[:-1])

    eps = 2.0 / 255

    def step(a, b):
        return np.abs(a - b) / (np.fmax(a, b) + eps)

    def f32(f, x):
        return f(x.astype(np.float64), axis=-1).astype(x.dtype)

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        inner, outside, plate = sample(z["inner"]), sample(z["outside"]), sample(z["plate"])
        i, j = z["pairs"]
        steps = step(plate[:, i], plate[:, j])
        q75 = np.nanpercentile(steps.astype(np.float64), 75, axis=1).astype(np.float32)
        rough = np.where(np.isfinite(steps).sum(1) >= min_pairs, q75, 0.0)
        link = np.where(z["linked"], step(outside, plate[:, z["nearest"]]), np.nan)
        off = np.nan_to_num(np.nanmax(f32(np.nanmedian, link), axis=1), nan=0.0)
        factors = [
            f32(np.nanmedian, 1 - sample(z["band"]).max(-1) / (np.fmax(inner, outside) + eps)).min(1),
            1 - 4 * rough,
            1 - 2 * np.clip(f32(np.nanmedian, (inner - outside) / (outside + eps)), 0, None).max(1),
            1 - off,
        ]
    return np.prod([np.clip(np.nan_to_num(f, nan=0.0), 0, 1) for f in factors], axis=0)


def test_ring_evidence_compiled_is_the_numpy_evidence(drawn_rings):
    """The compiled evidence gives what numpy and OpenCV's remap give (to a float32 rounding
    of a sample), on the marker, scaled, turned and shifted triples around it, and triples
    whose rings and plate the image's border cuts; its sampler is OpenCV's bilinear remap."""
    import cv2

    m = mp.Marker()
    rng = np.random.default_rng(4)
    s, a = 2.0, np.deg2rad(25)
    A = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ np.diag([1.0, -1.0])
    img = np.full((240, 320), 0.3, np.float32)
    x0, y0, x1, y1 = m.plate
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) @ A.T + [150, 120]
    cv2.fillConvexPoly(img, np.round(corners * 16).astype(np.int32), 0.85, cv2.LINE_AA, shift=4)
    marker = m.centers2d @ A.T + [150, 120]
    drawn_rings(img, marker, m.outer_radius * s, m.inner_radius * s, 0.08, 0.85)
    img = np.clip(img + rng.normal(0, 0.02, img.shape), 0, 1).astype(np.float32)
    tri = [marker, marker[[0, 2, 1]]]
    for _ in range(150):
        k, th = rng.uniform(0.6, 1.5), rng.uniform(-np.pi, np.pi)
        R = k * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        tri.append((marker - marker.mean(0)) @ R.T + rng.uniform([-40, -40], [360, 280]))
    tri = np.array(tri)
    got = evidence_mod.ring_evidence(img, tri, m)
    ref = _ring_evidence_reference(img, tri, m)
    assert got.dtype == np.float32 and got[0] > 0.6
    assert (ref > 0).sum() > 20  # not a comparison of zeros
    np.testing.assert_allclose(got, ref, atol=2e-6)
    # The sampler against remap, inside the image and on its last row and column.
    q = np.concatenate([rng.uniform([0, 0], [319, 239], (500, 2)), [[319, 239], [319, 10.5], [7.25, 239]]]).astype(np.float32)
    ours = evidence_mod._sample(img, np.eye(2)[None], np.zeros((1, 2)), q.astype(np.float64))[0]
    theirs = cv2.remap(img, q[None, :, 0].copy(), q[None, :, 1].copy(), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
    np.testing.assert_allclose(ours, theirs, atol=2e-7, rtol=0)
    assert np.isnan(evidence_mod._sample(img, np.eye(2)[None], np.zeros((1, 2)), np.array([[-0.5, 3.0], [3.0, 239.5]]))).all()
