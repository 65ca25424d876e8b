"""What one call of the pipeline needs and learns, in one object made per call.

A :class:`Frame` is created when ``estimate()``, ``track()`` or ``detect()`` starts and
dropped when it returns. It holds the call's images, the seconds spent per stage, the
first reason a hypothesis failed, the cold detection's work budget, each image's noise
estimate (computed once however many hypotheses refine it) and stage 1's inputs (made
once however many looks and evidence tests use them). Nothing of a call lives in the
settings or in the stages, so two trackers in two threads share nothing but their
read-only networks and settings.

With several tools, each tool's detection works in its own :meth:`Frame.child`: its own
work budget and reason, the images, timings, noise estimates and stage 1's looks shared
(:meth:`Frame.shared`), and the rings of the tools found so far claimed
(:meth:`Frame.claim`), so that no other tool is made of them.
"""

from __future__ import annotations

import time

import numpy as np

from . import classical


class Frame:
    """One call's working state.

    Args:
        grays: the views' uint8 gray images (H, W), left first.
    Attributes:
        timings: seconds per stage (``"total"`` once :meth:`finish` ran).
        why: the first reason met why a hypothesis failed (None: none yet).
        fits_left: hypotheses the cold detection may still refine (None: no budget).
        blur_fits: the blurred-ring fits it may still run (None: no limit).
        looked: stage 1's inputs of these images, (image, size, input, scale) (see
            :meth:`markerpose.keypoints.KeypointNet.candidates`).
    """

    def __init__(self, grays: list[np.ndarray]):
        self.grays = grays
        self.timings: dict[str, float] = {}
        self.why: str | None = None
        self.fits_left: int | None = None
        self.max_fits = 0
        self.blur_fits: classical.FitBudget | None = None
        self.looked: list = []
        self.plate_seen = False  # a view's refined rings fitted the marker's plate (no second look helps)
        self.claimed: list[list] = [[], []]  # per view, (centre (2,), radius px, tool name) of the rings found
        self._noise: dict[int, tuple[np.ndarray, float]] = {}
        self._memo: dict = {}
        self._t0 = time.perf_counter()

    def child(self) -> Frame:
        """A frame for one more tool's work on the same images: its own budget and reason;
        the images, timings, noise estimates, stage 1's inputs and looks, and the claimed
        rings shared with this one."""
        sub = Frame.__new__(Frame)
        sub.__dict__.update(self.__dict__)
        sub.why, sub.fits_left, sub.max_fits, sub.blur_fits, sub.plate_seen = None, None, 0, None, False
        return sub

    def shared(self, key, fn, *args):
        """``fn(*args)``, computed once per call for ``key`` (hashable) across this frame
        and its children: stage 1's look at the images serves every tool."""
        if key not in self._memo:
            self._memo[key] = fn(*args)
        return self._memo[key]

    def prefit(self, name: str, predicted: list, found: list) -> None:
        """Keep the tool ``name``'s edge fit ``found`` of its ``predicted`` rings, made in
        one batch with other tools' (see :meth:`prefitted`)."""
        self._memo[("prefit", name)] = (predicted, found)

    def prefitted(self, name: str, predicted: list) -> list | None:
        """The fit :meth:`prefit` kept for the tool ``name``, if of these very ``predicted``
        rings (once), else None."""
        kept = self._memo.pop(("prefit", name), None)
        return kept[1] if kept is not None and kept[0] is predicted else None

    def prelay(self, name: str, points: list, found: list, blur_fits: int) -> None:
        """Keep the tool ``name``'s first cold hypothesis, ``points`` (per view (centres (3, 2),
        score)), refined from its layout (``found``, per view a Detection or None) in one
        batch with other tools' and having run ``blur_fits`` blurred-ring fits (see
        :meth:`prelaid`)."""
        self._memo[("prelay", name)] = (points, found, blur_fits)

    def prelaid(self, name: str, points: list) -> tuple[list, int] | None:
        """(found, blur fits run) that :meth:`prelay` kept for the tool ``name``, if of the same
        ``points`` (once), else None: a tool whose candidates another tool's rings thinned
        makes other hypotheses."""
        kept = self._memo.pop(("prelay", name), None)
        if kept is None or len(kept[0]) != len(points):
            return None
        same = all(
            (a is None) == (b is None) and (a is None or (np.array_equal(a[0], b[0]) and a[1] == b[1])) for a, b in zip(kept[0], points)
        )
        return (kept[1], kept[2]) if same else None

    def claim(self, name: str, rings: list) -> None:
        """The rings of the tool ``name``, found in this call: per view, its outer
        ellipses ((cx, cy), (major, minor), angle). Another tool's rings must lie off them."""
        for view, ellipses in zip(self.claimed, rings):
            view.extend((np.asarray(c, np.float64), max(axes) / 2, name) for c, axes, _ in ellipses)

    def claimant(self, view: int, point) -> str | None:
        """The tool whose claimed ring in ``view`` covers ``point`` (x, y), or None."""
        x, y = float(point[0]), float(point[1])
        for c, r, name in self.claimed[view]:
            if (x - c[0]) ** 2 + (y - c[1]) ** 2 <= r * r:
                return name
        return None

    def unclaimed(self, cand: list) -> list:
        """Per view, the (N, 3) candidates off every claimed ring (all of them while none is)."""
        if not any(self.claimed):
            return cand
        return [c[keep] if len(c) else c for c, keep in zip(cand, self.unclaimed_masks(cand))]

    def unclaimed_masks(self, cand: list) -> list:
        """Per view, which of the (N, 3) candidates lie off every claimed ring (N,)."""
        return [np.array([self.claimant(v, p[:2]) is None for p in c], bool).reshape(len(c)) for v, c in enumerate(cand)]

    def failed(self, reason: str) -> None:
        """Remember why a hypothesis failed, if it is the first reason of this call."""
        if self.why is None:
            self.why = reason

    def timed(self, stage: str, fn, *args):
        """``fn(*args)``, its seconds added to ``timings[stage]``."""
        t = time.perf_counter()
        out = fn(*args)
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - t
        return out

    def budget(self, fits: int, blur_fits: int) -> None:
        """Start a cold detection's work budget: ``fits`` refined hypotheses, ``blur_fits``
        blurred-ring fits (the costliest refinement)."""
        self.fits_left, self.max_fits = int(fits), int(fits)
        self.blur_fits = classical.FitBudget(blur_fits)

    @property
    def spent(self) -> bool:
        """Whether the cold detection's budget is spent (no hypothesis may be refined)."""
        return self.fits_left is not None and self.fits_left <= 0

    def spend(self) -> bool:
        """Charge one refined hypothesis to the budget: False (with the reason) once it is
        spent; True without a budget."""
        if self.fits_left is None:
            return True
        if self.fits_left <= 0:
            self.failed(f"work budget: {self.max_fits} hypotheses refined, none accepted")
            return False
        self.fits_left -= 1
        return True

    def noises(self, grays: list[np.ndarray], known: list | None = None) -> list[float]:
        """Per image, its noise sigma (:func:`markerpose.classical.noise_sigma`), each
        estimated once in this call. ``known``: the images' sigmas as already estimated (a
        video stream's cameras, from an earlier frame): this call's later requests take
        them instead."""
        if known is not None:
            self._noise.update((id(g), (g, float(n))) for g, n in zip(grays, known))
            return [float(n) for n in known]
        new = list({id(g): g for g in grays if id(g) not in self._noise}.values())  # the memo holds the image: its id is not reused
        self._noise.update((id(g), (g, n)) for g, n in zip(new, classical.noise_sigmas(new)))
        return [self._noise[id(g)][1] for g in grays]

    def estimate_noise(self, j: int, residuals=None) -> None:
        """Estimate image ``j``'s noise sigma now, for :meth:`noises` (once per call; from
        any thread: a cold detection's first look does it on each view's own thread), from
        ``residuals`` where they are the histogram of the estimate's own grid (stage 1's
        input counted them: :func:`markerpose.keypoints.to_input`), else from the image."""
        g = self.grays[j]
        if id(g) in self._noise:
            return
        if residuals is not None and classical.noise_stride(g.shape) == 4:
            self._noise[id(g)] = (g, classical.noise_from_residuals(residuals))
        else:
            self._noise[id(g)] = (g, classical.noise_sigma(g))

    def finish(self) -> dict[str, float]:
        """The call's timings, with its total."""
        self.timings["total"] = time.perf_counter() - self._t0
        return self.timings


__all__ = ["Frame"]
