"""bfloat16 products in the hidden SIREN layers (models.precision): the same function to bfloat16's
rounding, float32 outside the context and in the first layer, gradients along float32's, and a
training that uses them only for the first part of its steps, resumes exactly and ends in float32."""

from __future__ import annotations

import copy

import pytest
import torch

import models.precision as precision
import models.siren as siren
from capture.actor.training import resolve_settings
from models.precision import hidden_layers, hidden_matmul_dtype, resolve_hidden_matmul
from models.siren import SineLayer, Siren
from models.train import ActorTrainer, model_config_for
from tests.tiny_actor import tiny_training_data


def _net():
    torch.manual_seed(0)
    return Siren(3, 5, width=64, depth=3, first_omega_0=30.0, hidden_omega_0=1.0)


def test_bf16_products_compute_the_same_function_to_bfloat16_rounding():
    net = _net()
    x = torch.rand(500, 3) * 2 - 1
    ref = net(x)
    with hidden_matmul_dtype(net, torch.bfloat16):
        assert all(layer.matmul_dtype == torch.bfloat16 for layer in hidden_layers(net))
        low = net(x)
        first = net.layers[0](x)
    assert low.dtype == torch.float32
    # bfloat16 keeps 8 bits of mantissa: each product's inputs are off by <= 2^-9 (0.2 %) relative,
    # so a dot product of many such terms is off by about 0.2 % of its size (random signs): RMS over
    # two hidden layers and the output well under 1 % of the output's spread, and not 0.
    err = (low - ref).square().mean().sqrt() / ref.std()
    assert 1e-4 < err < 1e-2
    torch.testing.assert_close(first, net.layers[0](x), rtol=0, atol=0)  # the first layer stays float32
    torch.testing.assert_close(net(x), ref, rtol=0, atol=0)  # restored after the block
    assert all(layer.matmul_dtype is None for layer in hidden_layers(net))


def test_bf16_gradients_point_where_float32_gradients_do():
    net = _net()
    x = torch.rand(2000, 3) * 2 - 1
    target = torch.randn(2000, 5)

    def grads(dtype):
        net.zero_grad()
        with hidden_matmul_dtype(net, dtype):
            (net(x) - target).square().mean().backward()
        return torch.cat([p.grad.ravel() for p in net.parameters()])

    g32, g16 = grads(None), grads(torch.bfloat16)
    cos = torch.nn.functional.cosine_similarity(g32, g16, dim=0)
    assert cos > 0.999
    assert not torch.equal(g32, g16)
    for p in net.parameters():  # the weights themselves stay float32
        assert p.dtype == torch.float32 and p.grad.dtype == torch.float32


@pytest.mark.parametrize("onednn", ["probed", "not rounding"])
def test_hidden_layer_in_bf16_equals_a_readable_reference(onednn, monkeypatch):
    """On every CPU: oneDNN's bfloat16 mode where it rounds (AMX), else products of bfloat16 copies."""
    if onednn == "not rounding":
        monkeypatch.setattr(siren, "_ONEDNN_ROUNDS", False)
    torch.manual_seed(1)
    layer = SineLayer(32, 16, omega_0=30.0)
    layer.matmul_dtype = torch.bfloat16
    x = torch.randn(40, 32)
    w = (layer.linear.weight * 30.0).to(torch.bfloat16).float()
    product = x.to(torch.bfloat16).float() @ w.T  # exact products of bfloat16 inputs, float32 sums
    # the product comes back rounded to bfloat16: within half a unit in its 8th bit
    pre = layer.preactivation(x)
    bias = 30.0 * layer.linear.bias
    assert ((pre - bias - product).abs() <= 2.0 ** -8 * product.abs() + 1e-6).all()
    assert not torch.equal(pre, torch.nn.functional.linear(x, 30.0 * layer.linear.weight, bias))
    torch.testing.assert_close(layer(x), torch.sin(pre), rtol=0, atol=0)


