"""Learning an actor: fit the AIM networks and per-shape jaw transforms to registered shapes.

Pure optimisation, no file I/O: :class:`ActorTrainer` takes tensors (:class:`TrainingData`) and
settings (:class:`TrainSettings`), exposes ``step()``, ``evaluate()`` and a checkpointable
``state_dict()``; the command line (``capture.actor.training``) owns progress, files and resume.

Presets (:data:`PRESETS`):

* ``paper``: the paper's settings - SIREN omega_0 = 30 in every layer, width 256, Adam lr 2e-3
  held constant for 1e4 iterations, every point in every step.
* ``default``: the project's - omega_0 = 30 on the first layer only (stable at lr 2e-3, see
  :mod:`models.siren`), 2,300 steps with a cosine learning-rate decay to 30 % of the start
  (``lr_final_fraction``): the first 85 % of them on 4,096 template points drawn uniformly (and the same share
  of the constrained points), the last 15 % on every point (``points_per_step``, ``sampled_until``; issue 13: on
  the sample the same final error as every point in every step, 0.0480 against 0.0474 mm, for half the
  steps' cost), and a closed-form solve of the linear output layers
  of E, B and D every 100 steps (``expression_solve_every``): with everything else fixed the skin
  loss is quadratic in E's output layer, so its least-squares optimum is one small linear solve
  (width x width) instead of thousands of Adam steps. Adam keeps its moments of a solved layer
  (``keep_moments_at_solves``). The hidden sine layers step at 3x the learning rate of the output
  layers (``hidden_lr_scale``, issue 13: on the sample actor 0.061 mm after 3,000 steps against
  0.086 mm without it). The symmetry term (weight 1e-4) sees the mirror images of 2,048 of the
  points, and the anatomy terms 2,048 of the constrained points, a new uniform draw each step
  (``symmetry_points``: a step costs 15 % less; ``constraint_points_per_step``: 16 % less with
  estimated bones, which constrain 4,859 of the sample's points; in the sampled steps the symmetry term sees
  the first 2,048 of the step's points). Where bfloat16 products are
  measured 2x faster than float32 (CPUs with AMX, GPUs) the hidden layers multiply
  in bfloat16 for the first 85 % of the steps (``hidden_matmul="auto"``, :mod:`models.precision`).
  The networks read the template through the input chart (``input_chart``).
* ``fast``: the same five networks and losses in 2,000 cheaper steps (issue 13; it ends at a
  higher error than ``default`` in a sixth of its CPU time, BENCHMARKS.md):
  E is solved before the first step (the expression field starts at the fit of the shape deltas)
  and every 10 steps, B's and D's output layers jointly every 50 (``solve_anatomy``); each Adam
  step sees 2,048 template points (and the same share of the constrained points), half of them
  drawn where the per-vertex error of the last solve is large; the solves always use every
  point. Once solved, those output layers are left out of Adam (``freeze_solved_layers``): a
  fresh Adam state moves every weight of a just-solved layer by about lr in its first step,
  which took the mean error from 0.24 to 0.98 mm within 4 steps of a solve.
  Each network runs only on the points its losses need (:meth:`ActorTrainer.losses`). The hidden
  sine layers step at 3x the learning rate of the output layers (``hidden_lr_scale``: the
  previous preset's end error in 2.7x less CPU), and the symmetry term (weight 1e-4) sees the
  mirror images of 256 of the step's points, not all 2,048 (``symmetry_points``; 10 % cheaper
  steps); bfloat16 products where they are faster, as in ``default``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch

from models.aim import AIMConfig, AnatomicalFaceModel
from models.checks import check_shapes
from models.input_chart import InputChart
from models.losses import (LossWeights, anatomy_losses, skin_position_loss, skinning_weight_loss,
                           symmetry_loss, thickness_regularizer)
from models.precision import hidden_matmul_dtype, resolve_hidden_matmul
from models.rotation import identity_6d, kabsch, matrix_to_rot6d, rot6d_to_matrix


@dataclass(frozen=True)
class TrainSettings:
    """Settings of one actor training (saved in the actor package)."""

    iterations: int = 3000
    lr: float = 2e-3
    lr_final_fraction: float = 0.01
    """Cosine decay of the learning rate to this fraction of ``lr``; 1.0 keeps it constant."""
    hidden_lr_scale: float = 1.0
    """Adam's learning rate of the hidden (sine) layers of the five networks relative to ``lr``
    (the output layers and the jaw transforms keep ``lr``). With ``hidden_omega_0 = 1`` a step of
    lr moves a hidden layer 30 times less, relative to its weights, than in the paper's
    ``omega_0 = 30`` parametrisation; a scale of 3 gives part of that speed back (issue 13)."""
    width: int = 256
    depth: int = 3
    first_omega_0: float = 30.0
    hidden_omega_0: float = 1.0
    points_per_step: int = 0
    """Template points sampled per step; 0 = all points every step. The constrained points are
    subsampled in the same proportion."""
    sampled_until: float = 1.0
    """With ``points_per_step``, the fraction of the iterations that sample points; the rest step on every
    point (as ``points_per_step`` 0)."""
    constraint_points_per_step: int = 0
    """Of a step on every template point (``points_per_step`` 0), how many of the constrained points carry
    the anatomy terms: a new uniform draw each step; 0 = all of them. The terms are means over the
    points, so a draw keeps them unbiased, and the closed-form solves still use every point. With
    estimated bones there are 2.5x as many constrained points as with fitted ones (the sample: 4,859
    against 1,979), and B, D and N on them made a step 44 % dearer (issue 13)."""
    importance: float = 0.0
    """Fraction of the sampled points drawn in proportion to the current per-vertex error (known
    from the last closed-form solve), the rest uniformly; 0 = uniform sampling."""
    symmetry_points: int = 0
    """How many of the step's points also carry the symmetry term, whose B evaluation at the
    mirrored points is a third of a sampled step's work (a seventh of a full step's) for a term of
    weight 1e-4: of a sample the first (a uniform subset of its draws), of a step on every point a
    uniform draw without repetition; 0 = all of them."""
    importance_reweight: bool = True
    """Weight each sampled point by ``1 / (V q)`` (q its probability) so that the per-point means
    of the losses stay unbiased estimates of the paper's means over all points."""
    keep_moments_at_solves: bool = False
    """Keep Adam's running moments of an output layer when a closed-form solve sets it. Restarted moments
    make Adam's next step move every weight of the solved layer by about lr (its first step is
    ``lr * sign(g)``), which undoes much of the solve: the mean error rose 30-40 % within 50 steps of
    each solve. Kept, the steps stay scaled by the layer's history (issue 13: -15 to -30 % error at
    equal steps). Only matters while the solved layers stay in Adam (``freeze_solved_layers`` off)."""
    freeze_solved_layers: bool = False
    """Leave the output layers that the closed-form solves set (B, D when ``anatomy_solve``, E) out
    of Adam once they have been solved: between solves they stay at their least-squares optimum
    for the features of the last solve instead of following the noisy sampled gradient."""
    solve_at_start: bool = False
    """Solve E's output layer once before the first step: the expression field then starts at the
    least-squares fit of the shape deltas (what LBS of the initial neutral leaves). (B and D wait
    for the first scheduled solve: with the random initial normals their joint solve is poor.)"""
    expression_solve_every: int = 100
    """Closed-form solve of E's output layer every this many steps (0 = never, as in the paper)."""
    expression_solve_ridge: float = 1e-6
    anatomy_solve: bool = True
    """Also solve B's and D's output layers jointly (``solve_anatomy``)."""
    anatomy_solve_every: int = 0
    """Steps between the anatomy solves (0 = with every expression solve)."""
    expression_solve_start: float = 0.0
    """The first closed-form solve waits for this fraction of the iterations, so that the jaw
    (LBS) explains the rigid part of the motion before the expression basis absorbs it."""
    jaw_skinning_prior: float = 1.0
    """Weight of ``mean (K(c_j) - 1)^2`` on points constrained to the jaw bone: the counterpart of
    the paper's forehead loss that tells the skinning which points ride on the mandible
    (0 = off, as in the paper)."""
    hidden_matmul: str = "fp32"
    """Precision of the hidden sine layers' products in Adam's steps: ``"fp32"``, ``"bf16"`` (inputs
    and weights rounded to bfloat16 for the product, float32 otherwise) or ``"auto"`` (bfloat16
    where this device multiplies it at least 2x faster, measured at the start; the choice is kept
    in the checkpoint and the actor). See :mod:`models.precision`."""
    hidden_matmul_until: float = 0.85
    """With bfloat16 products, the fraction of the iterations that use them; the rest, every
    closed-form solve and every evaluation run in float32, so the actor ends as a float32 fit."""
    input_chart: float = 0.0
    """The networks read each template point this fraction of the way to the shape that tears the
    neutral's surface most (the mouth opening, where the touching lips part; :mod:`models.input_chart`);
    0 = at the point itself, as in the paper."""
    seed: int = 0
    weights: LossWeights = field(default_factory=LossWeights)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainSettings":
        d = dict(d)
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown training settings: {sorted(unknown)}")
        if isinstance(d.get("weights"), dict):
            d["weights"] = LossWeights(**d["weights"])
        return cls(**d)


