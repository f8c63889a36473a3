"""SIREN: multilayer perceptrons with sine activations (Sitzmann et al., NeurIPS 2020).

Each hidden layer computes ``sin(omega_0 * (W x + b))``. Initialisation follows SIREN: the first
layer draws W from U(-1/n_in, 1/n_in); every later layer from U(-sqrt(6/n_in)/omega_0,
sqrt(6/n_in)/omega_0), which keeps the pre-activations ``omega_0 (W x + b)`` near N(0, 1) and the
activations arcsine-distributed in [-1, 1] through any depth.

``first_omega_0`` and ``hidden_omega_0`` are separate constructor arguments. The paper's setting is
30 for both. With ``hidden_omega_0 = 1`` the hidden layers compute the same functions at
initialisation (the factor moves from the forward pass into the initial weights) but Adam's steps
on them are 30 times smaller relative to the weights, which was stable at lr 2e-3 where the
paper's setting diverged on our CPU prototype (DESIGN.md, measured notes).
"""

from __future__ import annotations

import contextlib
import math

import torch
from torch import nn


@contextlib.contextmanager
def _onednn_bf16():
    """oneDNN's float32 products with bfloat16 inputs inside the kernel (fp32 accumulation and result)."""
    mm = torch.backends.mkldnn.matmul
    before = mm.fp32_precision
    mm.fp32_precision = "bf16"
    try:
        yield
    finally:
        mm.fp32_precision = before


_ONEDNN_ROUNDS: bool | None = None


def onednn_bf16_rounds() -> bool:
    """Whether oneDNN's float32 products in its bfloat16 mode (:func:`_onednn_bf16`) really round their inputs
    to bfloat16 on this CPU: with AMX they do; on an AMD EPYC with AVX-512 BF16 they stayed float32-accurate
    (relative error 6e-7 against float64, a bfloat16 product's is 2.4e-3) and the promise of ``matmul_dtype``
    did not hold. Probed once per process on a product of the training's shape (1,024 x 256 by 256 x 256)."""
    global _ONEDNN_ROUNDS
    if _ONEDNN_ROUNDS is None:
        g = torch.Generator().manual_seed(0)
        a, b = torch.rand(1024, 256, generator=g) - 0.5, torch.rand(256, 256, generator=g) - 0.5
        with _onednn_bf16():
            p = a @ b
        exact = a.double() @ b.double()
        _ONEDNN_ROUNDS = bool((p.double() - exact).abs().max() > 1e-4 * exact.abs().max())
    return _ONEDNN_ROUNDS


class _OneDnnBf16Product(torch.autograd.Function):
    """``x @ w.T`` and its two backward products with bfloat16 inputs, float32 in and out (CPU)."""

    @staticmethod
    def forward(ctx, x, w):
        ctx.save_for_backward(x, w)
        with _onednn_bf16():
            return x @ w.T

    @staticmethod
    def backward(ctx, grad):
        x, w = ctx.saved_tensors
        with _onednn_bf16():
            gx = grad @ w if ctx.needs_input_grad[0] else None
            gw = grad.T @ x
        return gx, gw


class SineLayer(nn.Module):
    """``y = sin(omega_0 * (W x + b))`` with SIREN initialisation.

    Args:
        in_features, out_features: layer sizes.
        omega_0: frequency factor.
        is_first: use the first-layer initialisation U(-1/n_in, 1/n_in).
    """

    def __init__(self, in_features: int, out_features: int, omega_0: float = 30.0, is_first: bool = False):
        super().__init__()
        self.omega_0 = float(omega_0)
        self.is_first = is_first
        self.matmul_dtype: torch.dtype | None = None
        """Dtype of the product ``W x`` of a hidden layer (None = the weights' own, float32). With
        ``torch.bfloat16`` the inputs and weights are rounded to bfloat16 for the product only; the
        bias, the sine and the weights stay float32 (see :mod:`models.precision`). The first layer
        ignores it: its 3 inputs cost nothing and ``omega_0 = 30`` would amplify their rounding."""
        self.linear = nn.Linear(in_features, out_features)
        with torch.no_grad():
            bound = 1.0 / in_features if is_first else math.sqrt(6.0 / in_features) / self.omega_0
            self.linear.weight.uniform_(-bound, bound)
            # nn.Linear's default bias bound, 1/sqrt(n_in), as in the SIREN reference code.
            self.linear.bias.uniform_(-1.0 / math.sqrt(in_features), 1.0 / math.sqrt(in_features))

    def preactivation(self, x: torch.Tensor) -> torch.Tensor:
        """``omega_0 * (W x + b)``, the argument of the sine.

        Computed as ``(omega_0 W) x + omega_0 b``: the factor scales the (small) weights instead of
        the (points x width) product, one elementwise pass less forward and backward; the function
        and the gradients with respect to W and b are the same.
        """
        weight, bias = self.linear.weight, self.linear.bias
        if self.omega_0 != 1.0:
            weight, bias = weight * self.omega_0, bias * self.omega_0
        low = self.matmul_dtype
        if low is not None and not self.is_first and low != x.dtype:
            if x.device.type == "cpu" and low == torch.bfloat16 and onednn_bf16_rounds():
                return _OneDnnBf16Product.apply(x, weight) + bias
            return torch.nn.functional.linear(x.to(low), weight.to(low)).to(x.dtype) + bias
        return torch.nn.functional.linear(x, weight, bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sin(self.preactivation(x))


class Siren(nn.Module):
    """A SIREN MLP: ``depth`` sine layers of ``width`` units, then a linear output layer.

    Args:
        in_features: input size (3 for template points).
        out_features: output size.
        width: hidden width (the paper uses 256).
        depth: number of sine layers (>= 1).
        first_omega_0: frequency of the first layer (30 in SIREN and the paper).
        hidden_omega_0: frequency of the later layers (30 in the paper; see module docstring).
        output_scale: the linear output layer's weights are initialised in
            U(-s, s) * output_scale with SIREN's s; a small scale starts the network near zero.

    Shapes: ``(*, in_features) -> (*, out_features)``.
    """

    def __init__(self, in_features: int, out_features: int, width: int = 256, depth: int = 3,
                 first_omega_0: float = 30.0, hidden_omega_0: float = 30.0, output_scale: float = 1.0):
        super().__init__()
        if depth < 1 or width < 1:
            raise ValueError(f"Siren needs depth >= 1 and width >= 1, got depth={depth}, width={width}")
        layers = [SineLayer(in_features, width, first_omega_0, is_first=True)]
        layers += [SineLayer(width, width, hidden_omega_0) for _ in range(depth - 1)]
        self.layers = nn.Sequential(*layers)
        self.output = nn.Linear(width, out_features)
        with torch.no_grad():
            bound = math.sqrt(6.0 / width) / hidden_omega_0 * output_scale
            self.output.weight.uniform_(-bound, bound)
            self.output.bias.zero_()

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Activations of the last sine layer, ``(*, width)``."""
        return self.layers(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.output(self.layers(x))
