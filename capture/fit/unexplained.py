"""Where a 2D fit leaves landmarks unexplained: the frames and face regions the actor does not reach.

An actor is learned from about 20 expressions. Where a performance goes beyond them (lips pulled sideways, which
no training shape does), the fit still lands near the landmarks, but the mesh there can be a millimetre off, mostly
in depth, which the landmarks do not show (BENCHMARKS.md, "2D fit out of the actor's span"). What the landmarks
do show is the residual. Where the actor explains a frame, what is left is the detector's noise: with ``sigma``
px per axis, a 2D residual has RMS ``sqrt(2) sigma``. Where it does not, the region it cannot reach keeps
residuals well above that: on the out-of-span benchmark (1,000 landmarks at 0.5 px) the mouth's RMS reaches 2-4x
the noise's on every sequence of held-out expressions, and no region goes over 1.25x on performances made of
training shapes (BENCHMARKS.md, "Frames the actor does not explain").

* :func:`landmark_regions` labels each landmark mouth, eyes or face by its place on the actor's template:
  near the template's mouth opening (the inner lip line), near an eye opening (the lid margins), or elsewhere.
* :class:`ResidualTally` gathers a take's residuals frame by frame, in memory that does not grow with the landmark
  count: the take's landmark noise (the median residual, robust to the frames it flags) and each region's RMS
  residual per frame. Its :meth:`~ResidualTally.spans` are the runs of frames where a region's RMS residual
  exceeds ``ratio`` times the noise's (and what its landmark count could reach by chance, at ``p_false`` per
  frame) for ``min_frames`` or more; :func:`unexplained_spans` does the same for a whole take's arrays.

Such a run says that the actor does not explain the landmarks there: an expression outside its training shapes
(adding a scan of it to the actor's training set would capture it), or a detector error there (the overlay
shows which). Pure numpy: no scipy, whose own BLAS must not load into the run's process. ``capture run`` tallies
each fitted frame as it is exported and writes the runs in its report.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

#: Region names, indexed by the labels of :func:`landmark_regions`.
REGIONS = ("mouth", "eyes", "face")
MOUTH, EYES, FACE = range(3)
#: A landmark within this distance (template mm) of the mouth's opening / an eye's opening is in that region.
MOUTH_MM, EYES_MM = 20.0, 15.0
#: A region needs this many confident landmarks in a frame to be judged there.
MIN_LANDMARKS = 5
#: The least landmark noise (px per axis) residuals are judged against: a detector's landmarks are not better
#: than that, and excess residuals below it are sub-pixel.
MIN_SIGMA_PX = 0.25
#: The rule of :meth:`ResidualTally.spans` that ``capture run`` reports with (BENCHMARKS.md, "Frames the actor does
#: not explain", measures it): RMS over 1.5x the noise's, at least 5 frames, gaps of 2 frames bridged, 1e-3 chance.
RATIO, MIN_FRAMES, MAX_GAP, P_FALSE = 1.5, 5, 2, 1e-3


def landmark_regions(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, mouth_mm: float = MOUTH_MM,
                     eyes_mm: float = EYES_MM) -> np.ndarray:
    """Region label (``REGIONS`` index) of each landmark, ``(L,)`` int.

    ``vertices`` ``(V, 3)`` and ``faces`` ``(F, 3)``: the actor's template (mm, its frame: x the actor's left, y
    up, z out of the face); ``points`` ``(L, 3)``: the landmarks on it (mm). The template's openings are its
    boundary loops after the outer border (:func:`capture.export.features.boundary_loops`); of the three
    longest, the lowest (least y) is the mouth and the other two are the eyes, when they lie on either side of the
    mouth and above it. A template without such openings (a closed mouth, no eye holes) labels every landmark
    ``face``.
    """
    from capture.export.features import boundary_loops

    v = np.asarray(vertices, np.float64)
    p = np.asarray(points, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"vertices (V, 3) and points (L, 3) expected, got {v.shape} and {p.shape}")
    labels = np.full(len(p), FACE, np.int64)
    openings = boundary_loops(faces)[1:4]
    if len(openings) < 3 or len(p) == 0:
        return labels
    centres = np.stack([v[loop].mean(0) for loop in openings])
    mouth = int(np.argmin(centres[:, 1]))
    eyes = [k for k in range(3) if k != mouth]
    xm = centres[mouth, 0]
    above = (centres[eyes, 1] > centres[mouth, 1]).all()
    either_side = (centres[eyes[0], 0] - xm) * (centres[eyes[1], 0] - xm) < 0
    if not (above and either_side):
        return labels
    d_mouth = _nearest(p, v[openings[mouth]])
    d_eyes = np.minimum(*(_nearest(p, v[openings[k]]) for k in eyes))
    labels[d_eyes < eyes_mm] = EYES
    labels[d_mouth < mouth_mm] = MOUTH
    return labels


def _nearest(points: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Each point's distance to the nearest of a loop's vertices (a loop has ~100: no tree needed, and no scipy,
    whose own BLAS would load into the run's process after its pools were limited)."""
    return np.sqrt(((points[:, None, :] - loop[None, :, :]) ** 2).sum(-1).min(1))


