r"""The plant of the regional H∞ problem: sector-bounded nonlinearity and ROSS sensors.

Source: Z. Wang, B. Shen, X. Liu, "H∞ filtering with randomly occurring sensor saturations and
missing measurements", eqs. (1)–(4); our deviations: docs/sources/wang-hinf.md. Plant :math:`x_{k+1} = f(x_k) + Bw_k`,
:math:`z_k = Mx_k`, sector condition (4) :math:`[f(x)-U_1x]^T[f(x)-U_2x] \le 0`,
:math:`U_1-U_2 > 0`; sensors (2) through
:class:`~tobitkf.channels.saturation.RandomSaturation`. The LMI analysis and design are in
:mod:`tobitkf.design.hinf`, the filter (5) in :mod:`tobitkf.filters.hinf`, the simulator in
:mod:`tobitkf.simulate.ross`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array
from ..channels.saturation import RandomSaturation

__all__ = ["RossModel", "wang2010_model"]


@dataclass(frozen=True)
class RossModel:
    r"""Plant (1) with sector bound (4), ROSS sensors (2) and the error output of (6).

    Build it with :meth:`create` (validated); the fields below are the checked arrays.

    Attributes
    ----------
    B, M, U1, U2, C : ndarray
        As the parameters of :meth:`create`.
    D : (m,) ndarray
        Noise gains :math:`D_i`.
    channel : RandomSaturation
        The sensor channel built from ``mu``, ``nu``, ``level``.
    f : callable or None
        The plant nonlinearity (needed only to simulate).
    """

    B: np.ndarray
    M: np.ndarray
    U1: np.ndarray
    U2: np.ndarray
    C: np.ndarray
    D: np.ndarray
    channel: RandomSaturation
    f: Callable[[np.ndarray], np.ndarray] | None = None

    @classmethod
    def create(
        cls,
        *,
        B: Any,
        M: Any,
        U1: Any,
        U2: Any,
        C: Any,
        D: Any,
        mu: Any,
        nu: Any,
        level: Any = 1.0,
        f: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> RossModel:
        r"""Validated constructor (use this, not the dataclass initializer).

        Parameters
        ----------
        B : (n, p) array_like
            Disturbance input of the plant.
        M : (r, n) array_like
            Output to be estimated, :math:`z = Mx` (the filter output is :math:`M\hat x`).
        U1, U2 : (n, n) array_like
            Sector bounds of (4); :math:`U_1-U_2` must be symmetric positive definite.
        C : (m, n) array_like
            Stacked sensor rows :math:`C_i`.
        D : (m,) array_like
            Noise gains :math:`D_i` (D_v = diag{D_i}).
        mu, nu : (m,) array_like
            Saturation / arrival probabilities (see :class:`RandomSaturation`).
        level : float or (m,) array_like, default 1.0
            Saturation levels u_i (paper: 1).
        f : callable, optional
            Batched nonlinearity ``f(x) -> (..., n)`` for ``x`` of shape (..., n); needed only to
            simulate. The LMIs use only U1, U2.

        Raises
        ------
        ShapeError
            A matrix does not conform.
        ValidationError
            Sector bounds in the wrong order (U1-U2 not positive definite or not symmetric),
            probabilities outside [0, 1], levels <= 0, non-finite entries.
        """
        B = as_float_array(B, "B", ndim=2)
        n, p = B.shape
        M = as_float_array(M, "M", ndim=2)
        if M.shape[1] != n:
            raise ShapeError(f"M: expected (r, n) with n={n} (rows of B), got shape {M.shape}")
        U1 = as_float_array(U1, "U1", ndim=2)
        U2 = as_float_array(U2, "U2", ndim=2)
        for name, U in (("U1", U1), ("U2", U2)):
            if U.shape != (n, n):
                raise ShapeError(f"{name}: expected shape ({n}, {n}), got {U.shape}")
        U = U1 - U2
        if np.abs(U - U.T).max() > 1e-10 * max(1.0, np.abs(U).max()):
            raise ValidationError("U1, U2: expected U1 - U2 symmetric (Assumption 1), it is not")
        eig = np.linalg.eigvalsh(0.5 * (U + U.T))
        if eig.min() <= 0:
            hint = " (the bounds look swapped: U2 - U1 is positive definite)" if eig.max() < 0 else ""
            raise ValidationError(
                f"U1, U2: expected U1 - U2 positive definite (Assumption 1), smallest eigenvalue {eig.min():.3g}{hint}"
            )
        C = as_float_array(C, "C", ndim=2)
        if C.shape[1] != n:
            raise ShapeError(f"C: expected (m, n) with n={n}, got shape {C.shape}")
        m = C.shape[0]
        D = as_float_array(D, "D", ndim=(0, 1, 2))
        if D.ndim == 2:
            if D.shape != (m, m) or np.abs(D - np.diag(np.diag(D))).max() > 0:
                raise ShapeError(f"D: expected (m,) or a diagonal ({m}, {m}) matrix, got shape {D.shape}")
            D = np.diag(D).copy()
        D = np.broadcast_to(D, (m,)).copy() if D.ndim == 0 else D
        if D.shape != (m,):
            raise ShapeError(f"D: expected shape ({m},), got {D.shape}")
        channel = RandomSaturation(mu, nu, level)
        if channel.m != m:
            raise ShapeError(f"mu, nu: expected length m={m} (rows of C), got {channel.m}")
        if f is not None and not callable(f):
            raise ValidationError(f"f: expected a callable f(x) -> (..., n), got {type(f).__name__}")
        return cls(B=B, M=M, U1=U1, U2=U2, C=C, D=D, channel=channel, f=f)

    n = property(lambda self: self.B.shape[0], doc="State dimension n.")
    p = property(lambda self: self.B.shape[1], doc="Dimension p of w.")
    m = property(lambda self: self.C.shape[0], doc="Number of sensors m.")
    r = property(lambda self: self.M.shape[0], doc="Dimension r of z.")

    def with_channel(self, mu: Any = None, nu: Any = None, level: Any = None) -> RossModel:
        """A copy with other probabilities / levels (validated)."""
        ch = self.channel
        return replace(
            self,
            channel=RandomSaturation(
                ch.mu if mu is None else mu, ch.nu if nu is None else nu, ch.level if level is None else level
            ),
        )

    def nonlinearity(self, x: np.ndarray) -> np.ndarray:
        """:math:`f(x)`; refused by name when the model was built without ``f``."""
        if self.f is None:
            raise ValidationError(
                "f: this model has no plant nonlinearity (built with f=None); pass f= to RossModel.create"
            )
        return self.f(x)

    def sector_value(self, x: Any, fx: Any | None = None) -> np.ndarray:
        """:math:`[f(x)-U_1x]^T[f(x)-U_2x]` for ``x`` (..., n) (<= 0 if (4) holds)."""
        x = np.asarray(x, dtype=float)
        fx = self.nonlinearity(x) if fx is None else np.asarray(fx, dtype=float)
        return np.einsum("...i,...i->...", fx - x @ self.U1.T, fx - x @ self.U2.T)


# The paper's example (Section 4)
def _wang2010_f(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
    return np.stack(
        [
            -0.7 * x1 + 0.05 * x2 + 0.05 * x3,
            -0.05 * x1 + 0.85 * x2,
            -0.05 * x1 - 0.475 * x3 + x3 * np.sin(x1) / np.sqrt(x1**2 + x2**2 + 20.0),
        ],
        axis=-1,
    )


def wang2010_model(**overrides: Any) -> RossModel:
    """The example of Section 4 (Section 4 of the source); keyword overrides replace any field (mu, nu, D, ...)."""
    kw: dict[str, Any] = dict(
        B=[[0.5], [0.1], [0.1]],
        M=[[0.2, 0.0, 0.15], [0.0, 0.1, 0.2]],
        U1=[[-0.5, 0.1, 0.0], [0.0, 0.9, 0.0], [-0.1, 0.0, -0.2]],
        U2=[[-0.9, 0.0, 0.1], [-0.1, 0.8, 0.0], [0.0, 0.0, -0.75]],
        C=[[1.0, 0.0, 1.0], [1.0, 1.0, 0.0]],
        D=[1.0, 1.0],
        mu=[0.7, 0.6],
        nu=[0.7, 0.75],
        level=1.0,
        f=_wang2010_f,
    )
    kw.update(overrides)
    return RossModel.create(**kw)
