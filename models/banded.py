"""Symmetric positive definite systems with a banded block structure (the fits' normal equations).

The normal equations of a window of frames couple each frame only with its neighbours (the temporal
terms), so their matrix is block banded; these solvers cost what the band costs instead of the dense
``N^3 / 3``, with torch's own threads (no second BLAS thread pool spinning beside them).
"""

from __future__ import annotations

import torch

__all__ = ["block_bandwidth", "solve_block_banded", "solve_block_tridiagonal"]


def solve_block_tridiagonal(D: torch.Tensor, U: torch.Tensor | None, g: torch.Tensor) -> torch.Tensor | None:
    """Solve the symmetric positive definite block tridiagonal system ``A x = g``.

    Args: D ``(J, m, m)`` the diagonal blocks ``A[j, j]``, or ``(1, m, m)`` when all are the same;
        U ``(J-1, m, m)`` the blocks ``A[j, j+1]`` (``A[j+1, j] = U[j]^T``), or None when they are all
        zero (independent blocks); g ``(J, m)``.
    Returns ``x (J, m)``, or None when a pivot block is not positive definite.
    Block Cholesky (Thomas) elimination: ``S_0 = D_0``, ``S_j = D_j - U_{j-1}^T S_{j-1}^-1 U_{j-1}``.
    """
    J = g.shape[0]
    if J == 1 or U is None:   # no coupling between frames: independent blocks
        L, info = torch.linalg.cholesky_ex(D)
        if bool(info.any()):
            return None
        if D.shape[0] == 1:   # one matrix for every frame: factored once, J right-hand sides
            return torch.cholesky_solve(g.T, L[0]).T
        return torch.cholesky_solve(g[..., None], L)[..., 0]
    Ls, Ws, ys = [], [], []
    S, y = D[0], g[0]
    for j in range(J):
        L, info = torch.linalg.cholesky_ex(S)
        if int(info) != 0:
            return None
        Ls.append(L)
        ys.append(y)
        if j + 1 < J:
            W = torch.cholesky_solve(U[j], L)                    # S_j^-1 U_j
            Ws.append(W)
            S = D[j + 1] - U[j].T @ W
            y = g[j + 1] - W.T @ y
    x = [None] * J
    x[J - 1] = torch.cholesky_solve(ys[J - 1][:, None], Ls[J - 1])[:, 0]
    for j in range(J - 2, -1, -1):
        x[j] = torch.cholesky_solve(ys[j][:, None], Ls[j])[:, 0] - Ws[j] @ x[j + 1]
    return torch.stack(x)


def block_bandwidth(H: torch.Tensor, n: int) -> int:
    """The largest ``|j - k|`` of a nonzero ``(n, n)`` block ``H[j, k]`` of ``H (J n, J n)``."""
    J = H.shape[0] // n
    nz = torch.nonzero(H.reshape(J, n, J, n).abs().amax((1, 3)) > 0)
    return int((nz[:, 0] - nz[:, 1]).abs().max()) if len(nz) else 0


def solve_block_banded(A: torch.Tensor, g: torch.Tensor, n: int, b: int | None = None) -> torch.Tensor | None:
    """Solve ``A x = g`` for a symmetric positive definite ``A (J n, J n)`` whose ``(n, n)`` blocks vanish
    more than ``b`` blocks off the diagonal (default: :func:`block_bandwidth`); ``g (J n,)``.

    Groups of ``max(b, 1)`` consecutive blocks make the system block tridiagonal
    (:func:`solve_block_tridiagonal`): ``J / b`` Cholesky factorisations of ``(b n, b n)`` instead of one of
    ``(J n, J n)`` (a 30-frame window of the 2D fit, ``n = 31``, ``b = 2``: about 15x fewer operations).
    Returns ``x (J n,)``, or None when ``A`` is not positive definite.
    """
    N = A.shape[0]
    J = N // n
    if A.shape != (N, N) or J * n != N or g.shape != (N,):
        raise ValueError(f"A must be (J n, J n) and g (J n,) with n = {n}; got {tuple(A.shape)}, {tuple(g.shape)}")
    b = block_bandwidth(A, n) if b is None else b
    s = max(b, 1)
    G = -(-J // s)                        # groups of s frames; the last one padded with identity blocks
    if G <= 1 or 3 * s >= J:              # no gain over one dense factorisation
        L, info = torch.linalg.cholesky_ex(A)
        return None if int(info) != 0 else torch.cholesky_solve(g[:, None], L)[:, 0]
    m, pad = s * n, G * s * n - N
    if pad:
        A = torch.block_diag(A, torch.eye(pad, dtype=A.dtype, device=A.device))
        g = torch.cat([g, g.new_zeros(pad)])
    blocks = A.reshape(G, m, G, m)
    idx = torch.arange(G, device=A.device)
    D = blocks[idx, :, idx]                                   # (G, m, m)
    U = blocks[idx[:-1], :, idx[1:]]                          # (G-1, m, m): A[group k, group k+1]
    x = solve_block_tridiagonal(D, U if b > 0 else None, g.reshape(G, m))
    return None if x is None else x.reshape(-1)[:N]