@dataclass(frozen=True)
class UnexplainedSpan:
    """Frames ``first``..``last`` (video frame numbers, ``frames`` of them judged) where ``region``'s landmarks
    are fitted at ``mean_ratio`` (at most ``peak_ratio``, at ``peak_frame``) times the take's noise RMS."""

    region: str
    first: int
    last: int
    frames: int
    mean_ratio: float
    peak_ratio: float
    peak_frame: int

    def to_dict(self) -> dict:
        d = asdict(self)
        d["mean_ratio"], d["peak_ratio"] = round(self.mean_ratio, 3), round(self.peak_ratio, 3)
        return d


def chance_ratio(count: np.ndarray, p_false: float) -> np.ndarray:
    """The RMS ratio that ``count`` landmarks of pure noise exceed with probability ``p_false``: their squared
    residuals over ``sigma^2`` sum to a chi-square with ``k = 2 count`` degrees of freedom, whose upper quantile is
    Wilson and Hilferty's ``k (1 - 2 / (9 k) + z sqrt(2 / (9 k)))^3`` with ``z`` the normal's (within 0.3 % of
    the exact ratio from 5 landmarks on; no scipy in the run's process, see :func:`_nearest`)."""
    from statistics import NormalDist

    k = 2.0 * np.maximum(np.asarray(count, np.float64), 1.0)
    z = NormalDist().inv_cdf(1.0 - float(p_false))
    return np.sqrt((1.0 - 2.0 / (9.0 * k) + z * np.sqrt(2.0 / (9.0 * k))) ** 3)


#: The residual lengths' histogram (px) that the take's median is read from: bins 1.2 % wide (200 a decade) from
#: 1e-3 to 1e4 px, and one below and one above.
_LOG_LO, _LOG_HI, _PER_DECADE = -3.0, 4.0, 200
_BINS = int((_LOG_HI - _LOG_LO) * _PER_DECADE) + 2


def _bins(r: np.ndarray) -> np.ndarray:
    """The histogram bin of each residual length ``r`` (px, >= 0): 0 below 1e-3 px, ``_BINS - 1`` from 1e4 px."""
    with np.errstate(divide="ignore"):
        k = np.floor((np.log10(r) - _LOG_LO) * _PER_DECADE) + 1
    return np.clip(np.nan_to_num(k, nan=0.0, neginf=0.0), 0, _BINS - 1).astype(np.int64)


