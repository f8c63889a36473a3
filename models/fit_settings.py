"""Settings of a sequence fit (:class:`FitSettings`) and the named presets: :data:`FIT_PRESETS` for
fits to 2D landmarks (``capture run``), :data:`FIT3D_PRESETS` for fits to registered meshes
(``capture fit3d``).

Shared by the fit's state (:mod:`models.fit_state`), energy (:mod:`models.fit_energy`) and solvers
(:mod:`models.fit`, :mod:`models.fit_lm`); see :mod:`models.fit` for the method.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace


@dataclass(frozen=True)
class FitSettings:
    """Settings of one sequence fit (saved with every run)."""

    iterations: int = 500
    lr: float = 5e-3
    lr_final_fraction: float = 0.1
    """Cosine decay to this fraction of ``lr``; 1.0 keeps it constant (the paper)."""
    code_dim: int = 32
    hidden: int = 128
    coeff_weight: float = 0.0075
    temporal_weight: float = 0.05
    length_unit_mm: float = 10.0
    robust_px: float = 3.0
    """Scale of the pseudo-Huber 2D loss in pixels (quadratic below, linear above); 0 = squared."""
    seed: int = 0
    warm_iterations: int | None = 150
    """Iterations of a window warm-started from the previous one (None: ``iterations``)."""
    early_stop_tol: float = 0.0
    """Stop when the mean loss of the last ``early_stop_every`` iterations improved on the block
    before by less than this fraction (0 = run all iterations, the paper)."""
    early_stop_every: int = 25
    pose_accel_weight: float = 0.0
    """Weight of the squared second differences over frames of the head and jaw transforms
    (translations in ``length_unit_mm``, rotation matrices unit-free): a smooth-motion prior that
    removes per-frame depth jitter of monocular fits. Not in the paper (0 there). This and the next
    two priors apply to 2D fits only (:func:`monocular_priors`)."""
    coeff_temporal_weight: float = 0.0
    """Weight of the squared first differences over frames of the coefficients ``w_j(c)`` (mean over
    points): keeps expressions from flickering. Not in the paper (0 there)."""
    jaw_prior_weight: float = 0.0
    """Weight of the squared distance of the jaw transform from its target (``jaw_prior_target``;
    translation in ``length_unit_mm``, rotation matrices subtracted): the jaw's translation along the
    view and an opening expression explain landmarks almost alike, and this keeps the jaw where
    nothing moves it. Not in the paper (0 there). The Levenberg-Marquardt solve holds the target fixed
    within a linearisation and moves it to the solved coefficients after every accepted step
    (:mod:`models.fit_lm`)."""
    jaw_prior_target: str = "rest"
    """What the jaw prior pulls towards: ``rest`` (identity, 0) or ``expressions``: the jaw that the
    frame's expression coefficients imply through the actor's learned jaw transform of each training
    shape (:meth:`~models.fit_state.ActorAtPoints.jaw_of`; rest for actors without them)."""
    lm_iterations: int = 0
    """Levenberg-Marquardt iterations on each frame's *base* (head and jaw pose, one coefficient
    offset per expression; :mod:`models.fit_lm`) before the Adam iterations, with the networks'
    outputs held fixed. 0 = none (the paper)."""
    lm_polish_iterations: int = 0
    """The same after the Adam iterations and the coefficient field (0 = none). Skipped when neither ran
    after a first solve (the 2D default): it would start at that solve's own minimum. It used to move
    the jaw prior's target to the solved coefficients, which the solve now does after every step."""
    lm_tol: float = 1e-6
    """Levenberg-Marquardt stops when an accepted step lowers the energy by less than this fraction."""
    adam_on_landmarks: bool = True
    """Run the Adam iterations on 2D landmark fits (3D fits always run them). False: a 2D fit is the
    Levenberg-Marquardt solve of the base alone and the networks keep their zero start (on synthetic
    takes with 1,000 landmarks the Adam phase changed the error by < 0.001 mm at 10x the time)."""
    field_centres: int = 0
    """Per-point coefficient field (:mod:`models.fit_field`): ``w_j(c)`` gets ``sum_b phi_b(c) a_jb``
    with ``phi`` normalised Gaussians around this many centres (farthest-point samples of the fit
    points) and per-frame ``a_jb (E,)`` solved by Gauss-Newton with the poses fixed. 0 = none (the
    paper, which leaves the spatial detail to F_W)."""
    field_sigma_mm: float = 12.0
    """Width of the field's Gaussians (mm on the template)."""
    field_weight: float = 0.0
    """Weight of the mean squared field coefficient ``a`` (keeps the field at 0 where landmarks say nothing)."""
    field_temporal_weight: float = 0.0
    """Weight of the squared first differences over frames of ``a`` (summed over centres and expressions)."""
    field_motion_weight: float = 0.0
    """Weight of the mean squared displacement the field adds (over frames and fit points, in
    ``length_unit_mm``): of the fields that explain the landmarks, the one that moves the face least,
    so a motion the camera cannot see (along its axis) is not invented."""
    field_iterations: int = 0
    """Gauss-Newton iterations of the field after each Levenberg-Marquardt solve of the base."""
    adaptive_ref_px: float = 0.0
    """Noise-adaptive smoothing of 2D fits (:mod:`models.fit_noise`): each window's ``coeff_temporal_weight``
    is multiplied by ``(sigma / adaptive_ref_px) * (adaptive_ref_landmarks / L)``, times
    ``(s / adaptive_ref_px_per_mm)^2`` when that is below 1,
    clamped to ``[1, adaptive_max]``, with ``sigma`` the landmark noise (px), ``L`` the landmarks per frame and
    ``s`` the face's px per mm, read from the previous window's landmarks and residuals (the first window is
    solved, read, and solved again). 0 = off (the prior as set; 3D fits always)."""
    adaptive_ref_landmarks: float = 800.0
    """The landmarks per frame at which ``coeff_temporal_weight`` was tuned."""
    adaptive_max: float = 30.0
    """The largest multiple of ``coeff_temporal_weight`` the noise may ask for."""
    adaptive_ref_px_per_mm: float = 0.0
    """The face's size in the image (px per mm, :func:`models.fit_noise.face_px_per_mm`) at which
    ``coeff_temporal_weight`` was tuned; a smaller face's scale is multiplied by ``(px_per_mm / this)^2`` (0 = not)."""

    def to_dict(self) -> dict:
        return asdict(self)


