"""Symmetric positive definite systems with a banded block structure (the fits' normal equations).

The normal equations of a window of frames couple each frame only with its neighbours (the temporal
terms), so their matrix is block banded; these solvers cost what the band costs instead of the dense
``N^3 / 3``, with torch's own threads (no second BLAS thread pool spinning beside them).
"""

from __future__ import annotations

import torch

__all__ = ["block_bandwidth", "solve_banded_blocks", "solve_block_tridiagonal"]


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


def block_bandwidth(H: torch.Tensor) -> int:
    """The largest ``|j - k|`` of a nonzero block ``H[j, k]`` of ``H (J, J, n, n)``."""
    nz = torch.nonzero(H.abs().amax((2, 3)) > 0)
    return int((nz[:, 0] - nz[:, 1]).abs().max()) if len(nz) else 0


def solve_banded_blocks(H: torch.Tensor, g: torch.Tensor, b: int, damping: torch.Tensor | None = None
                        ) -> torch.Tensor | None:
    """Solve ``(A + diag(damping)) x = g`` for a symmetric positive definite ``A`` given as its blocks
    ``H (J, J, n, n)`` (``H[j, k]`` the ``(n, n)`` block of frames ``j, k``, zero for ``|j - k| > b``);
    ``g``, ``damping`` ``(J n,)``.

    Groups of ``max(b, 1)`` consecutive frames make the system block tridiagonal
    (:func:`solve_block_tridiagonal`): ``J / b`` Cholesky factorisations of ``(b n, b n)`` instead of one of
    ``(J n, J n)`` (a 30-frame window of the 2D fit, ``n = 31``, ``b = 2``: about 15x fewer operations),
    and only the blocks inside the band are read. Returns ``x (J n,)``, or None when the matrix is not
    positive definite.
    """
    J, n = H.shape[0], H.shape[2]
    if H.shape != (J, J, n, n) or g.shape != (J * n,) or (damping is not None and damping.shape != (J * n,)):
        raise ValueError(f"H must be (J, J, n, n) and g, damping (J n,); got {tuple(H.shape)}, {tuple(g.shape)}")
    s = max(b, 1)
    G = -(-J // s)                        # groups of s frames; the last one padded with identity
    if G <= 1 or 3 * s >= J:              # no gain over one dense factorisation
        A = H.permute(0, 2, 1, 3).reshape(J * n, J * n)
        if damping is not None:
            A = A + torch.diag(damping)
        L, info = torch.linalg.cholesky_ex(A)
        return None if int(info) != 0 else torch.cholesky_solve(g[:, None], L)[:, 0]
    m = s * n
    D = H.new_zeros(G, m, m)
    U = H.new_zeros(G - 1, m, m) if b > 0 else None
    for k in range(G):
        a0, a1 = k * s, min(J, (k + 1) * s)
        w = (a1 - a0) * n
        D[k, :w, :w] = H[a0:a1, a0:a1].permute(0, 2, 1, 3).reshape(w, w)
        D[k, w:, w:] = torch.eye(m - w, dtype=H.dtype, device=H.device)
        if U is not None and k + 1 < G:
            b1 = min(J, a1 + s)
            U[k, :w, :(b1 - a1) * n] = H[a0:a1, a1:b1].permute(0, 2, 1, 3).reshape(w, (b1 - a1) * n)
    rhs = g.new_zeros(G * m)
    rhs[:J * n] = g
    if damping is not None:
        dd = damping.new_zeros(G * m)
        dd[:J * n] = damping
        D.diagonal(dim1=1, dim2=2).add_(dd.view(G, m))
    x = solve_block_tridiagonal(D, U, rhs.view(G, m))
    return None if x is None else x.reshape(-1)[:J * n]
