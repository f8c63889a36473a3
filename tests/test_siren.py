"""SIREN initialisation statistics (Sitzmann et al. 2020, Sec. 3.2 and supplement)."""

import math

import pytest
import torch

from models.siren import SineLayer, Siren


@pytest.mark.parametrize("hidden_omega", [1.0, 30.0])
def test_hidden_preactivations_stay_standard_normal_through_depth(hidden_omega):
    # SIREN's claim: with inputs uniform in [-1, 1], every hidden layer's pre-activation
    # omega_0 (W x + b) is close to normal with the weight part of unit variance (the bias adds a
    # little), at every depth. For z ~ N(0, s^2), sin(z) has mean 0 and variance (1 - exp(-2 s^2)) / 2.
    torch.manual_seed(0)
    net = Siren(3, 1, width=512, depth=5, first_omega_0=30.0, hidden_omega_0=hidden_omega)
    x = torch.rand(20000, 3) * 2 - 1
    h = net.layers[0](x)
    for layer in net.layers[1:]:
        pre = layer.preactivation(h)
        w_part = layer.omega_0 * (h @ layer.linear.weight.T)
        # Var(omega_0 W h) = n * Var(omega_0 w) * E[h^2] = 2 E[h^2]: about 1 for arcsine-like h.
        # 5 % covers the sampling noise of 512 x 512 weights.
        expected = 2 * h.square().mean().item()
        assert abs(w_part.var().item() / expected - 1.0) < 0.05
        assert 0.8 < expected < 1.1
        assert abs(pre.mean().item()) < 0.1
        h = torch.sin(pre)
        assert abs(h.mean().item()) < 0.05
        expected_var = (1 - math.exp(-2 * pre.var().item())) / 2
        assert abs(h.var().item() - expected_var) < 0.02


def test_first_layer_bounds_and_omega_as_constructor_argument():
    torch.manual_seed(0)
    first = SineLayer(3, 256, omega_0=45.0, is_first=True)
    hidden = SineLayer(256, 256, omega_0=45.0)
    assert first.linear.weight.abs().max() <= 1.0 / 3
    assert first.linear.weight.abs().max() > 0.9 / 3  # uniform over the whole range
    bound = math.sqrt(6 / 256) / 45.0
    assert hidden.linear.weight.abs().max() <= bound
    assert hidden.linear.weight.abs().max() > 0.95 * bound
    x = torch.randn(10, 3)
    torch.testing.assert_close(first(x), torch.sin(45.0 * first.linear(x)))


def test_siren_rejects_bad_sizes():
    with pytest.raises(ValueError, match="depth >= 1"):
        Siren(3, 1, depth=0)