def test_auto_follows_the_cpu_flags_and_measures_only_where_they_are_unknown(tmp_path, monkeypatch):
    """The same machine always makes the same choice: from its flags where Linux lists them (a timed probe
    moved with the load and flipped between two trainings started together); measured elsewhere."""
    def no_probe(device, width):
        raise AssertionError("the flags decide: no probe")

    monkeypatch.setattr(precision, "bf16_speedup", no_probe)
    cpus = {"amx": "model name\t: Xeon\nflags\t\t: fpu avx2 avx512f amx_bf16 amx_tile\n",
            "avx512_bf16": "model name\t: AMD EPYC\nflags\t\t: fpu avx2 avx512f avx512_bf16\n",
            "arm": "processor\t: 0\nFeatures\t: fp asimd sve bf16 i8mm\n",
            "avx512": "model name\t: Xeon\nflags\t\t: fpu avx2 avx512f\n",      # emulated bfloat16
            "arm_old": "processor\t: 0\nFeatures\t: fp asimd\n"}
    want = {"amx": "bf16", "avx512_bf16": "bf16", "arm": "bf16", "avx512": "fp32", "arm_old": "fp32"}
    for name, text in cpus.items():
        (tmp_path / name).write_text(text)
        assert resolve_hidden_matmul("auto", cpuinfo=tmp_path / name) == want[name], name
    missing = tmp_path / "missing"                            # not Linux: measured
    monkeypatch.setattr(precision, "bf16_speedup", lambda device, width: 5.0)
    assert resolve_hidden_matmul("auto", cpuinfo=missing) == "bf16"
    monkeypatch.setattr(precision, "bf16_speedup", lambda device, width: 0.3)  # emulated bfloat16
    assert resolve_hidden_matmul("auto", cpuinfo=missing) == "fp32"
    assert resolve_hidden_matmul("fp32") == "fp32" and resolve_hidden_matmul("bf16") == "bf16"
    with pytest.raises(ValueError, match="hidden_matmul"):
        resolve_hidden_matmul("half")


def test_bf16_speedup_is_a_positive_measurement():
    s = precision.bf16_speedup("cpu", width=32, rows=256)
    assert s > 0 and s == precision.bf16_speedup("cpu", width=32, rows=256)  # cached


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("bf16")
    return tiny_training_data(root)


def _trainer(tiny, **overrides):
    data, pivot = tiny
    settings = resolve_settings("fast", dict(width=32, iterations=8, points_per_step=300, **overrides))
    return ActorTrainer(data, settings, model_config_for(data, settings, pivot))


def test_training_uses_bf16_for_its_first_steps_only_and_solves_in_float32(tiny, monkeypatch):
    tr = _trainer(tiny, hidden_matmul="bf16", hidden_matmul_until=0.5, expression_solve_every=3)
    assert tr.hidden_matmul == "bf16"
    seen, solves = [], []
    layer = hidden_layers(tr.model.E)[0]
    layer.register_forward_hook(lambda m, i, o: seen.append((tr.iteration, m.matmul_dtype)))
    solve = tr.solve_expressions
    monkeypatch.setattr(tr, "solve_expressions", lambda *a, **k: (solves.append(layer.matmul_dtype), solve(*a, **k)))
    for _ in range(8):
        tr.step()
    in_steps = {it: d for it, d in seen if d is not None}
    assert sorted(in_steps) == [0, 1, 2, 3]  # 8 iterations x 0.5
    assert {d for it, d in seen if it >= 4} == {None}
    assert solves and set(solves) == {None}  # every closed-form solve on float32 features
    assert all(layer.matmul_dtype is None for layer in hidden_layers(tr.model))


def test_bf16_training_resumes_exactly_and_keeps_its_precision(tiny):
    a = _trainer(tiny, hidden_matmul="bf16", hidden_matmul_until=0.75)
    for _ in range(3):
        a.step()
    b = _trainer(tiny, hidden_matmul="fp32", hidden_matmul_until=0.75)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    assert b.hidden_matmul == "bf16"  # the checkpoint's choice, not the new settings' resolution
    for _ in range(5):  # through the switch to float32 at step 6
        a.step()
        b.step()
    for (name, p), q in zip(a.model.named_parameters(), b.model.parameters()):
        torch.testing.assert_close(p.detach(), q.detach(), rtol=0, atol=1e-6, msg=name)
