r"""What every fit shares: the :class:`FitResult` it returns, its residual diagnostics, the observed
information's inverse and the ``progress`` option.

The fits (:class:`~tobitkf.inference.censored_ar.CensoredAR` by exact maximum likelihood,
:func:`~tobitkf.inference.state_space.fit_state_space` by EM or direct maximisation) and the front door
:func:`~tobitkf.inference.fitting.fit` each import this module, and none of them imports another's, so
the fitting modules stand in one line: ``_results`` under the two fits, the two under ``fitting``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._progress import plural
from .._validation import ValidationError
from ._optimize import _inverse_information  # noqa: F401 - re-exported: the fits import it from here

__all__ = ["FitResult", "residual_diagnostics"]

_FORMAT = "tobitkf-fit"
_VERSION = 1


def _progress_callback(progress: Any, title: str):
    """``(callback, close, ticker)`` for a ``progress`` option.

    None (the default): no callback, and a :class:`~tobitkf.inference._optimize.Ticker` that prints a
    line on stderr every 10 s once the fit has run 10 s; False: silent; True: a rich status line on a
    terminal, else the ticker's lines from the start; a callable: called with every iteration's trace
    entry (no lines).
    """
    import sys

    from ._optimize import Ticker

    if progress is None:
        return None, lambda: None, Ticker(title)
    if progress is False:
        return None, lambda: None, Ticker(title, enabled=False)
    if progress is True:
        if not sys.stderr.isatty():
            return None, lambda: None, Ticker(title, after=0.0)
        from rich.console import Console

        console = Console(stderr=True)
        status = console.status(f"{title}: starting")
        status.start()

        def cb(entry: dict[str, Any]) -> None:
            status.update(
                f"{title}: iteration {entry['iteration']}, log-likelihood {entry['loglik']:.6f}, "
                f"{entry.get('seconds', 0):.1f} s"
            )

        return cb, status.stop, Ticker(title, enabled=False)
    if callable(progress):
        return progress, lambda: None, Ticker(title, enabled=False)
    raise ValidationError(f"progress: expected None, True, False or a callable, got {progress!r}")


@dataclass
class FitResult:
    r"""A fitted model: estimates with standard errors, likelihood, criteria, trace and data.

    Attributes
    ----------
    model : object
        The template that was fitted (e.g. :class:`~tobitkf.inference.censored_ar.CensoredAR`).
    names : list of str
        Parameter names, in the order of ``theta``.
    theta : (k,) ndarray
        Estimates (natural parameters).
    cov : (k, k) ndarray or None
        Inverse observed information (NaN when it is not positive definite).
    loglik : float
        Log-likelihood at the estimates, all constants included.
    n_obs, n_params : int
        Readings present (for BIC) and free parameters.
    method : str
        ``"direct"`` or ``"em"``.
    likelihood : str
        ``"exact"`` (quadrature), ``"kalman"`` or ``"adf"`` (assumed density).
    converged : bool
    message : str
    trace : list of dict
        Per iteration: ``iteration``, ``loglik``, ``params``, ``seconds``.
    fit_seconds : float
        Wall time of the whole fit (standard errors included).
    evaluations : int
        Log-likelihood evaluations.
    data : object or None
        The data the model was fitted to (not saved by :meth:`save`).
    """

    model: Any
    names: list[str]
    theta: np.ndarray
    cov: np.ndarray | None
    loglik: float
    n_obs: int
    n_params: int
    method: str
    likelihood: str
    converged: bool
    message: str = ""
    trace: list[dict[str, Any]] = field(default_factory=list)
    fit_seconds: float = 0.0
    evaluations: int = 0
    data: Any = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def params(self) -> dict[str, float]:
        """Estimates by name."""
        return {n: float(v) for n, v in zip(self.names, self.theta)}

    @property
    def se(self) -> dict[str, float]:
        """Standard errors by name (NaN when the information is not positive definite or not computed)."""
        if self.cov is None:
            return {n: float("nan") for n in self.names}
        d = np.diagonal(self.cov)
        return {n: float(np.sqrt(v)) if v >= 0 else float("nan") for n, v in zip(self.names, d)}

    @property
    def aic(self) -> float:
        r""":math:`-2\ell + 2k`."""
        return -2.0 * self.loglik + 2.0 * self.n_params

    @property
    def bic(self) -> float:
        r""":math:`-2\ell + k\log n`, n the readings present."""
        return -2.0 * self.loglik + self.n_params * math.log(max(self.n_obs, 1))

    def summary(self) -> str:
        """A plain-text table of the estimates and criteria."""
        lines = [
            f"{self.model!r}: {self.method} maximum likelihood ({self.likelihood} likelihood), "
            f"{'converged' if self.converged else 'NOT converged'} in {plural(len(self.trace), 'iteration')}, "
            f"{self.fit_seconds:.2f} s",
            f"{'parameter':<12}{'estimate':>14}{'s.e.':>12}",
        ]
        se = self.se
        for n, v in self.params.items():
            lines.append(f"{n:<12}{v:>14.6f}{se[n]:>12.6f}")
        lines.append(
            f"log-likelihood {self.loglik:.6f}   AIC {self.aic:.4f}   BIC {self.bic:.4f}   "
            f"n = {self.n_obs}, k = {self.n_params}"
        )
        return "\n".join(lines)

    # after the fit ------------------------------------------------------------------
    def system(self):
        """The fitted model as a :class:`~tobitkf.LinearSystem`."""
        if hasattr(self.model, "system"):
            l = _regressors(self)
            return self.model.system(self.theta, l)
        raise ValidationError("model: this fit has no state-space form")

    def smooth(self):
        r"""Posterior mean and variance of every latent reading :math:`y^*_t` given all the data, ``(mean, var)``
        (T,) each (exact to quadrature for a censored AR model)."""
        self._need_data()
        return self.model.smooth(self)

    def forecast(self, steps: int, *, X: Any = None, level: float = 0.95, lower: Any = None, upper: Any = None):
        r"""Forecast the next ``steps`` readings with intervals; see the model's ``forecast``.

        Returns
        -------
        dict
            ``mean``, ``lower``, ``upper`` (steps,) of the latent reading :math:`y^*_{T+h}` (central
            ``level`` interval), and ``censored_mean``, ``censored_lower``, ``censored_upper`` of the
            reading as recorded (clipped at ``lower``/``upper``, default the last limits).
        """
        self._need_data()
        from .._validation import check_count

        steps = check_count(steps, "steps")
        if not (isinstance(level, (int, float)) and 0 < level < 1):
            raise ValidationError(f"level: expected a probability in (0, 1), got {level!r}")
        return self.model.forecast(self, steps, X=X, level=level, lower=lower, upper=upper)

    def residuals(self, *, seed: int = 0) -> np.ndarray:
        r"""Standardised residuals: randomised quantile residuals (Dunn & Smyth 1996),
        :math:`r_t = \Phi^{-1}(u_t)` with :math:`u_t = F_t(y_t)` for an exact reading and :math:`u_t` uniform
        on the censored part of :math:`F_t` (seeded) for a censored one; :math:`F_t` the one-step predictive
        distribution. N(0, 1) and independent under the model. NaN for missing readings.
        """
        self._need_data()
        return self.model.residuals(self, seed=seed)

    def diagnostics(self, *, seed: int = 0, lags: int | None = None) -> dict[str, Any]:
        """:func:`residual_diagnostics` of :meth:`residuals`."""
        return residual_diagnostics(
            self.residuals(seed=seed),
            lags=lags,
            fitted=self.n_params - _regressors(self) - 1 if self.model.kind == "censored_ar" else 0,
        )

    def _need_data(self) -> None:
        if self.data is None:
            raise ValidationError("data: this fit was loaded without its data; pass data= to load_fit")

    # saving -------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """A plain JSON-able record (no data)."""
        return {
            "format": _FORMAT,
            "version": _VERSION,
            "model": self.model.to_spec(),
            "names": list(self.names),
            "estimates": self.params,
            "se": self.se,
            "cov": None if self.cov is None else np.where(np.isfinite(self.cov), self.cov, np.nan).tolist(),
            "loglik": self.loglik,
            "aic": self.aic,
            "bic": self.bic,
            "n_obs": self.n_obs,
            "n_params": self.n_params,
            "method": self.method,
            "likelihood": self.likelihood,
            "converged": self.converged,
            "message": self.message,
            "trace": self.trace,
            "fit_seconds": self.fit_seconds,
            "evaluations": self.evaluations,
            "extra": _jsonable(self.extra),
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write :meth:`to_dict` as JSON (NaN written as null) atomically; returns the path."""
        from .._io import atomic_write_json

        path = Path(path)
        atomic_write_json(path, _jsonable(self.to_dict()))
        return path


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    return obj


