"""Block banded solves (models/banded.py) against torch's dense solve."""

import pytest
import torch

from models.banded import block_bandwidth, solve_banded_blocks


def _blocks(A: torch.Tensor, n: int) -> torch.Tensor:
    """``A (J n, J n)`` as its frame blocks ``(J, J, n, n)``."""
    J = A.shape[0] // n
    return A.reshape(J, n, J, n).permute(0, 2, 1, 3)


def _banded_spd(J: int, n: int, b: int, seed: int = 0) -> torch.Tensor:
    """A random SPD ``(J n, J n)`` matrix whose blocks vanish more than ``b`` blocks off the diagonal."""
    g = torch.Generator().manual_seed(seed)
    A = torch.zeros(J * n, J * n, dtype=torch.float64)
    for j in range(J):
        for k in range(j, min(J, j + b + 1)):
            X = torch.randn(n, n, generator=g, dtype=torch.float64)
            A[j * n:(j + 1) * n, k * n:(k + 1) * n] = X
            A[k * n:(k + 1) * n, j * n:(j + 1) * n] = X.T if k != j else X + X.T
    A.diagonal().add_(4.0 * n * (b + 1))     # diagonally dominant: positive definite
    return A


@pytest.mark.parametrize("J,n,b", [(30, 7, 2), (31, 5, 2), (13, 4, 1), (9, 3, 0), (10, 4, 3), (4, 3, 2)])
def test_block_banded_solve_matches_dense(J, n, b):
    A = _banded_spd(J, n, b)
    assert block_bandwidth(_blocks(A, n)) == b
    rhs = torch.randn(J * n, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    x = solve_banded_blocks(_blocks(A, n), rhs, b)
    torch.testing.assert_close(x, torch.linalg.solve(A, rhs), rtol=1e-9, atol=1e-11)


def test_block_banded_solve_reports_an_indefinite_matrix():
    A = _banded_spd(12, 4, 2)
    A[20:24, 20:24] *= -1                     # one frame's block negative: not positive definite
    assert solve_banded_blocks(_blocks(A, 4), torch.ones(48, dtype=torch.float64), 2) is None


def test_block_banded_solve_checks_shapes():
    with pytest.raises(ValueError, match=r"\(J, J, n, n\)"):
        solve_banded_blocks(torch.eye(10, dtype=torch.float64).reshape(2, 5, 2, 5), torch.ones(10, dtype=torch.float64), 1)


@pytest.mark.parametrize("J,b", [(30, 2), (7, 2), (11, 1)])
def test_banded_blocks_with_damping_match_dense(J, b):
    """The fit's form: the matrix as frame blocks (J, J, n, n) plus Marquardt's diagonal damping."""
    n = 5
    A = _banded_spd(J, n, b, seed=2)
    A.diagonal().sub_(3.0 * n * (b + 1))          # less dominant: the damping matters
    damping = torch.rand(J * n, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 50
    rhs = torch.randn(J * n, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    x = solve_banded_blocks(_blocks(A, n), rhs, b, damping)
    torch.testing.assert_close(x, torch.linalg.solve(A + torch.diag(damping), rhs), rtol=1e-9, atol=1e-11)