FIT_PRESETS: dict[str, FitSettings] = {
    # hidden 64: 3x cheaper than 128 per iteration at the same accuracy on synthetic takes;
    # temporal 0.5: codes of neighbouring frames held closer than the paper's 0.05, which halves the
    # per-frame depth jitter of monocular fits (benchmarks/bench_fit.py).
    # The base (head and jaw pose, per-frame coefficient offsets) by Levenberg-Marquardt before and
    # after Adam, with smooth-motion, jaw and coefficient-smoothness priors; on 2D takes the solve is
    # the base alone (adam_on_landmarks). Weights first chosen on a synthetic 1280x720 take of the demo
    # actor with 1,000 landmarks (benchmarks/bench_fit.py, BENCHMARKS.md "Take fitting"); issue 12 then
    # raised the jaw prior (0.01 -> 1.0) and pointed it at the jaw the coefficients imply, and lowered the
    # pseudo-Huber scale (3 -> 1 px) so that landmarks the actor cannot explain (expressions outside its
    # span) do not pull the head pose: chosen on held-out ICT performances of seed 100
    # (benchmarks/bench_outofspan.py; reported on seed 0) and checked on the in-span takes. With the
    # 1 px loss LM needs more steps to its 1e-6 tolerance (1.7x the time) for < 0.001 mm: lm_tol 1e-4;
    # issue 16 then took 1e-3 (a window's last step lowered its energy by 1e-5 - 5e-5; on seeds 100, 6,
    # 7 the same errors to 0.001 mm, jitter to 1e-5 mm, one linearisation fewer per window).
    # Issue 12 (detectors as users have them) then made the coefficients' temporal prior follow the landmarks'
    # noise and number (adaptive_ref_px: the noise the residuals read at the tuning conditions, 1,000
    # landmarks of which ~800 seen, 0.5 px, a 1280x720 camera with the face at 1.65 px per mm;
    # models/fit_noise.py).
    "default": FitSettings(hidden=64, lr=1e-2, temporal_weight=0.5, early_stop_tol=2e-3, lm_iterations=10,
                           lm_polish_iterations=10, pose_accel_weight=10.0, coeff_temporal_weight=1.0,
                           jaw_prior_weight=1.0, jaw_prior_target="expressions", robust_px=1.0,
                           lm_tol=1e-3, adam_on_landmarks=False, adaptive_ref_px=0.53,
                           adaptive_ref_px_per_mm=1.65),
    "paper": FitSettings(iterations=10_000, lr=1e-3, lr_final_fraction=1.0, coeff_weight=0.75, robust_px=0.0,
                         warm_iterations=None),
    # default + the per-point coefficient field (models/fit_field.py) on 2D takes: 32 centres (sigma 10 mm)
    # where the expressions act, least-motion prior; ~11x the default's time (offline quality). Chosen on
    # the tuning seed 100 of benchmarks/bench_outofspan.py (1,000 landmarks, 0.5 px): 0.803 mm against
    # 0.938 with 16 centres (sigma 12), 0.738 with 64 (sigma 8, 48x the default's time) and 1.052 for
    # the default.
    "field": FitSettings(hidden=64, lr=1e-2, temporal_weight=0.5, early_stop_tol=2e-3, lm_iterations=10,
                         lm_polish_iterations=10, pose_accel_weight=10.0, coeff_temporal_weight=1.0,
                         jaw_prior_weight=1.0, jaw_prior_target="expressions", robust_px=1.0,
                         adam_on_landmarks=False, field_centres=32, field_sigma_mm=10.0, field_iterations=2,
                         field_weight=1.0, field_temporal_weight=1.0, field_motion_weight=10.0, adaptive_ref_px=0.53,
                         adaptive_ref_px_per_mm=1.65),
}


#: Presets of fits to registered 3D meshes (``capture fit3d``; :func:`capture.fit.take.fit_meshes`).
#: ``default``: the base by Levenberg-Marquardt, then a dense per-point coefficient field (256 centres,
#: sigma 8 mm) solved by Gauss-Newton with every vertex constrained, light coefficient priors (3D data
#: leave nothing ambiguous), no Adam: on held-out ICT performances (benchmarks/bench_fit3d.py, tuning
#: seed 100) 0.111 mm against 0.284 mm for ``networks`` (the 3D default before: LM, Adam on F_T/F_W,
#: LM polish, 1,000 vertices) and 0.759 mm for the 19-shape blendshape fit; in span (training shapes)
#: 0.060 against 0.106 mm, at about the same time per frame. ``paper``: the paper's settings.
FIT3D_PRESETS: dict[str, FitSettings] = {
    "default": replace(FIT_PRESETS["default"], iterations=0, warm_iterations=None, coeff_weight=1e-4,
                       field_centres=256, field_sigma_mm=8.0, field_iterations=3, field_weight=1e-4,
                       adaptive_ref_px=0.0),
    "networks": replace(FIT_PRESETS["default"], adaptive_ref_px=0.0),
    "paper": FIT_PRESETS["paper"],
}