def _regressors(res: FitResult) -> int:
    return sum(1 for n in res.names if n.startswith("beta"))


def residual_diagnostics(r: Any, *, lags: int | None = None, fitted: int = 0) -> dict[str, Any]:
    r"""Checks that standardised residuals are independent N(0, 1).

    Mean, variance, skewness, excess kurtosis, the Jarque–Bera statistic (with its chi-square(2) p-value)
    and the Ljung–Box statistic :math:`Q = n(n+2)\sum_{h\le H}\hat\rho_h^2/(n-h)` over H lags with its
    chi-square(H - ``fitted``) p-value (Ljung & Box 1978), on the residuals present (NaN skipped; the
    autocorrelations over the pairs present).

    Returns
    -------
    dict
    """
    from scipy import stats

    r = np.asarray(r, dtype=float)
    ok = ~np.isnan(r)
    x = r[ok]
    n = int(x.size)
    if n < 3:
        raise ValidationError(f"r: expected at least 3 residuals, got {n}")
    H = int(lags) if lags is not None else int(min(10, max(1, n // 5)))
    mean, var = float(x.mean()), float(x.var(ddof=1))
    skew, kurt = float(stats.skew(x)), float(stats.kurtosis(x))
    jb = n / 6.0 * (skew**2 + kurt**2 / 4.0)
    c = np.where(ok, r - mean, np.nan)
    denom = np.nansum(c * c)
    acf = []
    for h in range(1, H + 1):
        a, b = c[h:], c[:-h]
        both = ~np.isnan(a) & ~np.isnan(b)
        acf.append(float(np.sum(a[both] * b[both]) / denom))
    rho = np.array(acf)
    Q = float(n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, H + 1))))
    dof = max(H - fitted, 1)
    return {
        "n": n,
        "mean": mean,
        "variance": var,
        "skewness": skew,
        "excess_kurtosis": kurt,
        "jarque_bera": jb,
        "jarque_bera_p": float(stats.chi2.sf(jb, 2)),
        "ljung_box": Q,
        "ljung_box_lags": H,
        "ljung_box_dof": dof,
        "ljung_box_p": float(stats.chi2.sf(Q, dof)),
        "autocorrelation": rho.tolist(),
    }
