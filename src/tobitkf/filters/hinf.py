r"""The regional H∞ filter (5) of Wang, Shen & Liu: :math:`\hat x_{k+1} = A_f\hat x_k + B_f\tilde y_k`.

Source: Z. Wang, B. Shen, X. Liu, "H∞ filtering with randomly occurring sensor saturations and
missing measurements", eq. (5) (seed 004). The gains come from the LMI design of
:mod:`tobitkf.design.hinf` (:func:`~tobitkf.design.hinf.design`); the filter itself is a fixed
linear recursion, with no covariance.

Time convention (the source's, forced by (5) being a one-step predictor): ``y[..., k, :]`` is
:math:`\tilde y_k` for k = 0..T-1 (measured from x_k).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array
from ..design.hinf import HinfCertificate
from ..models.ross import RossModel

__all__ = ["HinfFilterResult", "hinf_filter", "RegionalHinfFilter"]


@dataclass(frozen=True)
class HinfFilterResult:
    """Output of the filter (5).

    Attributes
    ----------
    mean : (..., T+1, n) ndarray
        x̂_0..x̂_T (x̂_{k} uses ỹ_0..ỹ_{k-1}).
    z : (..., T+1, r) ndarray
        ẑ_k = M x̂_k.
    """

    mean: np.ndarray
    z: np.ndarray


def hinf_filter(Af: Any, Bf: Any, M: Any, y: Any, xhat0: Any = None) -> HinfFilterResult:
    r"""Run :math:`\hat x_{k+1} = A_f\hat x_k + B_f\tilde y_k`, :math:`\hat z_k = M\hat x_k` (5) on ``y`` (..., T, m)."""
    Af = as_float_array(Af, "Af", ndim=2)
    Bf = as_float_array(Bf, "Bf", ndim=2)
    M = as_float_array(M, "M", ndim=2)
    n = Af.shape[0]
    if Af.shape != (n, n) or Bf.shape[0] != n or M.shape[1] != n:
        raise ShapeError(f"Af, Bf, M: expected (n, n), (n, m), (r, n), got {Af.shape}, {Bf.shape}, {M.shape}")
    y = as_float_array(y, "y")
    if y.ndim < 2 or y.shape[-1] != Bf.shape[1]:
        raise ShapeError(f"y: expected (..., T, {Bf.shape[1]}), got {y.shape}")
    batch, T = y.shape[:-2], y.shape[-2]
    xh = np.empty(batch + (T + 1, n))
    if xhat0 is None:
        xh[..., 0, :] = 0.0
    else:
        x0 = as_float_array(xhat0, "xhat0")
        try:
            xh[..., 0, :] = x0
        except ValueError:
            raise ShapeError(f"xhat0: expected ({n},) or y's batch shape + ({n},), got {x0.shape}") from None
    for k in range(T):
        xh[..., k + 1, :] = xh[..., k, :] @ Af.T + y[..., k, :] @ Bf.T
    return HinfFilterResult(mean=xh, z=xh @ M.T)


class RegionalHinfFilter:
    """The filter (5) with given gains (thin class over :func:`hinf_filter`).

    Parameters
    ----------
    Af : (n, n) array_like
    Bf : (n, m) array_like
    M : (r, n) array_like
    """

    def __init__(self, Af: Any, Bf: Any, M: Any):
        self.Af = as_float_array(Af, "Af", ndim=2)
        self.Bf = as_float_array(Bf, "Bf", ndim=2)
        self.M = as_float_array(M, "M", ndim=2)
        n = self.Af.shape[0]
        if self.Af.shape != (n, n) or self.Bf.shape[0] != n or self.M.shape[1] != n:
            raise ShapeError(f"Af, Bf, M: expected (n, n), (n, m), (r, n), got {self.Af.shape}, "
                             f"{self.Bf.shape}, {self.M.shape}")

    @classmethod
    def from_certificate(cls, cert: HinfCertificate, model: RossModel) -> RegionalHinfFilter:
        """Filter from a successful :func:`design`; refuses a failed one."""
        if not isinstance(cert, HinfCertificate):
            raise ValidationError(f"cert: expected a HinfCertificate from design(), got {type(cert).__name__}")
        if not cert.ok:
            raise ValidationError(f"cert: expected a solved and verified design, got status {cert.status!r}")
        return cls(cert.Af, cert.Bf, model.M)

    def filter(self, y: Any, xhat0: Any = None) -> HinfFilterResult:
        """Run (5) on ``y`` (..., T, m); see :func:`hinf_filter`."""
        return hinf_filter(self.Af, self.Bf, self.M, y, xhat0)


# Names that lived in this module before the layout of 0.2 (design, model, simulator): kept for one
# release, with a DeprecationWarning naming the new home.
_MOVED_TO_DESIGN = ("HinfCertificate", "Verification", "augmented_step", "expected_lyapunov_next", "psi_matrix",
                    "verify", "analyze", "design", "zero_filter_gamma", "WANG2010_PAPER", "METHODS", "OBJECTIVES",
                    "COVARIANCES", "SOLVERS")
_MOVED_ELSEWHERE = {"RossModel": "tobitkf.models.ross", "wang2010_model": "tobitkf.models.ross",
                    "RossSimulation": "tobitkf.simulate.ross", "simulate_ross": "tobitkf.simulate.ross",
                    "wang2010_disturbances": "tobitkf.simulate.ross"}


def __getattr__(name: str):
    import warnings

    if name in _MOVED_TO_DESIGN:
        from ..design import hinf as _design

        warnings.warn(f"tobitkf.filters.hinf.{name} moved to tobitkf.design.hinf.{name}; the old name will be "
                      "removed in the next release", DeprecationWarning, stacklevel=2)
        return getattr(_design, name)
    if name == "RossModel":
        warnings.warn("tobitkf.filters.hinf.RossModel moved to tobitkf.models.ross.RossModel (also tk.RossModel); "
                      "the old name will be removed in the next release", DeprecationWarning, stacklevel=2)
        return RossModel
    if name in _MOVED_ELSEWHERE:
        raise AttributeError(f"tobitkf.filters.hinf.{name} moved to {_MOVED_ELSEWHERE[name]}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
