"""A B-mode image simulator for phantoms made of coaxial-ish cylinders and wires.

Honest enough that segmentation is a real task, cheap enough for a hundred frames a second:
- diffuse scattering as complex Gaussian noise per medium, filtered by the point-spread
  function, so the envelope shows fully developed (Rayleigh) speckle of the PSF's size;
- specular echoes at every interface the beam crosses, with the interface's reflection
  coefficient and a directivity that falls with the angle between the beam and the
  surface normal (smooth surfaces return little when hit obliquely: the sides of a tube
  drop out, as on real scans);
- two-way transmission losses below each interface (shadowing) and attenuation with depth
  per medium, compensated by a time-gain curve set for an average medium (so deep water
  comes out over-amplified, as it does on real machines);
- wires as point-like echoes where they cross the image plane;
- electronic noise, envelope detection, log compression to a dynamic range, 8 bits.

Not modelled (limits): the speed of sound is the same everywhere (no refraction, no depth
scaling), the elevation beam width (slice thickness) is zero, the lateral resolution does
not vary with depth, no reverberation or side lobes.

The image is simulated on a grid twice as fine as the output pixels and area-averaged
down (the envelope, before log compression), as a scan converter would.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ...ultrasound.probe import invert


@dataclass(frozen=True)
class Transducer:
    """Imaging settings of a linear probe.

    Attributes:
        size: (width, height) of the image, px.
        spacing: (sx, sy) pixel size, mm.
        frequency_mhz: centre frequency (sets the attenuation).
        axial_fwhm_mm, lateral_fwhm_mm: resolution (FWHM of the PSF envelope).
        tgc_db_per_mm: time-gain compensation, dB per mm of depth (two-way).
        dynamic_range_db: displayed range of the log-compressed envelope.
        noise: electronic noise amplitude (envelope units; a normal-incidence echo from an
            interface of reflection coefficient 1 has amplitude 1).
        gain_db: overall gain.
        directivity_deg: angle at which a specular echo falls to 1/e of its normal value.
        roughness: the part of an interface's echo that does not depend on the angle.
    """

    size: tuple[int, int] = (256, 334)
    spacing: tuple[float, float] = (0.15, 0.15)
    frequency_mhz: float = 7.5
    axial_fwhm_mm: float = 0.35
    lateral_fwhm_mm: float = 0.8
    tgc_db_per_mm: float = 0.06
    dynamic_range_db: float = 55.0
    noise: float = 0.002
    gain_db: float = 6.0
    directivity_deg: float = 20.0
    roughness: float = 0.04

    @property
    def extent_mm(self) -> tuple[float, float]:
        return self.size[0] * self.spacing[0], self.size[1] * self.spacing[1]


@dataclass(frozen=True)
class Medium:
    """Acoustic properties of a medium. ``scatter``: RMS backscatter amplitude per
    resolution cell; ``attenuation``: dB/cm/MHz."""

    name: str
    scatter: float
    attenuation: float


WATER = Medium("water", 0.0005, 0.002)
PLASTIC = Medium("plastic", 0.02, 1.5)
AIR = Medium("air", 0.0, 0.0)


@dataclass(frozen=True)
class Cylinder:
    """An infinite circular cylinder: axis through ``point`` along ``direction``."""

    point: tuple
    direction: tuple
    radius: float

    def radial(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance of points (..., 3) from the axis, and the unit outward normals."""
        a = np.asarray(self.point, dtype=np.float64)
        d = np.asarray(self.direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        q = p - a
        q = q - (q @ d)[..., None] * d
        r = np.linalg.norm(q, axis=-1)
        return r, q / np.maximum(r, 1e-12)[..., None]

    def crossings(self, p0: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Ray parameters s >= 0 where rays ``p0 + s b`` (p0 (N, 3), b (3,) unit) meet the
        surface: (N, 2), NaN where there is no crossing."""
        a = np.asarray(self.point, dtype=np.float64)
        d = np.asarray(self.direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        q = p0 - a
        q = q - (q @ d)[:, None] * d
        bp = b - (b @ d) * d
        A = bp @ bp
        B = 2 * q @ bp
        C = np.einsum("ij,ij->i", q, q) - self.radius**2
        disc = B * B - 4 * A * C
        out = np.full((len(p0), 2), np.nan)
        ok = (disc > 0) & (A > 1e-12)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        for j, sgn in enumerate((-1.0, 1.0)):
            s = (-B + sgn * sq) / (2 * A if A > 1e-12 else 1.0)
            out[:, j] = np.where(ok & (s >= 0), s, np.nan)
        return out


@dataclass(frozen=True)
class Layer:
    """Inside ``cylinder`` the medium is ``inside`` (nested layers: the smallest wins)."""

    cylinder: Cylinder
    inside: Medium
    reflection: float  # pressure reflection coefficient of its surface


@dataclass(frozen=True)
class Wire:
    """A thin wire (a line through ``point`` along ``direction``), seen as a point echo."""

    point: tuple
    direction: tuple
    amplitude: float = 0.6


@dataclass(frozen=True)
class Phantom:
    """Media outside every layer are ``background``; layers are listed outermost first and
    each lies inside the previous one where they overlap."""

    background: Medium
    layers: tuple = ()
    wires: tuple = ()


def tube_phantom(
    outer_diameter: float = 15.82,
    wall: float = 1.5,
    container_diameter: float = 88.0,
    container_wall: float = 3.0,
    container_offset: float = -20.0,
) -> Phantom:
    """The paper's object: a plastic tube of ``outer_diameter`` (axis = phantom x through
    the origin; z points down) in water inside a wide plastic trough whose axis lies
    ``container_offset`` mm deeper (negative: above), with air outside the trough."""
    out = Cylinder((0, 0, container_offset), (1, 0, 0), container_diameter / 2 + container_wall)
    inner_c = Cylinder((0, 0, container_offset), (1, 0, 0), container_diameter / 2)
    tube = Cylinder((0, 0, 0), (1, 0, 0), outer_diameter / 2)
    lumen = Cylinder((0, 0, 0), (1, 0, 0), outer_diameter / 2 - wall)
    return Phantom(
        AIR,
        (Layer(out, PLASTIC, 0.99), Layer(inner_c, WATER, 0.35), Layer(tube, PLASTIC, 0.35), Layer(lumen, WATER, 0.35)),
    )


def crosswire_phantom(point=(0.0, 0.0, 0.0), angle_deg: float = 60.0) -> Phantom:
    """Two wires crossing at ``point`` in a water bath, both roughly along phantom x (the
    sweep direction) and ``angle_deg`` apart."""
    h = np.deg2rad(angle_deg) / 2
    d1 = (np.cos(h), np.sin(h), 0.0)
    d2 = (np.cos(h), -np.sin(h), 0.0)
    return Phantom(WATER, (), (Wire(tuple(point), d1), Wire(tuple(point), d2)))


def _fine_grid(tr: Transducer):
    w, h = tr.size
    # Fine pixel j covers output pixel j // 2; its centre lies at (j - 0.5) / 2 output px.
    x = (np.arange(2 * w) - 0.5) / 2 * tr.spacing[0]
    y = (np.arange(2 * h) - 0.5) / 2 * tr.spacing[1]
    return x, y


def _sigma_px(fwhm_mm: float, spacing_mm: float) -> float:
    return fwhm_mm / 2.3548 / (spacing_mm / 2)


def simulate_bmode(
    phantom: Phantom,
    T_phantom_image: np.ndarray,
    transducer: Transducer | None = None,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """Simulate one B-mode frame.

    Args:
        phantom: the scene, in phantom coordinates (mm).
        T_phantom_image: (4, 4) image frame (see :mod:`markerpose.ultrasound.probe`) →
            phantom.
        transducer: imaging settings.
        rng: random generator or seed (speckle and noise).
    Returns:
        uint8 (height, width) B-mode image.
    """
    tr = transducer or Transducer()
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    T = np.asarray(T_phantom_image, dtype=np.float64)
    x, y = _fine_grid(tr)
    W2, H2 = len(x), len(y)
    ex, ey, o = T[:3, 0], T[:3, 1], T[:3, 3]
    tops = o + x[:, None] * ex  # (W2, 3): where each beam line starts (transducer face)
    dz = tr.spacing[1] / 2
    xs, ys = x.astype(np.float32)[None, :], y.astype(np.float32)[:, None]

    # Medium of every sample: the innermost layer containing it. The squared distance from
    # a cylinder's axis is a quadratic in the image-plane coordinates (x, y).
    scatter = np.full((H2, W2), phantom.background.scatter, np.float32)
    atten = np.full((H2, W2), phantom.background.attenuation, np.float32)
    for layer in phantom.layers:
        cyl = layer.cylinder
        d = np.asarray(cyl.direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        q0, qx, qy = (v - (v @ d) * d for v in (o - np.asarray(cyl.point, dtype=np.float64), ex, ey))
        r2 = (
            np.float32(q0 @ q0)
            + np.float32(2 * q0 @ qx) * xs
            + np.float32(2 * q0 @ qy) * ys
            + np.float32(qx @ qx) * xs * xs
            + np.float32(qy @ qy) * ys * ys
            + np.float32(2 * qx @ qy) * xs * ys
        )
        inside = r2 < cyl.radius**2
        scatter[inside] = layer.inside.scatter
        atten[inside] = layer.inside.attenuation
    # Two-way attenuation along each beam line: dB/cm/MHz × MHz × cm, there and back.
    loss_db = 2 * np.cumsum(atten * np.float32(tr.frequency_mhz * dz / 10.0), axis=0)
    gain = (10 ** ((np.float32(tr.gain_db) + np.float32(tr.tgc_db_per_mm) * ys - loss_db) / 20)).astype(np.float32)

    # Interfaces met by every beam line: depth, amplitude after directivity, shadowing.
    sig_ax = tr.axial_fwhm_mm / 2.3548
    spec = np.zeros((H2, W2), np.float32)
    loss_at = np.ones((H2 + 1, W2), np.float32)  # transmission factor applied from a row on
    hits = []
    theta0 = np.deg2rad(tr.directivity_deg)
    for layer in phantom.layers:
        s = layer.cylinder.crossings(tops, ey)  # (W2, 2)
        for j in range(2):
            sj = s[:, j]
            hit = np.isfinite(sj) & (sj <= y[-1] + 4 * sig_ax)
            if not hit.any():
                continue
            cols = np.flatnonzero(hit)
            _, n = layer.cylinder.radial(tops[cols] + sj[cols, None] * ey)
            ang = np.arccos(np.clip(np.abs(n @ ey), 0, 1))
            amp = layer.reflection * ((1 - tr.roughness) * np.exp(-((ang / theta0) ** 2)) + tr.roughness)
            row = np.clip(np.searchsorted(y, sj[cols]), 0, H2)
            hits.append((cols, sj[cols], amp, row))
            np.multiply.at(loss_at, (row, cols), np.float32(1 - layer.reflection**2))
    trans = np.cumprod(loss_at, axis=0)
    half = int(np.ceil(4 * sig_ax / dz)) + 1
    win = np.arange(-half, half + 1)
    for cols, sj, amp, row in hits:
        rows = np.clip(row[:, None] + win[None, :], 0, H2 - 1)
        prof = np.exp(-0.5 * ((y[rows] - sj[:, None]) / sig_ax) ** 2) * amp[:, None]
        prof[(row[:, None] + win[None, :] < 0) | (row[:, None] + win[None, :] > H2 - 1)] = 0
        # The echo is weakened by the interfaces above it, not by its own.
        above = trans[np.clip(row - 1, 0, H2), cols]
        np.add.at(spec, (rows, np.broadcast_to(cols[:, None], rows.shape)), (prof * above[:, None]).astype(np.float32))
    trans = trans[:H2]
    Ti = invert(T)
    sig_lat = tr.lateral_fwhm_mm / 2.3548
    for wire in phantom.wires:
        # Where the wire crosses the image plane (z = 0 in image coordinates).
        a = Ti[:3, :3] @ np.asarray(wire.point, float) + Ti[:3, 3]
        d = Ti[:3, :3] @ np.asarray(wire.direction, float)
        if abs(d[2]) < 1e-9:
            continue
        c = a - a[2] / d[2] * d  # crossing in image mm
        blob = np.exp(-0.5 * (((y[:, None] - c[1]) / sig_ax) ** 2 + ((x[None, :] - c[0]) / sig_lat) ** 2))
        spec += (wire.amplitude * blob).astype(np.float32)

    # Diffuse scattering: complex white noise × the medium's backscatter, through the PSF.
    sx = _sigma_px(tr.lateral_fwhm_mm, tr.spacing[0])
    sy = _sigma_px(tr.axial_fwhm_mm, tr.spacing[1])
    # Unit-variance complex noise blurred by a unit-sum Gaussian loses variance; this factor
    # restores one resolution cell's worth of amplitude (2·π·sx·sy cells → 1).
    norm = np.float32(np.sqrt(4 * np.pi * sx * sy))
    field_re = rng.standard_normal((H2, W2), dtype=np.float32) * scatter * trans
    field_im = rng.standard_normal((H2, W2), dtype=np.float32) * scatter * trans
    field_re = cv2.GaussianBlur(field_re, (0, 0), sigmaX=sx, sigmaY=sy) * norm
    field_im = cv2.GaussianBlur(field_im, (0, 0), sigmaX=sx, sigmaY=sy) * norm
    # Specular echoes are already shaped axially; the beam spreads them laterally.
    spec = cv2.GaussianBlur(spec, (0, 0), sigmaX=sx, sigmaY=1e-3)
    phase = rng.uniform(0, 2 * np.pi)
    field_re += spec * np.float32(np.cos(phase))
    field_im += spec * np.float32(np.sin(phase))
    field_re = field_re * gain + np.float32(tr.noise) * rng.standard_normal((H2, W2), dtype=np.float32)
    field_im = field_im * gain + np.float32(tr.noise) * rng.standard_normal((H2, W2), dtype=np.float32)
    env = np.sqrt(field_re**2 + field_im**2)
    env = cv2.resize(env, tr.size, interpolation=cv2.INTER_AREA)
    db = 20 * np.log10(np.maximum(env, 1e-12))
    out = (db + tr.dynamic_range_db) / tr.dynamic_range_db * 255.0
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


__all__ = [
    "AIR",
    "PLASTIC",
    "WATER",
    "Cylinder",
    "Layer",
    "Medium",
    "Phantom",
    "Transducer",
    "Wire",
    "crosswire_phantom",
    "simulate_bmode",
    "tube_phantom",
]