PRESETS: dict[str, TrainSettings] = {
    "default": TrainSettings(iterations=2300, lr_final_fraction=0.3, hidden_lr_scale=3.0, symmetry_points=2048,
                             hidden_matmul="auto", input_chart=0.3, keep_moments_at_solves=True,
                             constraint_points_per_step=2048, points_per_step=4096, sampled_until=0.85),
    "fast": TrainSettings(iterations=2000, points_per_step=2048, importance=0.5, importance_reweight=False,
                          expression_solve_every=10, anatomy_solve_every=50, solve_at_start=True,
                          freeze_solved_layers=True, hidden_lr_scale=3.0, symmetry_points=256, hidden_matmul="auto",
                          input_chart=0.3),
    "paper": TrainSettings(iterations=10_000, lr=2e-3, lr_final_fraction=1.0, width=256, depth=3,
                           first_omega_0=30.0, hidden_omega_0=30.0, expression_solve_every=0, anatomy_solve=False,
                           jaw_skinning_prior=0.0, points_per_step=0, importance=0.0, solve_at_start=False),
}


@dataclass
class TrainingData:
    """Everything an actor learns from, as tensors in millimetres.

    Shapes: V template vertices, N training shapes (neutral first), M constrained points,
    F forehead points.
    """

    template: torch.Tensor            # (V, 3) template points c
    shapes: torch.Tensor              # (N, V, 3) registered shapes, shapes[0] = neutral
    constraint_points: torch.Tensor   # (M, 3) template points carrying anatomy constraints
    bone_target: torch.Tensor         # (M, 3)
    thickness_target: torch.Tensor    # (M,)
    normal_target: torch.Tensor       # (M, 3)
    forehead_points: torch.Tensor     # (F, 3) template points where k should be 0
    jaw_points: torch.Tensor          # (J, 3) template points constrained to the jaw bone (k near 1)
    jaw_positions: torch.Tensor       # (N, J, 3) where those points are in each training shape
    symmetry_normal: torch.Tensor     # (3,) unit normal of the symmetry plane
    symmetry_offset: float            # plane {x : x . n = offset}
    faces: torch.Tensor | None = None         # (T, 3) the template's triangles (for the input chart)
    chart_offset: torch.Tensor | None = None  # (V, 3) mm, the input chart's move of each vertex; None: no chart

    def __post_init__(self):
        check_shapes({
            "template": (self.template, "V,3"), "shapes": (self.shapes, "N,V,3"),
            "constraint_points": (self.constraint_points, "M,3"), "bone_target": (self.bone_target, "M,3"),
            "thickness_target": (self.thickness_target, "M"), "normal_target": (self.normal_target, "M,3"),
            "forehead_points": (self.forehead_points, "F,3"), "jaw_points": (self.jaw_points, "J,3"),
            "jaw_positions": (self.jaw_positions, "N,J,3"),
            "symmetry_normal": (self.symmetry_normal, "3"),
            **({} if self.chart_offset is None else {"chart_offset": (self.chart_offset, "V,3"),
                                                     "faces": (self.faces, "T,3")}),
        })
        if self.shapes.shape[0] < 2:
            raise ValueError("training needs the neutral and at least one expression")

    def reflect(self, x: torch.Tensor) -> torch.Tensor:
        """Mirror points ``(*, 3)`` about the symmetry plane."""
        n = self.symmetry_normal
        return x - 2.0 * ((x @ n) - self.symmetry_offset).unsqueeze(-1) * n

    def to(self, device) -> "TrainingData":
        moved = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in self.__dict__.items()}
        return TrainingData(**moved)