class ResidualTally:
    """Frame by frame, what :meth:`spans` needs of a take's landmark residuals, in memory that does not grow with
    the landmark count: per frame and region the sum of squared residuals and the count, and one histogram of
    every residual's length (for the take's median).

    ``labels`` ``(L,)``: each landmark's region (:func:`landmark_regions`). Frames may come in any order
    (:meth:`add`); they are judged in frame order."""

    def __init__(self, labels: np.ndarray):
        labels = np.asarray(labels, np.int64)
        if labels.ndim != 1 or (labels.size and (labels.min() < 0 or labels.max() >= len(REGIONS))):
            raise ValueError(f"labels (L,) in 0..{len(REGIONS) - 1} expected, got shape {labels.shape}")
        self.labels = labels
        self._onehot = (labels[:, None] == np.arange(len(REGIONS))[None, :]).astype(np.float64)   # (L, R)
        self._hist = np.zeros(_BINS, np.int64)
        self._frames: list[int] = []
        self._sumsq: list[np.ndarray] = []
        self._count: list[np.ndarray] = []

    @classmethod
    def on_template(cls, template, points: np.ndarray) -> ResidualTally:
        """A tally for landmarks at ``points`` ``(L, 3)`` (mm) on ``template`` (the actor's, with ``vertices`` and
        ``faces``), regions by :func:`landmark_regions`."""
        return cls(landmark_regions(np.asarray(template.vertices), np.asarray(template.faces), points))

    def add(self, frame: int, residual_px: np.ndarray, used: np.ndarray) -> None:
        """One fitted frame: ``residual_px`` ``(L,)`` each landmark's residual length (fitted minus detected, px),
        ``used`` ``(L,)`` bool the ones to judge (confident, detected)."""
        r = np.asarray(residual_px, np.float64).reshape(-1)
        u = np.asarray(used, bool).reshape(-1)
        if r.shape != self.labels.shape or u.shape != self.labels.shape:
            raise ValueError(f"{len(self.labels)} landmark residuals expected, got {r.shape} and {u.shape}")
        u &= np.isfinite(r)
        self._hist += np.bincount(_bins(r[u]), minlength=_BINS)
        self._frames.append(int(frame))
        self._sumsq.append(np.where(u, r, 0.0) ** 2 @ self._onehot)
        self._count.append(u.astype(np.float64) @ self._onehot)

    @property
    def sigma(self) -> float:
        """The take's landmark noise per axis (px): the median residual length over every used landmark and frame,
        as a 2D Gaussian's (its length's median is ``sigma sqrt(2 ln 2)``). A median: the frames and regions the
        actor does not explain (a minority) barely move it. NaN before any used landmark."""
        total = int(self._hist.sum())
        if total == 0:
            return float("nan")
        cum = np.cumsum(self._hist)
        k = int(np.searchsorted(cum, total / 2.0))          # the bin that holds the median
        below = cum[k - 1] if k > 0 else 0
        inside = (total / 2.0 - below) / max(int(self._hist[k]), 1)   # how far into it, uniform in log
        log_r = _LOG_LO + (np.clip(k - 1 + inside, 0.0, _BINS - 2)) / _PER_DECADE
        return float(10.0 ** log_r / np.sqrt(2.0 * np.log(2.0)))

    def ratios(self, sigma: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(frames (T,), ratio (T, R), count (T, R))``: per frame and region the RMS residual of its used
        landmarks divided by the noise's (``sqrt(2) sigma``; default the take's) and how many it had; ratio NaN
        where a region had none."""
        s = self.sigma if sigma is None else float(sigma)
        frames = np.asarray(self._frames, np.int64)
        order = np.argsort(frames, kind="stable")
        sumsq = np.reshape(self._sumsq, (-1, len(REGIONS)))[order]
        count = np.reshape(self._count, (-1, len(REGIONS)))[order]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.sqrt(sumsq / count) / (np.sqrt(2.0) * s)
        return frames[order], ratio, count.astype(np.int64)

    def spans(self, ratio: float = RATIO, min_frames: int = MIN_FRAMES, max_gap: int = MAX_GAP,
              p_false: float = P_FALSE, sigma: float | None = None, min_sigma_px: float = MIN_SIGMA_PX
              ) -> tuple[float, list[UnexplainedSpan]]:
        """``(sigma, spans)``: the take's noise (px per axis; or the given one) and the runs of frames where a region
        is unexplained.

        A frame's region is unexplained when it has at least :data:`MIN_LANDMARKS` used landmarks and its RMS
        residual is above ``ratio`` times the noise's and above what its landmark count reaches by chance with
        probability ``p_false`` (:func:`chance_ratio`). The noise is taken as at least ``min_sigma_px``, so that a
        near noiseless detector (a synthetic one) does not turn sub-pixel differences into notes. Unexplained frames
        of a region with at most ``max_gap`` frames between them join into a run; runs of at least ``min_frames``
        judged frames are returned, in frame order."""
        s = self.sigma if sigma is None else float(sigma)
        if not np.isfinite(s):
            return s, []
        frames, rat, count = self.ratios(max(s, float(min_sigma_px)))
        with np.errstate(invalid="ignore"):
            bad = (count >= MIN_LANDMARKS) & (rat > np.maximum(ratio, chance_ratio(count, p_false)))
        spans = []
        for k, name in enumerate(REGIONS):
            idx = np.flatnonzero(bad[:, k])
            if idx.size == 0:
                continue
            for run in np.split(idx, np.flatnonzero(np.diff(frames[idx]) > max_gap + 1) + 1):
                if len(run) < min_frames:
                    continue
                peak = run[int(np.argmax(rat[run, k]))]
                spans.append(UnexplainedSpan(name, int(frames[run[0]]), int(frames[run[-1]]), len(run),
                                             float(np.mean(rat[run, k])), float(rat[peak, k]), int(frames[peak])))
        return s, sorted(spans, key=lambda sp: (sp.first, REGIONS.index(sp.region)))


def unexplained_spans(residual_px: np.ndarray, used: np.ndarray, labels: np.ndarray, frame_numbers: np.ndarray,
                      **kwargs) -> tuple[float, list[UnexplainedSpan]]:
    """:meth:`ResidualTally.spans` of a whole take at once: ``residual_px`` and ``used`` ``(T, L)``, ``labels``
    ``(L,)``, ``frame_numbers`` ``(T,)`` increasing; ``kwargs`` go to :meth:`ResidualTally.spans`."""
    r, u = np.asarray(residual_px), np.asarray(used)
    if r.ndim != 2 or r.shape != u.shape or len(frame_numbers) != len(r):
        raise ValueError(f"residual_px and used (T, L) and frame_numbers (T,) expected, got {r.shape}, {u.shape}, "
                         f"{np.shape(frame_numbers)}")
    tally = ResidualTally(labels)
    for f, rf, uf in zip(frame_numbers, r, u):
        tally.add(int(f), rf, uf)
    return tally.spans(**kwargs)
