r"""The regional H∞ filter (5) of Wang, Shen & Liu: :math:`\hat x_{k+1} = A_f\hat x_k + B_f\tilde y_k`.

Source: Z. Wang, B. Shen, X. Liu, "H∞ filtering with randomly occurring sensor saturations and
missing measurements", eq. (5); our deviations: docs/sources/wang-hinf.md. The gains come from the LMI design of
:mod:`tobitkf.design.hinf` (:func:`~tobitkf.design.hinf.design`); the filter itself is a fixed
linear recursion, with no covariance.

Time convention (the source's, forced by (5) being a one-step predictor): ``y[..., k, :]`` is
:math:`\tilde y_k` for k = 0..T-1 (measured from x_k); row k of the result is :math:`\hat x_{k+1}`
(``times`` = 1..T), and the prior :math:`\hat x_0` is the state at ``k = 0``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array
from ..design.hinf import HinfCertificate
from ..models import ross as _ross
from .core import Estimator, FilterResult, FilterState
from .registry import family_entry, register

__all__ = ["RegionalHinfFilter"]


class RegionalHinfFilter(Estimator):
    r"""The filter (5), :math:`\hat x_{k+1} = A_f\hat x_k + B_f\tilde y_k`, :math:`\hat z_k = M\hat x_k`.

    An estimator with the common online API: ``init(batch_shape, x0=...)`` is :math:`\hat x_0`
    (default 0, ``state.k = 0``); ``step(state, y_k)`` takes :math:`\tilde y_k` and returns
    :math:`\hat x_{k+1}` (``state.k = k+1``); ``filter(y)`` returns the common :class:`FilterResult`
    whose row i is :math:`\hat x_{i+1}` from :math:`\tilde y_0..\tilde y_i` (``times`` 1..T),
    with ``extras["z"]`` the estimated outputs :math:`\hat z_{i+1}`. The filter has no covariance
    (``cov`` is None) and no prediction separate from its estimate (``pred_mean`` is None).

    Parameters
    ----------
    Af : (n, n) array_like
    Bf : (n, m) array_like
    M : (r, n) array_like

    Raises
    ------
    ShapeError
        Gains that do not conform.

    Examples
    --------
    >>> import numpy as np, tobitkf as tk
    >>> f = tk.RegionalHinfFilter([[0.5]], [[1.0]], [[2.0]])
    >>> out = f.filter(np.array([[1.0], [0.0]]))
    >>> out.mean[:, 0].tolist(), out.extras["z"][:, 0].tolist(), out.times.tolist()
    ([1.0, 0.5], [2.0, 1.0], [1, 2])
    """

    _name = "RegionalHinfFilter"
    _filter_doc = (
        """Run the filter (5) on ``y`` (..., T, m): rows x̂_1..x̂_T, ``extras["z"]`` ẑ_1..ẑ_T, ``times`` 1..T."""
    )
    _filter_params = {
        "y": "(..., T, m) array_like\n    The readings y_1..y_T; no NaN (the filter has no update to skip).",
        "x0": "array_like, optional\n    The initial estimate x̂_0, ``(n,)`` or ``(..., n)`` (default 0).",
    }
    _allow_missing = False
    _missing_reason = (
        "the filter (5) has given gains and no rule for a lost reading: pass the value its channel "
        "delivers in that case"
    )

    def __init__(self, Af: Any, Bf: Any, M: Any):
        self.Af = as_float_array(Af, "Af", ndim=2)
        self.Bf = as_float_array(Bf, "Bf", ndim=2)
        self.M = as_float_array(M, "M", ndim=2)
        n = self.Af.shape[0]
        if self.Af.shape != (n, n) or self.Bf.shape[0] != n or self.M.shape[1] != n:
            raise ShapeError(
                f"Af, Bf, M: expected (n, n), (n, m), (r, n), got {self.Af.shape}, {self.Bf.shape}, {self.M.shape}"
            )
        self.n, self.m = n, self.Bf.shape[1]

    @classmethod
    def from_certificate(cls, cert: HinfCertificate, model: _ross.RossModel) -> RegionalHinfFilter:
        """Filter from a successful :func:`~tobitkf.design.hinf.design`; refuses a failed one."""
        if not isinstance(cert, HinfCertificate):
            raise ValidationError(f"cert: expected a HinfCertificate from design(), got {type(cert).__name__}")
        if not cert.ok:
            raise ValidationError(f"cert: expected a solved and verified design, got status {cert.status!r}")
        return cls(cert.Af, cert.Bf, model.M)

    def _initial(self, N, x0, P0, batch):
        if P0 is not None:
            raise ValidationError("P0: the H-infinity filter has no covariance; only x0 can be given")
        n = self.n
        if x0 is None:
            return np.zeros((N, n)), None, {}
        x = as_float_array(x0, "x0")
        try:
            x = np.broadcast_to(x, tuple(batch) + (n,)).reshape(N, n).copy()
        except ValueError:
            raise ShapeError(f"x0: expected ({n},) or the batch shape + ({n},), got {x.shape}") from None
        return x, None, {}

    def _step_arrays(self, k, x, P, S, carry, y, u, options=None):
        x_new = x @ self.Af.T + y @ self.Bf.T  # (5)
        return x_new, None, None, carry, None, None, {"z": x_new @ self.M.T}

    def filter(  # type: ignore[override]  # no u, no P0: the estimate carries no covariance
        self, y: Any, *, x0: Any = None, outputs: Any = "all", state: FilterState | None = None
    ) -> FilterResult:
        return self._run(y, None, x0, None, outputs=outputs, state=state)


def _from_gains(system, parts, o):
    return RegionalHinfFilter(o["Af"], o["Bf"], system.M)


register(
    family_entry(
        RegionalHinfFilter,
        "regional H-infinity filter with given gains (Wang, Shen & Liu)",
        options={"Af": object, "Bf": object},  # the designed gains (n, n) and (n, m), array_like
        required=("Af", "Bf"),
        model="ross",
        factory=_from_gains,
    )
)
