"""What real recordings have and the standard rendered world does not, one effect at a time.

Each effect draws its strength from a stated range (:data:`EFFECTS`) and returns the
:class:`~markerpose.synth.render.Imaging` settings (and, for a bright ring-shaped object
beside the plate, the backgrounds) of one stereo pair:

- ``shadow``: a hand's or a tool's shadow across the plate: the light on one side of a
  line through the rings falls to 25–50 %, over a penumbra of 0.5–2 mm;
- ``light_gradient``: uneven light on the plate, falling to 35–60 % across it;
- ``defocus``: soft focus, a Gaussian PSF of σ 1.5–2.5 px (10–90 % edge over 4–6 px);
- ``gamma``: a camera response curve, output ∝ input^γ, γ from 0.45 to 2.2;
- ``jpeg``: JPEG compression at quality 20–50;
- ``resample``: the image shrunk 3–4.5× and enlarged back (a video or an animated
  figure's frames);
- ``toner``: ink that is dark grey rather than black (reflectance 0.15–0.3, paper 0.85);
- ``occluded_border``: a dark occluder (a thumb) over the plate's border, clear of the rings;
- ``ring_object``: a bright ring-shaped object (a connector) beside the plate in each view.

Shadows and light act on the plate in its own coordinates, so both views see the same
shadow; an occluder is modelled as a dark patch on the plate.
"""

from __future__ import annotations

import numpy as np

from ..marker import Marker

EFFECTS = ("shadow", "light_gradient", "defocus", "gamma", "jpeg", "resample", "toner", "occluded_border", "ring_object")


def _soft_step(d: np.ndarray, width: float) -> np.ndarray:
    """0 → 1 across a line, over ``width`` (10–90 %, a logistic edge)."""
    return 1.0 / (1.0 + np.exp(-4.394 * d / max(width, 1e-6)))


def shadow(rng: np.random.Generator, marker: Marker) -> dict:
    c = marker.centers2d
    p = rng.uniform(c.min(0), c.max(0))  # the shadow's edge passes among the rings
    a = rng.uniform(0, 2 * np.pi)
    nrm = np.array([np.cos(a), np.sin(a)])
    level, width = rng.uniform(0.25, 0.5), rng.uniform(0.5, 2.0)

    def light(mx, my):
        d = (mx - p[0]) * nrm[0] + (my - p[1]) * nrm[1]
        return level + (1.0 - level) * _soft_step(d, width)

    return {"plate_light": light}


def light_gradient(rng: np.random.Generator, marker: Marker) -> dict:
    x0, y0, x1, y1 = marker.plate
    a = rng.uniform(0, 2 * np.pi)
    u = np.array([np.cos(a), np.sin(a)])
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]) @ u
    lo, hi = corners.min(), corners.max()
    low = rng.uniform(0.35, 0.6)

    def light(mx, my):
        t = np.clip((mx * u[0] + my * u[1] - lo) / (hi - lo), 0.0, 1.0)
        return 1.0 - (1.0 - low) * t

    return {"plate_light": light}


def occluded_border(rng: np.random.Generator, marker: Marker) -> dict:
    x0, y0, x1, y1 = marker.plate
    c, R = marker.centers2d, marker.outer_radius
    for _ in range(100):  # a disk centred on the plate's border, clear of every ring
        side = rng.integers(4)
        t = rng.uniform(0, 1)
        p = [(x0 + t * (x1 - x0), y0), (x1, y0 + t * (y1 - y0)), (x0 + t * (x1 - x0), y1), (x0, y0 + t * (y1 - y0))][side]
        r = rng.uniform(6.0, 12.0)
        if np.min(np.linalg.norm(c - np.asarray(p), axis=1)) > R + r + 1.0:
            break
    else:
        r = 0.0
    shade = rng.uniform(0.05, 0.2)

    def light(mx, my):
        inside = (mx - p[0]) ** 2 + (my - p[1]) ** 2 <= r * r
        return np.where(inside, shade, 1.0)

    return {"plate_light": light}


def imaging_settings(name: str, rng: np.random.Generator, marker: Marker) -> dict:
    """The :class:`Imaging` settings of one pair with effect ``name``."""
    if name == "shadow":
        return shadow(rng, marker)
    if name == "light_gradient":
        return light_gradient(rng, marker)
    if name == "occluded_border":
        return occluded_border(rng, marker)
    if name == "defocus":
        return {"psf_sigma": rng.uniform(1.5, 2.5)}
    if name == "gamma":
        return {"gamma": float(np.exp(rng.uniform(np.log(0.45), np.log(2.2))))}
    if name == "jpeg":
        return {"jpeg_quality": int(rng.integers(20, 51))}
    if name == "resample":
        return {"resample": rng.uniform(3.0, 4.5)}
    if name == "toner":
        return {"ink": rng.uniform(0.15, 0.3)}
    if name == "ring_object":
        return {}
    raise ValueError(f"unknown effect {name!r}; known: {list(EFFECTS)}")


def ring_object_backgrounds(rig, T_left_marker: np.ndarray, marker: Marker, backgrounds: tuple, rng: np.random.Generator) -> tuple:
    """Each view's background with a bright ring-shaped object painted beside the plate:
    a white annulus (its hole dark) about the size of the marker's rings, 1–1.5 plate
    widths from the plate's centre. Returns new backgrounds."""
    x0, y0, x1, y1 = marker.plate
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    a = rng.uniform(0, 2 * np.pi)
    offset = rng.uniform(1.0, 1.5) * max(x1 - x0, y1 - y0) * np.array([np.cos(a), np.sin(a), 0.0])
    out = []
    for cam, T, bg in zip(rig.cameras, (T_left_marker, rig.T_right_left @ T_left_marker), backgrounds):
        P = (centre + offset) @ T[:3, :3].T + T[:3, 3]
        uv = cam.project(P[None])[0]
        scale = cam.K[0, 0] / P[2]  # px per mm there
        r_out, r_in = marker.outer_radius * scale * rng.uniform(0.8, 1.3), marker.inner_radius * scale * rng.uniform(0.8, 1.3)
        h, w = bg.shape
        yy, xx = np.mgrid[0:h, 0:w]
        d = np.hypot(xx - uv[0], yy - uv[1])
        img = np.array(bg, np.float32, copy=True)
        img[d <= r_out] = 0.95
        img[d <= r_in] = 0.05
        out.append(img)
    return tuple(out)


__all__ = ["EFFECTS", "imaging_settings", "ring_object_backgrounds"]