@dataclass
class Sample:
    """The points of one stochastic step."""

    index: torch.Tensor | None             # (P,) template vertex indices (may repeat), None = every point
    weights: torch.Tensor | None           # (P,) importance weights 1 / (V q), None = uniform
    constraint_index: torch.Tensor | None  # (M',) constrained points used, None = all
    symmetry_index: torch.Tensor | None = None
    """(S,) positions among the step's points that carry the symmetry term; None = the first
    ``symmetry_points`` of a sample (a uniform subset of its draws), or every point."""


@dataclass
class Evaluation:
    """Quality figures of the current model (all lengths mm)."""

    shape_mean_mm: list[float]
    shape_max_mm: list[float]
    bone_mm: float            # mean |b~ - b| on constrained points
    thickness_mm: float       # mean |d~ - d| on constrained points
    normal_deg: float         # mean angle between n~ and n on constrained points
    symmetry_mm: float        # mean ||B(R(c)) - R(B(c))|| over template points
    forehead_k: float         # mean |k| on the forehead region
    jaw_vertices: int = 0     # template points that follow the jaw (skinning weight k > 0.5)

    @property
    def mean_mm(self) -> float:
        return float(sum(self.shape_mean_mm) / len(self.shape_mean_mm))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["mean_mm"] = self.mean_mm
        return d


