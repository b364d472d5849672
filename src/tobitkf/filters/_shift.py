"""Time update of a state augmented with its own past (block-shift transition), batched over runs.

Used by the fading TKF (Geng et al. 2017, (17)-(18)) and the protocol TKF (Geng et al., (17)-(18)):
:math:`\\xi = \\mathrm{col}\\{x_k, x_{k-1}, \\dots\\}`, transition with ``A`` in the top-left block and
identities on the block sub-diagonal, noise :math:`BQB^T` in the top-left block only.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def shift_predict(xi: np.ndarray, P: np.ndarray, A: np.ndarray, Qd: np.ndarray, bx: Any = 0.0):
    r""":math:`\bar\xi = \mathcal A\xi + [b; 0]`,
    :math:`\bar P = \mathrm{sym}(\mathcal A P\mathcal A^T + \mathcal BQ\mathcal B^T)`.

    ``xi`` (N, nxi), ``P`` (N, nxi, nxi) **exactly symmetric**, ``A`` and ``Qd`` (n, n), nxi a
    multiple of n. O(N n nxi^2) copies and two GEMMs over the stacked runs instead of two
    batched (nxi x nxi) matmuls: P symmetric makes its first block column ``P[:, :, :n]`` equal to
    (block row 0)^T, so X = P[:, :, :n] A^T = (A P[:, :n, :])^T, and A P00 A^T = A X00 is read
    from X's top block. Only that top block can come out asymmetric (rounding), so only it is
    symmetrized; the other blocks are copies that mirror exactly. The result equals
    ``sym(Aa @ P @ Aa.T + Qa)`` to rounding (tested) and is exactly symmetric.
    """
    N, nxi = xi.shape
    n = A.shape[-1]
    xi_p = np.empty_like(xi)
    xi_p[:, :n] = xi[:, :n] @ A.T + bx
    xi_p[:, n:] = xi[:, :nxi - n]
    X = (P[:, :, :n].reshape(-1, n) @ A.T).reshape(N, nxi, n)
    P_p = np.empty_like(P)
    top = (np.swapaxes(X[:, :n], -1, -2).reshape(-1, n) @ A.T).reshape(N, n, n) + Qd
    P_p[:, :n, :n] = 0.5 * (top + np.swapaxes(top, -1, -2))
    P_p[:, n:, :n] = X[:, :nxi - n]
    P_p[:, :n, n:] = np.swapaxes(X[:, :nxi - n], -1, -2)
    P_p[:, n:, n:] = P[:, :nxi - n, :nxi - n]
    return xi_p, P_p
