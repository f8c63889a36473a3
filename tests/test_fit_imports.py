"""A 2D fit with the default preset does not pull in torch's compiler stack (seconds of import per run)."""

import subprocess
import sys
from pathlib import Path

SCRIPT = """
import sys, torch
from calib.projection import project_points
from models.fit import FIT_PRESETS, Observations, fit_sequence
from tests.test_fit import DIST, K, toy_actor, truth
actor = toy_actor(P=30, E=3)
head_R, head_t, face = truth(toy_actor(P=30, E=4), J=6)
res = fit_sequence(actor, Observations(points2d=project_points(face, K, DIST), K=K, dist=DIST), FIT_PRESETS["default"],
                   head_R, head_t + 5.0)
assert res.lm_iterations > 0 and not res.losses   # the Levenberg-Marquardt solve ran, Adam did not
print(" ".join(m for m in ("torch._dynamo", "sympy", "torch.fx.experimental.symbolic_shapes") if m in sys.modules))
"""


def test_default_2d_fit_does_not_import_the_compiler_stack():
    repo = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=repo, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "", f"imported by a default 2D fit: {out.stdout.strip()}"