def model_config_for(data: TrainingData, settings: TrainSettings, jaw_pivot) -> AIMConfig:
    """The model architecture and normalisation for ``data`` under ``settings``."""
    lo = data.template.min(0).values
    hi = data.template.max(0).values
    return AIMConfig(
        n_expressions=data.shapes.shape[0] - 1,
        center=tuple(float(v) for v in (lo + hi) / 2),
        scale=float((hi - lo).max() / 2),
        jaw_pivot=tuple(float(v) for v in jaw_pivot),
        width=settings.width, depth=settings.depth,
        first_omega_0=settings.first_omega_0, hidden_omega_0=settings.hidden_omega_0,
    )


class ActorTrainer:
    """Owns the model, the per-shape jaw transforms and the optimiser of one actor training."""

    def __init__(self, data: TrainingData, settings: TrainSettings, config: AIMConfig,
                 device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.data = data.to(self.device)
        self.settings = settings
        torch.manual_seed(settings.seed)
        self.model = AnatomicalFaceModel(config).to(self.device)
        d = self.data
        if d.chart_offset is not None:
            self.model.chart = InputChart(d.template, d.faces, d.chart_offset).to(self.device)
        with torch.no_grad():  # where the networks read each point set (models/input_chart.py), once
            at = self.model.chart_points
            self.chart = {"template": at(d.template), "constraint": at(d.constraint_points),
                          "reflected": at(d.reflect(d.template)), "forehead": at(d.forehead_points),
                          "jaw": at(d.jaw_points)}
        n_expr = config.n_expressions
        self.jaw_rot6d = torch.nn.Parameter(identity_6d(n_expr, device=self.device))
        # The jaw translation is optimised in units of ``length_unit_mm`` so that Adam's steps
        # (about lr per iteration) move it as fast as the rotation, not 10x slower in mm.
        self.jaw_t_units = torch.nn.Parameter(torch.zeros(n_expr, 3, device=self.device))
        if settings.hidden_lr_scale == 1.0:  # one group, in the order of earlier checkpoints
            groups = [{"params": list(self.model.parameters()) + [self.jaw_rot6d, self.jaw_t_units]}]
        else:
            hidden = [p for n, p in self.model.named_parameters() if ".layers." in n]
            others = [p for n, p in self.model.named_parameters() if ".layers." not in n]
            groups = [{"params": others + [self.jaw_rot6d, self.jaw_t_units]},
                      {"params": hidden, "lr": settings.lr * settings.hidden_lr_scale}]
        self.optimizer = torch.optim.Adam(groups, lr=settings.lr)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, self._lr_factor)
        self._init_jaw()
        self.hidden_matmul = resolve_hidden_matmul(settings.hidden_matmul, self.device, config.width)
        """The resolved ``hidden_matmul`` (``"fp32"`` or ``"bf16"``) of this training."""
        self.generator = torch.Generator(device="cpu").manual_seed(settings.seed)
        self.iteration = 0
        self._solved: set[torch.nn.Parameter] = set()  # output layers set by a closed-form solve
        self.vertex_error: torch.Tensor | None = None
        """(V,) per-vertex RMS training error (mm) at the last closed-form solve (importance sampling)."""

    @torch.no_grad()
    def _init_jaw(self) -> None:
        """Start each shape's jaw transform at the rigid motion of its jaw-constrained skin points.

        A least-squares rigid fit (Kabsch) of where the points over the mandible went in shape i
        gives the jaw's rotation about the pivot and its translation; the networks then learn the
        rest. Without at least 3 such points the jaw starts at rest (the paper's initialisation).
        """
        d = self.data
        if d.jaw_points.shape[0] < 3:
            return
        rest = d.jaw_positions[0].expand_as(d.jaw_positions[1:])
        R, t0 = kabsch(rest, d.jaw_positions[1:])
        pivot = self.model.jaw_pivot
        t = t0 + (R @ pivot) - pivot
        self.jaw_rot6d.copy_(matrix_to_rot6d(R))
        self.jaw_t_units.copy_(t / self.settings.weights.length_unit_mm)

    @property
    def jaw_t(self) -> torch.Tensor:
        """Jaw translations ``(N-1, 3)`` in mm."""
        return self.jaw_t_units * self.settings.weights.length_unit_mm

    def jaw_translation(self) -> torch.Tensor:
        return self.jaw_t

    def _lr_factor(self, it: int) -> float:
        f = self.settings.lr_final_fraction
        if f >= 1.0:
            return 1.0
        progress = min(it / max(self.settings.iterations, 1), 1.0)
        return f + (1 - f) * 0.5 * (1 + math.cos(math.pi * progress))

    def work(self, iterations: int) -> float:
        """Cost of the first ``iterations`` steps in units of a step on every template point.

        A step that samples ``points_per_step`` of the V points costs about ``points_per_step / V`` of one on
        every point (measured 0.39 for 4,096 of the sample's 9,409); what the time left is reckoned from."""
        sampled = min(iterations, self.sampled_steps)
        return sampled * self.settings.points_per_step / self.data.template.shape[0] + (iterations - sampled)

    @property
    def sampled_steps(self) -> int:
        """How many of the steps, the first ones, draw ``points_per_step`` points (the rest step on every point)."""
        s, n = self.settings, self.data.template.shape[0]
        return math.ceil(s.sampled_until * s.iterations) if 0 < s.points_per_step < n else 0

    def _sample(self) -> Sample | None:
        """The points of one step: all (None), or ``points_per_step`` of them (see TrainSettings)."""
        s, n = self.settings, self.data.template.shape[0]
        p = s.points_per_step if self.iteration < self.sampled_steps else 0
        g = self.generator
        if p <= 0 or p >= n:
            m = self.data.constraint_points.shape[0]
            con = None
            if 0 < s.constraint_points_per_step < m:
                con = torch.randperm(m, generator=g)[:s.constraint_points_per_step].to(self.device)
            sym = None
            if 0 < s.symmetry_points < n:
                sym = torch.randperm(n, generator=g)[:s.symmetry_points].to(self.device)
            return None if con is None and sym is None else Sample(None, None, con, sym)
        weights = None
        if s.importance > 0 and self.vertex_error is not None:
            err = self.vertex_error.double().cpu()
            prob = (1 - s.importance) / n + s.importance * err / err.sum().clamp_min(1e-12)
            index = torch.multinomial(prob, p, replacement=True, generator=g)
            if s.importance_reweight:
                weights = (1.0 / (n * prob[index])).float().to(self.device)
        else:
            index = torch.randperm(n, generator=g)[:p]
        m = self.data.constraint_points.shape[0]
        mc = min(m, math.ceil(m * p / n))
        con_index = torch.randperm(m, generator=g)[:mc] if mc < m else None
        return Sample(index.to(self.device), weights, None if con_index is None else con_index.to(self.device))

    def losses(self, sample: "Sample | None" = None) -> dict[str, torch.Tensor]:
        """Weighted loss terms on the points of ``sample`` (all when None); key ``total`` sums them.

        Each network runs only on the points its terms need: B, D and N on the skin and the
        constrained points (B also on the mirror images of the points that carry the symmetry term:
        all, or ``sample.symmetry_index``, or the first ``symmetry_points`` of a sample), K on the
        skin, forehead and jaw points, E on the skin.
        """
        w, unit, d, model = self.settings.weights, self.settings.weights.length_unit_mm, self.data, self.model
        index = None if sample is None else sample.index
        pw = None if sample is None else sample.weights
        pick = lambda a, i: a if i is None else a[i]
        c, xc = pick(d.template, index), pick(self.chart["template"], index)
        target = d.shapes if index is None else d.shapes[:, index]
        ci = None if sample is None else sample.constraint_index
        cc, xcc = pick(d.constraint_points, ci), pick(self.chart["constraint"], ci)
        bone_t = d.bone_target if ci is None else d.bone_target[ci]
        thick_t = d.thickness_target if ci is None else d.thickness_target[ci]
        normal_t = d.normal_target if ci is None else d.normal_target[ci]
        m, mc, mf = c.shape[0], cc.shape[0], d.forehead_points.shape[0]
        sym = None if sample is None else sample.symmetry_index
        if sym is None:
            ns = m if sample is None or self.settings.symmetry_points <= 0 else min(m, self.settings.symmetry_points)
            sym = slice(0, ns)
        reflected = d.reflect(c[sym])
        x = model.normalize(torch.cat([xc, xcc, pick(self.chart["reflected"], index)[sym]], dim=0))
        out_b = model.B(x)
        out_d, out_n = model.D(x[:m + mc]), model.N(x[:m + mc])
        out_k = model.K(model.normalize(torch.cat([xc, self.chart["forehead"], self.chart["jaw"]], dim=0)))
        skin = model.assemble(c, {"B": out_b[:m], "D": out_d[:m], "N": out_n[:m], "K": out_k[:m],
                                  "E": model.E(x[:m])})
        con = model.assemble(cc, {"B": out_b[m:m + mc], "D": out_d[m:], "N": out_n[m:]})
        bone_of_reflected = model.assemble(reflected, {"B": out_b[m + mc:]}).bone
        pred = model.training_shapes(skin, self.jaw_rot6d, self.jaw_translation())
        lb, ld, ln = anatomy_losses(con.bone, con.thickness, con.normal, bone_t, thick_t, normal_t, unit)
        terms = {
            "skin": w.skin * skin_position_loss(pred, target, unit, pw),
            "bone": w.bone * lb, "thickness": w.thickness * ld, "normal": w.normal * ln,
            "thickness_reg": w.thickness_reg * thickness_regularizer(skin.thickness, unit, pw),
            "symmetry": w.symmetry * symmetry_loss(bone_of_reflected, d.reflect(skin.bone[sym]), unit,
                                                   None if pw is None else pw[sym]),
            "forehead": w.forehead_skinning * skinning_weight_loss(out_k[m:m + mf].squeeze(-1)),
        }
        if self.settings.jaw_skinning_prior > 0:
            terms["jaw"] = self.settings.jaw_skinning_prior * skinning_weight_loss(out_k[m + mf:].squeeze(-1) - 1.0)
        terms["total"] = sum(terms.values())
        return terms

    def step(self) -> dict[str, float]:
        """One Adam step (plus the closed-form solves when due); returns the loss terms."""
        self.model.train()
        if self.iteration == 0 and self.settings.solve_at_start:
            self.solve_output_layers(anatomy=False)
        low = None
        if self.hidden_matmul == "bf16" and self.iteration < self.settings.hidden_matmul_until * self.settings.iterations:
            low = torch.bfloat16
        with hidden_matmul_dtype(self.model, low):
            terms = self.losses(self._sample())
            self.optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
        if self.settings.freeze_solved_layers:
            for p in self._solved:
                p.grad = None  # Adam skips parameters without a gradient
        self.optimizer.step()
        self.scheduler.step()
        self.iteration += 1
        every = self.settings.expression_solve_every
        start = self.settings.expression_solve_start * self.settings.iterations
        if every > 0 and self.iteration % every == 0 and self.iteration >= start:
            every_anatomy = self.settings.anatomy_solve_every or every
            self.solve_output_layers(anatomy=self.settings.anatomy_solve and self.iteration % every_anatomy == 0)
        return {k: float(v.detach()) for k, v in terms.items()}

    @torch.no_grad()
    def solve_output_layers(self, anatomy: bool = True) -> None:
        """The closed-form solves: B's and D's output layers (when ``anatomy``), then E's.

        The sine features of the five networks at the template points are computed once and
        shared by both solves (the output layers are all that changes between them).
        """
        x = self.model.normalize(self.chart["template"])
        features = {name: getattr(self.model, name).features(x) for name in self.model.NETWORKS}
        if anatomy:
            self.solve_anatomy(features)
        self.solve_expressions(features)

    def _template_anatomy(self, features: dict[str, torch.Tensor] | None):
        """(Anatomy at the template points, sine features per network) - features computed if None."""
        model = self.model
        if features is None:
            x = model.normalize(self.chart["template"])
            features = {name: getattr(model, name).features(x) for name in model.NETWORKS}
        raw = {name: getattr(model, name).output(h) for name, h in features.items()}
        return model.assemble(self.data.template, raw), features

    @torch.no_grad()
    def solve_expressions(self, features: dict[str, torch.Tensor] | None = None) -> None:
        """Set E's linear output layer to its least-squares optimum with everything else fixed.

        Shape i >= 1 is ``LBS(s0, T_i, k) + expression_mm * (H W_i^T + b_i)`` where H are the last
        sine features of E at the template points; the skin loss is quadratic in (W, b), so the
        optimum solves one ridge-regularised normal equation shared by all 3(N-1) outputs.
        """
        d, model = self.data, self.model
        anatomy, features = self._template_anatomy(features)
        pred = model.training_shapes(anatomy, self.jaw_rot6d, self.jaw_t)[1:]  # (N-1, V, 3)
        scale = model.config.expression_mm
        e_now = anatomy.expressions.permute(1, 0, 2)                     # (N-1, V, 3)
        residual = (d.shapes[1:] - (pred - e_now)) / scale                 # target of H W^T + b
        target = residual.permute(1, 0, 2).reshape(d.template.shape[0], -1)  # (V, 3(N-1))
        h = features["E"]
        h1 = torch.cat([h, torch.ones_like(h[:, :1])], dim=1).double()
        gram = h1.T @ h1
        gram += self.settings.expression_solve_ridge * torch.trace(gram) / gram.shape[0] * torch.eye(
            gram.shape[0], dtype=gram.dtype, device=gram.device)
        sol = torch.linalg.solve(gram, h1.T @ target.double())            # (width+1, 3(N-1))
        model.E.output.weight.copy_(sol[:-1].T.to(model.E.output.weight.dtype))
        model.E.output.bias.copy_(sol[-1].to(model.E.output.bias.dtype))
        # Per-vertex RMS error over the shapes after the solve: where importance sampling looks.
        n_expr = d.shapes.shape[0] - 1
        left = ((target.double() - h1 @ sol) * scale).reshape(-1, n_expr, 3).square().sum(-1).sum(1)
        left += (anatomy.neutral - d.shapes[0]).double().square().sum(-1)
        self.vertex_error = (left / (n_expr + 1)).sqrt().float()
        self._solved_now((model.E.output.weight, model.E.output.bias))

    @torch.no_grad()
    def solve_anatomy(self, features: dict[str, torch.Tensor] | None = None) -> None:
        """Set the linear output layers of B and D jointly to their least-squares optimum.

        With the sine features of B and D, the normals N, the skinning weights K, the jaw
        transforms and the expression basis E fixed, the neutral ``s0 = b + d n`` is linear in the
        output layers of B and D, and so is every training shape ``s_i = A_i s0 + r_i`` (LBS is
        linear in the rest position: ``A_i = (1 - k) I + k R_i``). The skin loss over all shapes,
        the bone and thickness terms of the anatomy loss and the thickness regulariser are then one
        quadratic in 4 (width + 1) unknowns, solved exactly here. (The symmetry term, weight 1e-4,
        is left to Adam.) Solving it makes b, d and n agree on the skin at once, which Adam alone
        reaches only slowly because each of the three networks must learn to cancel the others'
        errors.
        """
        d, model, w = self.data, self.model, self.settings.weights
        u2 = w.length_unit_mm ** 2
        f64 = torch.float64
        c = d.template.double()
        P, N = c.shape[0], d.shapes.shape[0]
        an, features = self._template_anatomy(features)
        pred = model.training_shapes(an, self.jaw_rot6d, self.jaw_t).double()     # (N, P, 3)
        eye = torch.eye(3, dtype=f64, device=c.device)
        R = torch.cat([eye[None], rot6d_to_matrix(self.jaw_rot6d).double()], 0)   # (N, 3, 3)
        k = an.skin_weight.double()[None, :, None, None]
        A = (1 - k) * eye + k * R[:, None]                                         # (N, P, 3, 3)
        s0 = an.neutral.double()
        y = d.shapes.double() - (pred - torch.einsum("npab,pb->npa", A, s0))     # targets of A s0
        G = torch.einsum("npab,npac->pbc", A, A)                                   # sum_i A^T A
        q = torch.einsum("npab,npa->pb", A, y) - torch.einsum("pab,pb->pa", G, c)
        n = an.normal.double()
        one = torch.ones(P, 1, dtype=f64, device=c.device)
        hB = torch.cat([features["B"].double(), one], 1)                          # (P, h1)
        hD = torch.cat([features["D"].double(), one], 1)
        h1 = hB.shape[1]
        sb, sd = model.config.bone_offset_mm, model.config.thickness_mm
        a_s = w.skin / (N * P * u2)
        Gn = torch.einsum("pab,pb->pa", G, n)
        M = torch.zeros(4 * h1, 4 * h1, dtype=f64, device=c.device)
        rhs = torch.zeros(4 * h1, dtype=f64, device=c.device)
        # The (width+1)^2 blocks are sums over the P points: float32 products (their rounding is
        # far below the ridge) and G's symmetry halve the cost of the solve.
        hBf, hDf, Gf, Gnf = hB.float(), hD.float(), G.float(), Gn.float()
        for a in range(3):
            for b in range(a, 3):
                blk = a_s * sb * sb * ((hBf.T * Gf[:, a, b]) @ hBf).double()
                M[a * h1:(a + 1) * h1, b * h1:(b + 1) * h1] = blk
                M[b * h1:(b + 1) * h1, a * h1:(a + 1) * h1] = blk.T
            bd = a_s * sb * sd * ((hBf.T * Gnf[:, a]) @ hDf).double()
            M[a * h1:(a + 1) * h1, 3 * h1:] = bd
            M[3 * h1:, a * h1:(a + 1) * h1] = bd.T
            rhs[a * h1:(a + 1) * h1] = a_s * sb * hB.T @ q[:, a]
        M[3 * h1:, 3 * h1:] = a_s * sd * sd * (hD.T * (n * Gn).sum(1)) @ hD
        rhs[3 * h1:] = a_s * sd * hD.T @ (n * q).sum(1)
        # thickness regulariser on every skin point
        M[3 * h1:, 3 * h1:] += w.thickness_reg / (P * u2) * sd * sd * hD.T @ hD
        m = d.constraint_points.shape[0]
        if m:
            xm = model.normalize(self.chart["constraint"])
            onem = torch.ones(m, 1, dtype=f64, device=c.device)
            hBm = torch.cat([model.B.features(xm).double(), onem], 1)
            hDm = torch.cat([model.D.features(xm).double(), onem], 1)
            a_b, a_d = w.bone / (m * u2), w.thickness / (m * u2)
            target_b = d.bone_target.double() - d.constraint_points.double()
            gram_bm = a_b * sb * sb * hBm.T @ hBm
            for a in range(3):
                M[a * h1:(a + 1) * h1, a * h1:(a + 1) * h1] += gram_bm
                rhs[a * h1:(a + 1) * h1] += a_b * sb * hBm.T @ target_b[:, a]
            M[3 * h1:, 3 * h1:] += a_d * sd * sd * hDm.T @ hDm
            rhs[3 * h1:] += a_d * sd * hDm.T @ d.thickness_target.double()
        M += self.settings.expression_solve_ridge * torch.trace(M) / M.shape[0] * torch.eye(
            M.shape[0], dtype=f64, device=c.device)
        theta = torch.linalg.solve(M, rhs)
        WB = theta[:3 * h1].reshape(3, h1)
        wD = theta[3 * h1:]
        for layer, W in ((model.B.output, WB), (model.D.output, wD[None])):
            layer.weight.copy_(W[:, :-1].to(layer.weight.dtype))
            layer.bias.copy_(W[:, -1].to(layer.bias.dtype))
            self._solved_now((layer.weight, layer.bias))

    def _solved_now(self, params) -> None:
        """``params`` were just set by a closed-form solve: restart their Adam moments, unless
        ``keep_moments_at_solves`` (see TrainSettings)."""
        for p in params:
            if not self.settings.keep_moments_at_solves:
                self.optimizer.state.pop(p, None)
            self._solved.add(p)

    def _at(self, c: torch.Tensor, points: str, networks=AnatomicalFaceModel.NETWORKS):
        """``model(c)`` for one of the trainer's point sets, read at its chart points computed once (only
        ``networks`` evaluated)."""
        x = self.model.normalize(self.chart[points])
        return self.model.assemble(c, {name: getattr(self.model, name)(x) for name in networks})

    @torch.no_grad()
    def evaluate(self) -> Evaluation:
        """Per-shape mean and max vertex error (mm) on every template point, and anatomy residuals."""
        self.model.eval()
        d = self.data
        anatomy = self._at(d.template, "template")
        err = (self.model.training_shapes(anatomy, self.jaw_rot6d, self.jaw_t) - d.shapes).norm(dim=-1)
        con = self._at(d.constraint_points, "constraint")
        cosang = (con.normal * d.normal_target).sum(-1).clamp(-1, 1)
        sym = (self._at(d.reflect(d.template), "reflected", ("B",)).bone - d.reflect(anatomy.bone)).norm(dim=-1)
        fore = self._at(d.forehead_points, "forehead").skin_weight if d.forehead_points.shape[0] else torch.zeros(1)
        return Evaluation(
            shape_mean_mm=[float(v) for v in err.mean(1)], shape_max_mm=[float(v) for v in err.max(1).values],
            bone_mm=float((con.bone - d.bone_target).norm(dim=-1).mean()) if len(cosang) else float("nan"),
            thickness_mm=float((con.thickness - d.thickness_target).abs().mean()) if len(cosang) else float("nan"),
            normal_deg=float(torch.rad2deg(torch.arccos(cosang)).mean()) if len(cosang) else float("nan"),
            symmetry_mm=float(sym.mean()), forehead_k=float(fore.abs().mean()),
            jaw_vertices=int((anatomy.skin_weight > 0.5).sum()),
        )

    def weights(self) -> dict:
        """A copy of what the actor is made of (the networks and the jaw transforms; no optimiser state)."""
        return {"model": {k: v.detach().clone() for k, v in self.model.state_dict().items()},
                "jaw_rot6d": self.jaw_rot6d.detach().clone(), "jaw_t_units": self.jaw_t_units.detach().clone()}

    def load_weights(self, weights: dict) -> None:
        """Back to a copy from :meth:`weights`."""
        self.model.load_state_dict(weights["model"])
        with torch.no_grad():
            self.jaw_rot6d.copy_(weights["jaw_rot6d"])
            self.jaw_t_units.copy_(weights["jaw_t_units"])

    def state_dict(self) -> dict:
        """Everything needed to continue training exactly (tensors and plain numbers only)."""
        return {
            "model": self.model.state_dict(),
            "jaw_rot6d": self.jaw_rot6d.detach().clone(), "jaw_t_units": self.jaw_t_units.detach().clone(),
            "optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
            "generator": self.generator.get_state(), "iteration": self.iteration,
            "vertex_error": self.vertex_error, "hidden_matmul": self.hidden_matmul,
            "solved_layers": sorted(n for n, p in self.model.named_parameters() if p in self._solved),
        }

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["model"])
        with torch.no_grad():
            self.jaw_rot6d.copy_(state["jaw_rot6d"])
            self.jaw_t_units.copy_(state["jaw_t_units"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        self.generator.set_state(state["generator"])
        self.iteration = int(state["iteration"])
        self.vertex_error = state.get("vertex_error")
        self.hidden_matmul = state.get("hidden_matmul", "fp32")  # a resumed training keeps its precision
        solved = set(state.get("solved_layers", ()))
        self._solved = {p for n, p in self.model.named_parameters() if n in solved}


