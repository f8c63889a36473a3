"""The trainer's closed-form solves reach the optimum of what they solve; Kabsch against scipy."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from capture.actor.training import resolve_settings
from models.rotation import kabsch
from models.train import ActorTrainer, model_config_for
from tests.tiny_actor import tiny_training_data


@pytest.fixture(scope="module")
def trainer(tmp_path_factory):
    root = tmp_path_factory.mktemp("solve")
    data, pivot = tiny_training_data(root)
    settings = resolve_settings("default", dict(width=48, iterations=1000))
    torch.manual_seed(0)
    tr = ActorTrainer(data, settings, model_config_for(data, settings, pivot))
    for _ in range(20):  # away from the initialisation, before any solve (first at 100)
        tr.step()
    return tr


def _terms(tr, names):
    t = tr.losses()
    return sum(t[n] for n in names)


def _grad_norm(tr, names, params):
    tr.optimizer.zero_grad(set_to_none=True)
    _terms(tr, names).backward()
    return sum(float(p.grad.norm() ** 2) for p in params) ** 0.5


def test_solve_anatomy_is_stationary_for_the_terms_it_solves(trainer):
    names = ["skin", "bone", "thickness", "thickness_reg"]
    params = [trainer.model.B.output.weight, trainer.model.B.output.bias,
              trainer.model.D.output.weight, trainer.model.D.output.bias]
    with torch.no_grad():
        before_loss = float(_terms(trainer, names))
    before_grad = _grad_norm(trainer, names, params)
    trainer.solve_anatomy()
    with torch.no_grad():
        after_loss = float(_terms(trainer, names))
    after_grad = _grad_norm(trainer, names, params)
    assert after_loss < before_loss
    # float32 evaluation of a float64 optimum: the gradient drops by orders of magnitude, not to 0.
    assert after_grad < 1e-3 * before_grad, (before_grad, after_grad)


def test_solve_expressions_is_stationary_for_the_skin_loss(trainer):
    params = [trainer.model.E.output.weight, trainer.model.E.output.bias]
    with torch.no_grad():
        before_loss = float(_terms(trainer, ["skin"]))
    before_grad = _grad_norm(trainer, ["skin"], params)
    trainer.solve_expressions()
    with torch.no_grad():
        assert float(_terms(trainer, ["skin"])) < before_loss
    assert _grad_norm(trainer, ["skin"], params) < 1e-3 * before_grad


def test_kabsch_recovers_a_known_rigid_motion():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 3)) * 30
    rot = Rotation.random(random_state=1)
    t = np.array([3.0, -2.0, 10.0])
    dst = rot.apply(src) + t + rng.normal(scale=1e-3, size=src.shape)
    R, tt = kabsch(torch.tensor(src), torch.tensor(dst))
    np.testing.assert_allclose(R.numpy(), rot.as_matrix(), atol=1e-4)
    np.testing.assert_allclose(tt.numpy(), t, atol=1e-3)
    # A mirrored point set still gives a proper rotation (det +1), as scipy's align_vectors does.
    Rm, _ = kabsch(torch.tensor(src), torch.tensor(dst * np.array([-1, 1, 1])))
    assert torch.linalg.det(Rm).item() == pytest.approx(1.0)
