r"""The fixed-gain Tobit observer of Miller (2015) Ch. 5, (5.2), as an estimator.

Source: Miller (2015), §5.1, (5.2): an observer with a constant gain L whose innovation compares the
censored reading with its expectation at the estimate,

.. math::

    \hat x_{k+1} = A\hat x_k + L\,(y_k - E[\hat y_k]), \qquad
    E[\hat y_k] = E[\mathrm{clip}(C\hat x_k + v_k, l, h)]  \quad\text{(the censored mean, (3.8))}

(``form="predictor"``, the source's form: ``y`` holds y_0..y_{T-1} and row k is x̂_{k+1}), or in the
package's filter convention (``form="filter"``): :math:`\bar x_k = A\hat x_{k-1}`,
:math:`\hat x_k = \bar x_k + L(y_k - E[y_k](\bar x_k))`, ``y`` holds y_1..y_T and row k-1 is x̂_{k|k};
with :math:`L = K_f` this is the predictor form with :math:`L_p = AK_f`. ``gain_form="linear"``
replaces the censored expectation by :math:`C\hat x`: the uncompensated LQG observer of Fig 5.11.

The observer has no covariance (its gain is given, e.g. by :func:`tobitkf.control.tobit_lqe`); it cannot
skip a reading (NaN is refused). Both forms have ``times`` 1..T and the prior x̂_0 at ``state.k = 0``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ShapeError, as_float_array, check_option
from ..censored import unchecked_moments
from .core import Estimator, FilterResult, FilterState

__all__ = ["FixedGainTobitObserver"]


class FixedGainTobitObserver(Estimator):
    """The observer (5.2) with the gain ``L``; see the module docstring.

    Parameters
    ----------
    A : (n, n) array_like
    L : (n, m) array_like
        The observer gain (predictor gain for ``form="predictor"``, filter gain for ``"filter"``).
    C : (m, n) array_like
    sigma : float or (m,) array_like
        Measurement-noise standard deviations.
    lower, upper : float or (m,) array_like
        Censoring limits of the readings.
    gain_form : {"tobit", "linear"}, default "tobit"
    form : {"predictor", "filter"}, default "predictor"

    Raises
    ------
    ShapeError, ValidationError
        Matrices that do not conform; an unknown option.
    """

    _name = "FixedGainTobitObserver"
    _filter_doc = """Run the observer (5.2) over ``y`` (..., T, m): rows x̂ (``times`` 1..T)."""
    _filter_params = {"x0": "array_like, optional\n    The initial estimate x̂_0, ``(n,)`` or ``(..., n)`` (default 0)."}
    _allow_missing = False
    _missing_reason = "the observer (5.2) has a given gain and no rule for a lost reading"

    def __init__(
        self,
        A: Any,
        L: Any,
        C: Any,
        sigma: Any,
        lower: Any = -np.inf,
        upper: Any = np.inf,
        *,
        gain_form: str = "tobit",
        form: str = "predictor",
    ):
        check_option(gain_form, "gain_form", ("tobit", "linear"))
        check_option(form, "form", ("predictor", "filter"))
        self.A, self.L, self.C = (np.atleast_2d(as_float_array(v, name)) for v, name in ((A, "A"), (L, "L"), (C, "C")))
        n, m = self.A.shape[0], self.C.shape[0]
        if self.A.shape != (n, n) or self.L.shape != (n, m) or self.C.shape[1] != n:
            raise ShapeError(
                f"A, L, C: expected (n, n), (n, m), (m, n), got {self.A.shape}, {self.L.shape}, {self.C.shape}"
            )
        self.sigma = as_float_array(sigma, "sigma")
        self.lower = as_float_array(lower, "lower", allow_inf=True)
        self.upper = as_float_array(upper, "upper", allow_inf=True)
        self.gain_form, self.form = gain_form, form
        self.n, self.m = n, m

    def _expected(self, x: np.ndarray) -> np.ndarray:
        if self.gain_form == "linear":
            return x @ self.C.T
        return unchecked_moments(x @ self.C.T, self.sigma, self.lower, self.upper).censored_mean

    def _initial(self, N, x0, P0, batch):
        n = self.n
        if x0 is None:
            return np.zeros((N, n)), None, {}
        x = as_float_array(x0, "x0")
        try:
            return np.broadcast_to(x, tuple(batch) + (n,)).reshape(N, n).copy(), None, {}
        except ValueError:
            raise ShapeError(f"x0: expected ({n},) or the batch shape + ({n},), got {x.shape}") from None

    def _step_arrays(self, k, x, P, S, carry, y, u, options=None):
        if self.form == "filter":
            xbar = x @ self.A.T
            return xbar + (y - self._expected(xbar)) @ self.L.T, None, None, carry, xbar, None, None
        return x @ self.A.T + (y - self._expected(x)) @ self.L.T, None, None, carry, None, None, None

    def filter(  # type: ignore[override]  # no u, no P0: the estimate carries no covariance
        self, y: Any, *, x0: Any = None, outputs: Any = "all", state: FilterState | None = None
    ) -> FilterResult:
        return self._run(y, None, x0, None, outputs=outputs, state=state)
