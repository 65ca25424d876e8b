"""Propose: where the rings might be, before anything is named or refined.

- Neural (the paper's stage 1, :mod:`markerpose.keypoints`): both views go through the
  SuperPoint-like network in one batch at 320x240; each view's best local maxima of the
  location score are its candidates (:meth:`NeuralProposer.candidates`). The paper's
  configuration instead decodes one triple per view by the ID head
  (:meth:`NeuralProposer.decoded`). When a look finds no marker, stage 1 looks again at
  ``second_look`` times the input size, resized from the full image (ours): rings under
  ~12 px at 320x240 are found far more often. That look sees only windows around the
  first look's best candidates (``second_look_near``, ``second_look_window``), and only
  where some view has three candidates of some strength (``second_look_min``): a marker's
  rings score that even where they are too small to be matched, most clutter does not.
- Classical (paper §3.4, :mod:`markerpose.classical`): binarise, contours, concentric
  ellipses; each view's ring candidates and its marker-like triples named by layout
  (:func:`classical_view`).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np

from .. import classical, jit, keypoints, settings
from ..keypoints import KeypointNet
from ..marker import Marker
from ..nets import default_weights, have_onnxruntime, int8_weights, wide_vectors
from ..settings import choice, flag, number, path

# The shipped stage-1 networks, by the name propose's "network" takes: the file stem in
# markerpose/weights/ (NAME.onnx, NAME.pt, NAME-int8.onnx). "standard" is the paper's
# layers at half their widths (a quarter in the first four), "mid" at three eighths (an
# eighth), "lite" at a quarter (an eighth); "fast" is the mid network distilled onto a stem with
# no layer at full resolution (keypoints.build_network's "strided").
NETWORKS = {"mid": "keypoints-mid", "standard": "keypoints", "lite": "keypoints-lite", "fast": "keypoints-fast"}
# The paper's configuration and the ablations from it towards ours keep the network and
# the input they were measured with.
PAPER_NETWORK = {"network": "standard", "input": "paper", "int8": False}

default_conf = {
    "network": "fast",  # neural: which shipped stage-1 network (NETWORKS) ...
    "weights": None,  # ... or this weights file (None: the shipped network)
    "int8": None,  # neural: the shipped network's int8 copy (ours; float32 in its narrow layers and its
    #                 logits): True, False (float32), or None: where one is shipped, no weights are
    #                 given and ONNX Runtime or OpenVINO's float32 runs the networks
    "threshold": 0.01,  # neural: the candidates' least location score
    "second_look": 2.0,  # neural: zoom of a second look when the first finds nothing (1: none) ...
    "second_look_min": 0.2,  # ... and has, in some view, three candidates scoring at least this (a
    #                          marker's rings do, even too small to be matched there; clutter
    #                          mostly does not: no second look on most marker-free pairs; 0: always)
    "input": "isotropic",  # neural: the input's size: "paper" 320x240 whatever the image, "isotropic"
    #                    the image's aspect at 320 wide (320x256 for 1280x1024: an exact 4x4 area resize)
    "stack_views": None,  # neural, ONNX Runtime: the two views in one run of the network's shipped
    #                       copy that takes them as two channels (nets.stack_views; the same
    #                       outputs): True where one is shipped, False never, None where one is
    #                       shipped and the CPU has AVX-512 (nets.wide_vectors)
}
RULES = {
    "network": choice(*NETWORKS),
    "weights": path(),
    "int8": flag(optional=True),
    "threshold": number(0, 1),
    "second_look": number(1),
    "second_look_min": number(0, 1),
    "input": choice("paper", "isotropic"),
    "stack_views": flag(optional=True),
}

# Stage 1's candidate list for the stereo detector: the same quantities, under the same
# names, as the decoded detector's (markerpose.decode.default_conf: threshold,
# max_candidates, nms_radius, tuned when the weights were exported), at an operating point
# of their own: more, weaker candidates, since matching across the views rejects decoys.
MAX_CANDIDATES = 16  # candidates per view
NMS_RADIUS = 4  # non-maximum-suppression radius between candidates, px of the 320x240 input
# The second look sees only windows around the first look's best candidates per view (a
# marker too small to be matched at the first look is still among its best ones), of this
# many px of its input each side (a large ring needs context beyond its own size).
SECOND_LOOK_NEAR = 5
SECOND_LOOK_WINDOW = 64
# A view with two candidates this strong is worth the second look too (worth_second_look).
SECOND_LOOK_TWO = 0.8


def network_weights(network: str) -> Path:
    """The shipped weights file of a stage-1 network named in :data:`NETWORKS`."""
    return default_weights(NETWORKS[network])


def check_conf(conf: dict) -> dict:
    """``conf`` if every value fits :data:`RULES` (``ValueError`` naming the key)."""
    return settings.check("propose", conf, RULES)


class NeuralProposer:
    """Stage 1 with its weights, for one way of naming the rings.

    Args:
        conf: :data:`default_conf` with overrides.
        marker: the marker's geometry.
        ids: the match method ("stereo", "layout" or "head"): "head" and "layout" decode
            one triple per view (:meth:`decoded`), "stereo" uses :meth:`candidates`.
    """

    def __init__(self, conf: dict, marker: Marker, ids: str, threads: int | None = None, backend: str = "onnxruntime"):
        self.conf = check_conf(conf)
        decoding = {"ids": "layout" if ids == "stereo" else ids}
        if ids != "stereo":
            decoding["second_look"] = float(conf["second_look"])
        weights = conf["weights"]
        int8 = conf["int8"]
        if int8 is None:
            int8 = (
                weights is None
                and backend in ("onnxruntime", "openvino")
                and have_onnxruntime()
                and int8_weights(NETWORKS[conf["network"]]).is_file()
            )
        if int8:
            if weights is not None:
                raise ValueError(
                    "propose int8 runs the shipped weights' int8 copy; quantize your own weights with "
                    "`markerpose train keypoints --int8 SRC DEST` and give DEST as weights, without int8"
                )
            weights = int8_weights(NETWORKS[conf["network"]])
            if not weights.is_file():
                raise ValueError(
                    f"no int8 copy of the {conf['network']} stage-1 network is shipped ({weights.name}); make one with "
                    "`markerpose train keypoints --int8 SRC DEST` and give DEST as weights, without int8"
                )
        elif weights is None:
            weights = network_weights(conf["network"])
        jit.warm_up(keypoints.warm_up)  # compiled now, not at a stream's first frame
        stack = conf["stack_views"]
        if stack is None:
            stack = wide_vectors()
        self.net = KeypointNet(weights, decoding, marker=marker, stereo=True, threads=threads, backend=backend, stack_views=stack)
        self.net.isotropic = conf["input"] == "isotropic"

    def for_marker(self, marker: Marker) -> NeuralProposer:
        """This stage 1 for another marker (its layout and rings' evidence), sharing the network."""
        other = copy.copy(self)
        other.net = copy.copy(self.net)
        other.net.marker = marker
        return other

    def look_size(self, zoom: float, shape: tuple) -> tuple[int, int]:
        """Stage 1's input (width, height) for an image of ``shape`` at the look ``zoom``."""
        return self.net.look_size(zoom, shape)

    def looks(self) -> tuple[float, ...]:
        """Stage 1's zoom factors, tried in turn while the marker is not found."""
        zoom = float(self.conf["second_look"])
        return (1.0, zoom) if zoom > 1 else (1.0,)

    def worth_second_look(self, cand: list) -> bool:
        """Whether the first look's candidates (per view, (N, 3) rows (x, y, score)) may hide a
        marker the second look would find: some view has three scoring ``second_look_min`` or
        more, or two scoring :data:`SECOND_LOOK_TWO` (a marker whose third ring the first look
        missed: a shadow across it, an occluder)."""
        least = float(self.conf["second_look_min"])
        return any(
            int(np.count_nonzero(c[:, 2] >= least)) >= 3 or int(np.count_nonzero(c[:, 2] >= max(least, SECOND_LOOK_TWO))) >= 2 for c in cand
        )

    def candidates(
        self, grays: list[np.ndarray], zoom: float = 1.0, previous: list | None = None, kept: list | None = None, beside=None
    ) -> list[np.ndarray]:
        """Per view, (N, 3) candidates (x, y, score) in full-resolution pixels, best first.
        A look with ``zoom`` > 1 given the ``previous`` look's candidates looks only near
        its best ones (``second_look_near``). ``kept``: the call's stage-1 inputs
        (:attr:`markerpose.frame.Frame.looked`), made once per call. ``beside``: per view
        ``j``, ``beside(j, residuals)`` on that view's thread where the views run side by side
        (:meth:`markerpose.keypoints.KeypointNet.candidates`)."""
        c = self.conf
        near = None
        if zoom > 1 and previous is not None:
            near = [p[:SECOND_LOOK_NEAR, :2] for p in previous]
        return self.net.candidates(
            grays, c["threshold"], MAX_CANDIDATES, zoom, NMS_RADIUS, near=near, window=SECOND_LOOK_WINDOW, kept=kept, beside=beside
        )

    @staticmethod
    def near_key(previous: np.ndarray) -> bytes:
        """What of one view's ``previous`` candidates a zoomed look depends on (hashable)."""
        return np.ascontiguousarray(previous[:SECOND_LOOK_NEAR, :2]).tobytes()

    def near(self, grays: list[np.ndarray], points: list, half: int, kept: list | None = None) -> list[np.ndarray]:
        """Per view, (N, 3) candidates as :meth:`candidates` gives them, from a first look
        that sees only windows of 2 ``half`` x 2 ``half`` input px around ``points`` (per
        view, (M, 2) full-resolution pixels): where a tracker's prior put the marker."""
        c = self.conf
        return self.net.candidates(grays, c["threshold"], MAX_CANDIDATES, 1.0, NMS_RADIUS, near=points, window=int(half), kept=kept)

    def decoded(self, grays: list[np.ndarray], kept: list | None = None) -> list:
        """The paper's decoding: per view, (points (3, 2) by ID, score) or None."""
        return self.net(grays, kept)

    def evidence(self, gray: np.ndarray, triples: np.ndarray, zoom: float = 1.0, kept: list | None = None) -> np.ndarray:
        """Ring evidence (:func:`markerpose.evidence.ring_evidence`) of (T, 3, 2) triples
        in the input of the look ``zoom`` that found them: (T,)."""
        return self.net.evidence(gray, triples, zoom, kept)


def classical_view(image: np.ndarray, marker: Marker, conf: dict | None = None):
    """The classical detector's proposals in one view: (gray float32, noise sigma, ring
    candidates, marker-like triples best first) — :func:`markerpose.classical.view_triples`."""
    return classical.view_triples(image, marker, conf)


__all__ = [
    "MAX_CANDIDATES",
    "NETWORKS",
    "NMS_RADIUS",
    "RULES",
    "SECOND_LOOK_NEAR",
    "SECOND_LOOK_TWO",
    "SECOND_LOOK_WINDOW",
    "NeuralProposer",
    "check_conf",
    "classical_view",
    "network_weights",
    "default_conf",
]
