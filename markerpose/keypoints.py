"""Stage 1: the SuperPoint-like network that finds ring centres, and its runtime.

The image is resized to 320x240 (the paper's input), a VGG-style encoder brings it to
H/8 x W/8 cells, and two heads classify every cell:

- the detector head (65 channels): which of the 64 pixels of the 8x8 cell holds a ring
  centre, or channel 64, "no centre here";
- the ID head (4 channels): c0, c1, c2 or background.

:class:`KeypointNet` loads the shipped (or a given) weights with the decoding thresholds
tuned when they were exported, and turns full-resolution images into candidates
(:meth:`KeypointNet.candidates`, what the default pipeline uses) or into the paper's
triple by ID (:meth:`KeypointNet.__call__`, :mod:`markerpose.decode`). The shipped
``.onnx`` weights run on ONNX Runtime (or OpenVINO); building and training the network
needs torch; the decoding is numpy.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import cv2
import numpy as np

from . import decode as _decode
from . import evidence
from .decode import CELL, ID_MODES, decode, peaks
from .decode import default_conf as decode_defaults
from .evidence import ring_evidence
from .images import RESIDUAL_BINS
from .jit import compiled
from .marker import Marker
from .nets import detector_only_path, load_network
from .threads import Worker

INPUT_SIZE = (320, 240)  # (width, height) the paper resizes every image to
PAPER_WIDTHS = (64, 64, 64, 64, 128, 128, 128, 128)
PAPER_HEAD = 256
_MARKER = Marker()  # the default marker
_WORKER = Worker()  # the second view's input
_UNIT = np.arange(256, dtype=np.float32) / 255.0  # uint8 grey level -> the network's [0, 1]


def layer_widths(width: float = 1.0, stem_width: float | None = None) -> tuple[tuple[int, ...], int]:
    """(encoder widths (8,), head width) for a width multiplier (1.0 = the paper's).

    ``stem_width`` (ours), when given, multiplies the first four convolutions instead —
    those at full and half resolution, which cost most of the compute: the deeper layers
    and the heads run on 16x fewer pixels, so they can be wider for little time."""
    stem = width if stem_width is None else stem_width
    enc = tuple(max(8, int(round(c * (stem if i < 4 else width)))) for i, c in enumerate(PAPER_WIDTHS))
    return enc, max(16, int(round(PAPER_HEAD * width)))


STEMS = ("pool", "strided", "pointwise")  # how the encoder halves the input the first time (build_network)


def build_network(width: float = 1.0, stem_width: float | None = None, stem: str = "pool"):
    """The SuperPoint-like network (torch ``nn.Module``), paper widths times ``width``
    (the first four convolutions times ``stem_width`` when given; see :func:`layer_widths`).

    ``stem``: "pool", the paper's two 3x3 convolutions at full resolution then a 2x2
    max-pool; or "strided" (ours), one 4x4 convolution of stride 2 to twice the first
    width, then a 3x3 one to the second at half resolution: features of the same shape
    and centres with no layer at full resolution, whose work dominates a narrow
    network's time; or "pointwise" (ours), the same with a 1x1 convolution in place of
    the 3x3 one, which was the costliest layer left in the narrow networks' stems (the
    two 3x3 convolutions after it widen the view again).

    Input: (B, 1, H, W) float in [0, 1], H and W multiples of 8.
    Output: (det (B, 65, H/8, W/8), ids (B, 4, H/8, W/8)) logits. Weights channels-last.
    """
    import torch
    from torch import nn

    if stem not in STEMS:
        raise ValueError(f"stem must be one of {STEMS}, got {stem!r}")
    enc, head = layer_widths(width, stem_width)

    def conv(cin, cout, k=3, stride=1, pad=None):
        pad = k // 2 if pad is None else pad
        return [nn.Conv2d(cin, cout, k, stride, pad, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]

    class SuperPointLike(nn.Module):
        def __init__(self):
            super().__init__()
            layers, cin = [], 1
            for i, c in enumerate(enc):
                if stem != "pool" and i < 2:
                    if i == 1:
                        # Output cell j covers input pixels 2j-1..2j+2: centred where the
                        # pool's cell is. The identity keeps the later layers' indices (and
                        # so the state-dict keys) those of the pooled network's.
                        k = 1 if stem == "pointwise" else 3
                        layers += conv(1, 2 * enc[0], 4, 2, 1) + conv(2 * enc[0], c, k) + [nn.Identity()]
                        cin = c
                    continue
                layers += conv(cin, c)
                cin = c
                if i % 2 == 1 and i < 7:  # 2x2 max-pool after every two convs, three pools
                    layers.append(nn.MaxPool2d(2, 2))
            self.encoder = nn.Sequential(*layers)
            self.det_head = nn.Sequential(*conv(cin, head), nn.Conv2d(head, CELL * CELL + 1, 1))
            self.id_head = nn.Sequential(*conv(cin, head), nn.Conv2d(head, 4, 1))
            self.width, self.stem_width, self.stem = width, stem_width, stem

        def forward(self, x: torch.Tensor):
            f = self.encoder(x)
            return self.det_head(f), self.id_head(f)

    # Channels-last: the convolutions run faster on the CPU, in training and inference,
    # with the same outputs to ~1e-6.
    return SuperPointLike().to(memory_format=torch.channels_last)


def network_for(meta: dict):
    """:func:`build_network` for a checkpoint's or weights file's ``width``, ``stem_width``
    and ``stem`` (absent: "pool", the paper's)."""
    return build_network(float(meta["width"]), meta.get("stem_width"), meta.get("stem", "pool"))


def to_input(gray: np.ndarray, size=INPUT_SIZE, residuals: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A full-resolution gray image → the network's input and the scale back.

    ``residuals``: a zeroed int64 histogram of :data:`~markerpose.images.RESIDUAL_BINS` bins: where the input is the image's
    exact quarter (uint8), the same pass over the image also counts, at each 4x4 block's
    pixel (1, 1), the residuals |4 I - (sum of the 4 neighbours)|, the grid that
    :func:`markerpose.classical.noise_sigma` reads at a stride of 4 (its histogram, for
    the noise estimate without a second pass); elsewhere it stays zero.

    Returns:
        (image (H, W) float32 in [0, 1] at ``size``, scale (2,) = full / input, per axis).
    """
    w, h = size
    if gray.dtype == np.uint8 and gray.shape == (4 * h, 4 * w) and gray.flags.c_contiguous:
        return _quartered(gray, residuals), input_scale(gray.shape, size)
    return _unit(cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA)), input_scale(gray.shape, size)


_NO_COUNTS = np.zeros(0, np.int64)


def _quartered(gray: np.ndarray, residuals: np.ndarray | None = None) -> np.ndarray:
    """The network's input of a C-contiguous uint8 image four times its size per axis
    (:func:`_quarter`), with ``residuals`` counted where given (:func:`to_input`)."""
    small = np.empty((gray.shape[0] // 4, gray.shape[1] // 4), np.float32)
    _quarter(gray, _UNIT, small, _NO_COUNTS if residuals is None else residuals)
    return small


@compiled
def _quarter(gray, table, out, hist):  # pragma: no cover - compiled
    """out[y, x] = table[mean of gray's 4x4 block (y, x), rounded half to even] (uint8 gray):
    OpenCV's area resize by exactly 4 (it rounds these means half to even), in one pass
    with the table lookup and without the uint8 image between (the default first look at
    1280x1024: 320x256). Where ``hist`` has bins, hist[v] += how many blocks' pixel (1, 1)
    has |4 I - (sum of its 4 neighbours)| = v: all within the block's rows 0-2."""
    h, w = out.shape
    cols = np.empty(w * 4, np.int32)
    count = hist.shape[0] > 0
    for y in range(h):
        r0, r1, r2, r3 = gray[4 * y], gray[4 * y + 1], gray[4 * y + 2], gray[4 * y + 3]
        for X in range(w * 4):  # the block rows' column sums: contiguous, vectorised
            cols[X] = np.int32(r0[X]) + np.int32(r1[X]) + np.int32(r2[X]) + np.int32(r3[X])
        for x in range(w):
            s = cols[4 * x] + cols[4 * x + 1] + cols[4 * x + 2] + cols[4 * x + 3]
            q, r = s >> 4, s & 15
            q += (r > 8) | ((r == 8) & (q & 1))
            out[y, x] = table[q]
        if count:
            for x in range(w):
                X = 4 * x + 1
                v = 4 * np.int32(r1[X]) - (np.int32(r0[X]) + np.int32(r2[X]) + np.int32(r1[X - 1]) + np.int32(r1[X + 1]))
                hist[abs(v)] += 1


def warm_up() -> None:
    """Compile this module's loops, the candidates' and the ring evidence's (or load them from numba's cache)
    before a stream's first frame."""
    to_input(np.zeros((32, 32), np.uint8), (8, 8))
    _decode.warm_up()
    evidence.warm_up()


def input_scale(shape: tuple, size=INPUT_SIZE) -> np.ndarray:
    """(2,) full / input per axis, for an image of ``shape`` (H, W) looked at in ``size`` (W, H)."""
    return np.array([shape[1] / size[0], shape[0] / size[1]])


def _unit(small: np.ndarray) -> np.ndarray:
    if small.dtype == np.uint8:  # a table lookup: the same values as dividing, without the division
        return cv2.LUT(small, _UNIT)
    return small.astype(np.float32) / 255.0


def to_input_window(gray: np.ndarray, size, x0: int, y0: int, w: int, h: int) -> np.ndarray:
    """``to_input(gray, size)[0][y0:y0 + h, x0:x0 + w]``, resizing only the part of the
    image the window needs.

    The area resize maps every block of input pixels that spans a whole number of image
    pixels (per axis: size / gcd(size, image size) input pixels) onto those image pixels
    alone, so a crop of the image on block boundaries resizes to the same values as the
    whole image gives there."""
    W, H = size
    Hs, Ws = gray.shape[:2]
    bx, by = W // math.gcd(W, Ws), H // math.gcd(H, Hs)  # input px per block
    X0, Y0 = x0 // bx * bx, y0 // by * by
    X1, Y1 = min(-(-(x0 + w) // bx) * bx, W), min(-(-(y0 + h) // by) * by, H)
    crop = gray[Y0 * Hs // H : Y1 * Hs // H, X0 * Ws // W : X1 * Ws // W]
    if gray.dtype == np.uint8 and (Hs, Ws) == (4 * H, 4 * W):  # the whole input's exact 4x4 resize, on the crop
        small = _quartered(np.ascontiguousarray(crop))
    else:
        small = _unit(cv2.resize(crop, (X1 - X0, Y1 - Y0), interpolation=cv2.INTER_AREA))
    return small[y0 - Y0 : y0 - Y0 + h, x0 - X0 : x0 - X0 + w]


def to_full(points: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Network-input pixels → full-resolution pixels (pixel centres at integers in both)."""
    return (np.asarray(points, np.float64) + 0.5) * scale - 0.5


def look_conf(conf: dict) -> dict:
    """The decoding settings of the second look: ``min_score`` from ``look_min_score``."""
    ms = conf.get("look_min_score")
    return conf if ms is None else {**conf, "min_score": ms}


def check_second_look(value) -> float:
    """``second_look`` as a float; ValueError unless it is a zoom factor >= 1 (1: none)."""
    if not float(value) >= 1:
        raise ValueError(f"second_look is a zoom factor >= 1 (1: none), got {value!r}")
    return float(value)


def look_size(zoom: float = 1.0) -> tuple[int, int]:
    """The network input's (width, height) for a look ``zoom`` times the paper's 320x240."""
    return round(INPUT_SIZE[0] * zoom), round(INPUT_SIZE[1] * zoom)


def tuned_key(ids: str, verify: bool = False, stereo: bool = False, align: bool = False) -> str:
    """Name of a set of decoding thresholds tuned at export: the ID mode, ``_verify``,
    ``_align`` and ``_stereo`` (the operating point for views of a stereo pair). The
    second look's threshold is stored under this name + ``_look``."""
    return ids + ("_verify" if verify else "") + ("_align" if align else "") + ("_stereo" if stereo else "")


def _windows(points: np.ndarray, shape: tuple, half: int) -> list[tuple[int, int]]:
    """Top-left corners (x0, y0) of windows of 2 ``half`` x 2 ``half`` px (on the network's
    cell grid, inside an input of ``shape`` (H, W)) centred on each point; points that an
    earlier window already holds with a margin of half / 2 get none."""
    H, W = shape
    size = 2 * half
    out: list[tuple[int, int]] = []
    for x, y in points:
        if any(x0 + half / 2 <= x < x0 + size - half / 2 and y0 + half / 2 <= y < y0 + size - half / 2 for x0, y0 in out):
            continue
        x0 = int(np.clip(round((x - half) / CELL) * CELL, 0, max(W - size, 0)))
        y0 = int(np.clip(round((y - half) / CELL) * CELL, 0, max(H - size, 0)))
        out.append((x0, y0))
    return out


def _suppress(cand: np.ndarray, radius: float) -> np.ndarray:
    """Candidates (N, 3) best first, without those within ``radius`` of a better one (the
    same peak seen from two overlapping windows)."""
    keep: list[int] = []
    xy = cand[:, :2].tolist()  # Python numbers: numpy's per-element calls were most of the time
    for n in np.argsort(-cand[:, 2], kind="stable").tolist():
        if all(math.hypot(xy[n][0] - xy[m][0], xy[n][1] - xy[m][1]) > radius for m in keep):
            keep.append(n)
    return cand[keep]


class KeypointNet:
    """Stage 1 with its weights: full-resolution images → ring centres by ID.

    Args:
        weights: an ``.onnx`` file (ONNX Runtime) or a ``.pt`` checkpoint (PyTorch), or
            None for the shipped default (:func:`markerpose.nets.default_weights`).
        conf: decoding overrides of :data:`decode_defaults`; ``width`` and ``stem_width``
            come from the checkpoint.
        device: torch device ("cpu" by default; "cuda" when wanted and present).
        marker: the marker's geometry, for ``ids="layout"`` and ``verify`` (default: the
            default marker).
        stereo: use the thresholds tuned for views of a stereo pair (a looser
            false-positive budget, as the pair's epipolar and shape checks reject false
            triples) when the checkpoint has them; else those for single images.
        threads: the runtime's threads (None: its default, every core).
        backend: what runs ``.onnx`` weights (:data:`markerpose.nets.BACKENDS`).
        stack_views: run a batch of two (a stereo pair's views) by the weights'
            :func:`markerpose.nets.stack_views` copy where one lies beside them (ONNX
            Runtime only; the same outputs).
    """

    def __init__(
        self,
        weights: str | Path | None = None,
        conf: dict | None = None,
        device: str = "cpu",
        marker: Marker | None = None,
        stereo: bool = False,
        threads: int | None = None,
        backend: str = "onnxruntime",
        stack_views: bool = False,
    ):
        self.runner, meta, self.path = load_network(
            weights, "keypoints", network_for, threads, device, required=("state_dict", "width"), backend=backend, stack_views=stack_views
        )
        if "width" not in meta:
            raise ValueError(f"{self.path} is not a markerpose keypoints model: no 'width' in its metadata")
        self.locator = self._locator(meta, threads, backend, stack_views)
        # Decoding thresholds: the defaults, those tuned for this ID mode and operating
        # point when the weights were exported (keyed by tuned_key), then the caller's.
        self.tuned = meta.get("decode", {})
        self.conf = self.decode_conf(conf, stereo)
        self.conf["width"] = float(meta["width"])
        self.conf["stem_width"] = meta.get("stem_width")
        self.conf["stem"] = meta.get("stem", "pool")
        self.marker = marker or _MARKER
        # The input's height: the paper's 240 whatever the image (a 1280x1024 image squeezed
        # by 4.27 in y and 4 in x), or, isotropic, the image's own aspect at 320 wide (an
        # exact 4x4 area resize there, cheaper, with rings as round as in the renders
        # stage 1 is trained on).
        self.isotropic = False

    def _locator(self, meta: dict, threads: int | None, backend: str, stack_views: bool = False):
        """The runner of these weights' detector-head-only copy (:func:`markerpose.nets.detector_only`)
        where one lies beside an ``.onnx`` file with the same metadata, else None (the
        candidates then come from the whole network: the same values, a little later)."""
        det = detector_only_path(self.path)
        if self.path.suffix != ".onnx" or not det.is_file():
            return None
        runner, det_meta, _ = load_network(det, "keypoints", None, threads, backend=backend, stack_views=stack_views)
        return runner if det_meta == {**meta, "detector_only": True} else None

    def look_size(self, zoom: float, shape: tuple) -> tuple[int, int]:
        """The input's (width, height) for an image of ``shape`` (H, W) at the look ``zoom``:
        :func:`look_size`, or with :attr:`isotropic` the image's aspect at 320 px wide (the
        height in whole cells)."""
        if not self.isotropic:
            return look_size(zoom)
        w = INPUT_SIZE[0]
        h = max(CELL, CELL * round(w * shape[0] / shape[1] / CELL))
        return round(w * zoom), round(h * zoom)

    def decode_conf(self, conf: dict | None = None, stereo: bool = False) -> dict:
        """Decoding settings: the defaults, the thresholds tuned at export for the ID mode
        (``conf["ids"]``), ``verify`` and operating point (stereo or single view), then
        ``conf``."""
        mode = (conf or {}).get("ids", decode_defaults["ids"])
        if mode not in ID_MODES:
            raise ValueError(f"ids must be one of {ID_MODES}, got {mode!r}")
        verify = bool((conf or {}).get("verify", decode_defaults["verify"]))
        align = bool((conf or {}).get("align", decode_defaults["align"]))
        single = self.tuned.get(tuned_key(mode, verify, align=align), {})
        chosen = self.tuned.get(tuned_key(mode, verify, True, align), single) if stereo else single
        if float((conf or {}).get("second_look", decode_defaults["second_look"])) > 1:
            chosen = {**chosen, **self.tuned.get(tuned_key(mode, verify, stereo, align) + "_look", {})}
        out = {**decode_defaults, **chosen, **(conf or {})}
        check_second_look(out["second_look"])
        return out

    def logits(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, H, W) float32 inputs → (det (B, 65, Hc, Wc), ids (B, 4, Hc, Wc)) logits."""
        det, ids = self.runner(np.asarray(batch, np.float32)[:, None])
        return det, ids

    def det_logits(self, batch: np.ndarray) -> np.ndarray:
        """(B, H, W) float32 inputs → the detector head's (B, 65, Hc, Wc) logits alone."""
        if self.locator is None:
            return self.logits(batch)[0]
        return self.locator(np.asarray(batch, np.float32)[:, None])[0]

    @staticmethod
    def _kept(image: np.ndarray, size: tuple, kept: list | None) -> tuple | None:
        """(input, scale) of ``image`` at ``size`` if in ``kept``, else None."""
        for im, sz, small, scale in kept or ():
            if im is image and sz == size:
                return small, scale
        return None

    def _input(
        self, image: np.ndarray, zoom: float, kept: list | None = None, residuals: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """:func:`to_input` of an image at the look ``zoom``. ``kept``: one call's inputs,
        (image, size, input, scale), which it reuses and adds to (None: none kept).
        ``residuals``: as in :func:`to_input`, counted only where the input is made."""
        size = self.look_size(zoom, image.shape)
        found = self._kept(image, size, kept)
        if found is not None:
            return found
        small, scale = to_input(image, size, residuals)
        if kept is not None:
            kept.append((image, size, small, scale))
        return small, scale

    def _window(self, image: np.ndarray, zoom: float, x0: int, y0: int, size: int, kept: list | None = None) -> np.ndarray:
        """The input of the look ``zoom`` in the window of ``size`` px at (x0, y0): from the
        kept whole input if there is one, else from the window's part of the image."""
        shape = self.look_size(zoom, image.shape)
        found = self._kept(image, shape, kept)
        if found is not None:
            return found[0][y0 : y0 + size, x0 : x0 + size]
        return to_input_window(image, shape, x0, y0, size, size)

    def _forward(self, images: list[np.ndarray], zoom: float = 1.0, kept: list | None = None, ids: bool = True):
        """Full-resolution gray images → (det logits, ID logits (None unless ``ids``), per-image
        scales back, inputs), looked at ``zoom`` times the paper's input size."""
        # The views' inputs two at a time (their resize runs compiled, outside Python's lock).
        inputs, scales = zip(*_WORKER.map(lambda g: self._input(g, zoom, kept), images))

        def run(batch):
            return self.logits(batch) if ids else (self.det_logits(batch), None)

        if len({x.shape for x in inputs}) == 1:
            return (*run(np.stack(inputs)), scales, inputs)
        outs = [run(x[None]) for x in inputs]  # views of different sizes: one pass each
        return [o[0][0] for o in outs], [None if o[1] is None else o[1][0] for o in outs], scales, inputs

    def candidates(
        self,
        images: list[np.ndarray],
        threshold: float = 0.01,
        k: int = 16,
        zoom: float = 1.0,
        nms_radius: int | None = None,
        near: list | None = None,
        window: int = 64,
        kept: list | None = None,
        beside=None,
    ) -> list[np.ndarray]:
        """Every view's ``k`` best centre candidates, whatever their ID (one forward pass at
        ``zoom`` times 320x240; NMS radius in input px, None: ``conf["nms_radius"]``): per
        image, (N, 3) rows (x, y, score) in full-resolution pixels, best first.

        With ``near`` (per image, (M, 2) full-resolution points): the network sees only
        windows of 2 ``window`` x 2 ``window`` input px around those points (all windows
        of all images in one batch), not the whole input.

        ``kept``: the inputs one caller's frame has made so far (a list it owns; see
        :meth:`_input`): each image's input at each look is made once per frame (the
        evidence tests look again where the looks did). None: nothing kept.

        ``beside``: a call ``beside(j, residuals)`` made once per view ``j`` after its input,
        on the thread that makes its candidates, where a pair's two views run side by side
        on two threads (the caller's other work on each image, done while the other view's
        network runs; elsewhere it is not called): ``residuals`` the histogram of the
        image's noise residuals that making the input counted (:func:`to_input`), or None.
        """
        r = self.conf["nms_radius"] if nms_radius is None else nms_radius
        if near is not None:
            return self._candidates_near(images, threshold, k, zoom, r, near, window, kept)
        halves = self._halves()
        if halves is not None and len(images) == 2 and len({self.look_size(zoom, g.shape) for g in images}) == 1:
            # A pair's two views, each on its own thread from its image to its candidates:
            # the input, the network's half and the decoding of one view run beside the
            # other's, with no wait between the steps.
            def view(j):
                counts = None if beside is None else np.zeros(RESIDUAL_BINS, np.int64)
                small, scale = self._input(images[j], zoom, kept, counts)
                if beside is not None:
                    beside(j, counts if counts.any() else None)
                cand = peaks(halves[j](small[None, None])[0], threshold, k, r)[0]
                cand[:, :2] = to_full(cand[:, :2], scale)
                return cand

            return list(_WORKER.both(lambda: view(0), lambda: view(1)))
        det, _, scales, _ = self._forward(images, zoom, kept, ids=False)
        out = []
        found = peaks(det, threshold, k, r) if isinstance(det, np.ndarray) else [peaks(d[None], threshold, k, r)[0] for d in det]
        for cand, s in zip(found, scales):
            cand[:, :2] = to_full(cand[:, :2], s)
            out.append(cand)
        return out

    def _halves(self) -> tuple | None:
        """The runner of stage 1's candidates as two halves, each on its own thread
        (:attr:`markerpose.nets.Runner.halves`), or None where it runs whole."""
        return (self.locator if self.locator is not None else self.runner).halves

    def _candidates_near(self, images, threshold, k, zoom, r, near, window, kept=None):
        sizes = [self.look_size(zoom, g.shape) for g in images]
        scales = [input_scale(g.shape, wh) for g, wh in zip(images, sizes)]
        size = 2 * window
        where = []  # (image, x0, y0, the window's shape or None: a small input, all of it) of each window
        for j, (s, pts, (W, H)) in enumerate(zip(scales, near, sizes)):
            if min(H, W) < size:
                where.append((j, 0, 0, None))
                continue
            for x0, y0 in _windows((np.asarray(pts, np.float64).reshape(-1, 2) + 0.5) / s - 0.5, (H, W), window):
                where.append((j, x0, y0, (size, size)))
        shape_of = [(sizes[j][1], sizes[j][0]) if shape is None else shape for j, _, _, shape in where]

        def crop(n):
            j, x0, y0, shape = where[n]
            return self._input(images[j], zoom, kept)[0] if shape is None else self._window(images[j], zoom, x0, y0, size, kept)

        def found_in(idx, run):
            return peaks(run(np.stack([crop(n) for n in idx])[:, None])[0], threshold, k, r)

        found = [[] for _ in images]
        halves = self._halves()
        for shape in sorted(set(shape_of)):  # one batch per window size (one size unless an image is small)
            idx = [n for n, sh in enumerate(shape_of) if sh == shape]
            if halves is not None and len(idx) >= 2:  # each half's windows cut, run and decoded on its own thread
                h = len(idx) // 2
                first, second = _WORKER.both(
                    functools.partial(found_in, idx[:h], halves[0]), functools.partial(found_in, idx[h:], halves[1])
                )
                cands = [*first, *second]
            else:
                cands = found_in(idx, lambda x: (self.det_logits(x[:, 0]),))
            for n, cand in zip(idx, cands):
                j, x0, y0, _ = where[n]
                cand[:, :2] += (x0, y0)
                found[j].append(cand)
        out = []
        for j, s in enumerate(scales):
            cand = _suppress(np.concatenate(found[j]), r)[:k] if found[j] else np.zeros((0, 3))
            cand[:, :2] = to_full(cand[:, :2], s)
            out.append(cand)
        return out

    def evidence(self, image: np.ndarray, triples: np.ndarray, zoom: float = 1.0, kept: list | None = None) -> np.ndarray:
        """:func:`ring_evidence` of (T, 3, 2) triples in a full-resolution uint8 gray image's
        pixels, looked at in the network's input of the look that found them: (T,).
        ``kept``: as in :meth:`candidates`."""
        small, scale = self._input(image, zoom, kept)
        return ring_evidence(small, (np.asarray(triples, np.float64) + 0.5) / scale - 0.5, self.marker)

    def __call__(self, images: list[np.ndarray], kept: list | None = None) -> list[tuple[np.ndarray, float] | None]:
        """Centres in full-resolution pixels for a batch of uint8 gray images (one forward pass).

        Returns:
            per image, (centers (3, 2) by ID, score) or None (the paper's decoding,
            :func:`markerpose.decode.decode`; with ``second_look`` > 1 the images where
            nothing is found are decoded again from a larger input).
        """
        det, ids, scales, inputs = self._forward(images, 1.0, kept)
        out = []
        for k, s in enumerate(scales):
            found = decode(det[k], ids[k], self.conf, self.marker, inputs[k])
            out.append(None if found is None else (to_full(found[0], s), found[1]))
        zoom = float(self.conf["second_look"])
        again = [k for k, o in enumerate(out) if o is None]
        if zoom > 1 and again:
            # The second look resizes the full-resolution image, so it sees finer detail.
            det, ids, scales, inputs = self._forward([images[k] for k in again], zoom, kept)
            conf = look_conf(self.conf)
            for j, k in enumerate(again):
                found = decode(det[j], ids[j], conf, self.marker, inputs[j])
                out[k] = None if found is None else (to_full(found[0], scales[j]), found[1])
        return out


__all__ = [
    "INPUT_SIZE",
    "KeypointNet",
    "build_network",
    "network_for",
    "check_second_look",
    "input_scale",
    "layer_widths",
    "look_conf",
    "look_size",
    "to_full",
    "to_input",
    "to_input_window",
    "tuned_key",
    "warm_up",
]
