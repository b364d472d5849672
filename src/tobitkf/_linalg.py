r"""Small dense linear-algebra helpers shared by every layer (numpy, batched over leading axes).

Two square roots of a PSD matrix live here because they serve different purposes:
:func:`psd_sqrt` (a Cholesky factor when it exists, else an eigen root) for the filters' square-root
forms, and :func:`eigh_sqrt` (always the eigen root) for the simulators, whose random draws must
not change when a covariance crosses the boundary of numerical definiteness.
"""

from __future__ import annotations

import numpy as np

__all__ = ["symmetrize", "psd_sqrt", "eigh_sqrt"]


def symmetrize(P: np.ndarray) -> np.ndarray:
    """0.5 (P + P^T) over the last two axes."""
    return 0.5 * (P + P.swapaxes(-1, -2))


def psd_sqrt(M: np.ndarray) -> np.ndarray:
    r"""A square root :math:`L` with :math:`LL^T = M` of PSD matrices ``M`` (..., k, k).

    The lower Cholesky factor when every matrix of the batch is numerically positive
    definite; otherwise (a singular Q with zero rows, P0 = 0, ...) the eigen-decomposition
    root :math:`V\,\mathrm{diag}(\sqrt{\max(w, 0)})` of the symmetric part, which is not
    triangular (none of its users needs that) and sets rounding-negative eigenvalues to 0.
    """
    M = np.asarray(M, dtype=float)
    try:
        return np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(symmetrize(M))
        return V * np.sqrt(np.maximum(w, 0.0))[..., None, :]


def eigh_sqrt(cov: np.ndarray) -> np.ndarray:
    """A square root S with S S^T = cov for a symmetric PSD ``cov`` (..., n, n), singular allowed
    (eigen-decomposition of the symmetric part, negative rounding clipped to 0)."""
    w, V = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    return V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]
