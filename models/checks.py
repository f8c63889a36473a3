"""Shape checks at public boundaries, with messages that carry the expected and the found shape.

A spec is a comma-separated list of dimensions: an integer (must match), a name (must agree with
the same name in the same call, see :func:`check_shapes`), or a leading ``*`` (any number of batch
dimensions, including none).
"""

from __future__ import annotations

from typing import Mapping

import torch


def _match(shape: tuple[int, ...], spec: str, name: str, sizes: dict[str, int]) -> None:
    dims = [d.strip() for d in spec.split(",")]
    star = dims[0] == "*"
    if star:
        dims = dims[1:]
    if (len(shape) < len(dims)) if star else (len(shape) != len(dims)):
        raise ValueError(f"{name}: expected shape ({spec}), got {tuple(shape)}")
    tail = shape[len(shape) - len(dims):]
    for d, n in zip(dims, tail):
        if d.isdigit():
            if int(d) != n:
                raise ValueError(f"{name}: expected shape ({spec}), got {tuple(shape)}")
        elif d in sizes and sizes[d] != n:
            raise ValueError(f"{name}: expected shape ({spec}) with {d}={sizes[d]}, got {tuple(shape)}")
        else:
            sizes[d] = n


def check_shape(x: torch.Tensor, spec: str, name: str = "tensor") -> dict[str, int]:
    """Raise ValueError unless ``x.shape`` matches ``spec``; returns the named sizes."""
    sizes: dict[str, int] = {}
    _match(tuple(x.shape), spec, name, sizes)
    return sizes


def check_shapes(specs: Mapping[str, tuple[torch.Tensor, str]]) -> dict[str, int]:
    """Check several tensors at once; named dimensions must agree across them.

    Example: ``check_shapes({"points": (p, "N,3"), "weights": (w, "N")})``.
    """
    sizes: dict[str, int] = {}
    for name, (x, spec) in specs.items():
        _match(tuple(x.shape), spec, name, sizes)
    return sizes
