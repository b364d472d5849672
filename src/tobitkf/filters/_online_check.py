r"""The divergence check of the online ``step``: the correction check of ``filter``, kept in the state.

``filter`` warns once when a run's updates grow far larger than its own covariance allows
(:func:`tobitkf.filters.core._correction_check`): the statistic

.. math:: c_k = \max_i \frac{(\hat x_{k|k} - \hat x_{k|k-1})_i^2}{(P_{k|k-1})_{ii}},

each capped at ``CORRECTION_CAP`` times the threshold, summed over a window of ``CORRECTION_WINDOW``
steps and compared with :func:`~tobitkf.filters.core.correction_threshold` (100 times the
:math:`1 - 10^{-9}` quantile of :math:`\chi^2_{mW}`, a bound that a consistent filter's sum stays below).

A ``step`` loop gets the same check, at a fraction of the cost of a step: it looks at every
:data:`STRIDE`-th step (``state.k`` a multiple of it). For a consistent filter each :math:`c_k` is at most
the normalised innovation squared of its step, and those are independent from step to step, so a sum over
any ``W`` distinct steps stays below :math:`\chi^2_{mW}`: the bound holds for the sampled steps as it does
for consecutive ones, while a filter that diverges keeps making huge updates and is seen within
``STRIDE * W`` steps. On a checked step, the prediction comes from the step's own numpy path when it ran,
or is recomputed from the previous state (one time update, in numpy). The window of the last ``W`` checked
values of each run, and the fact that the lineage has warned, travel in the state's ``carry`` (key
:data:`KEY`), not in a global: each lineage of states (a run started with ``init``, its pickles, its
copies) warns at most once, and a state from before the warning still warns in a new lineage.

Not checked, as in ``filter``: a fixed-gain filter (the steady-state TKF: its covariance is nominal), a run
whose covariance stopped being finite (the non-finite check warns about it), components of zero predicted
variance.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from .._progress import plural

__all__ = [
    "CORRECTION_CAP",
    "CORRECTION_FACTOR",
    "CORRECTION_WINDOW",
    "KEY",
    "STRIDE",
    "has_warned",
    "check_step",
    "correction_threshold",
]

# --------------------------------------------------------------------------- shared with filter's check

#: steps of the window over which the normalised corrections are summed
CORRECTION_WINDOW = 20
#: how far above its bound for a consistent filter the window's sum must be to count as divergence
CORRECTION_FACTOR = 100.0
#: each step adds at most this fraction of the threshold: one absurd reading (an outlier, a hostile prior) is a
#: surprise, not a divergence; it takes at least 1 / CORRECTION_CAP such updates within a window
CORRECTION_CAP = 0.25


def correction_threshold(m: int, window: int = CORRECTION_WINDOW) -> float:
    r""":data:`CORRECTION_FACTOR` times the :math:`1 - 10^{-9}` quantile of :math:`\chi^2_{mW}`: the window sum
    of :func:`~tobitkf.filters.core.correction_statistic` above which a filter has stopped describing its readings."""
    from scipy.stats import chi2

    return CORRECTION_FACTOR * float(chi2.isf(1e-9, max(m, 1) * window))


def _correction_remedy(est: Any) -> str:
    if getattr(est, "noise_term", None) == "total_variance":
        return (
            "noise_term='dissertation' or 'exact_pv' (the total variance makes the gain grow like a^2 when the "
            "prediction sits a standard deviations inside the censored region), or the assumed-density filter "
            "(AssumedDensityTobitFilter)"
        )
    return "check the model (A, Q, R, the channel) against the readings; the assumed-density filter for censored ones"


def _caller_level() -> int:
    """``stacklevel`` of the first frame outside this package: the warning points at the user's call (a test,
    a script), however many of the package's own functions (``filter`` wrappers, an experiment) lie between."""
    import sys

    frame: Any = sys._getframe(1)
    level = 1
    while frame is not None and str(frame.f_globals.get("__name__", "")).startswith("tobitkf"):
        frame, level = frame.f_back, level + 1
    return level


# --------------------------------------------------------------------------- the online check


#: key of the check's memory in a state's ``carry``: a float64 array (N, W + 1), the last W checked values of
#: each run (column ``count % W`` the next to write), then (column W) the count of checked steps, -1 once the
#: lineage warned
KEY = "_correction_window"
#: the check looks at the steps whose ``k`` is a multiple of this
STRIDE = 8
_TINY = 1e-300
_FLOAT_TINY = np.finfo(np.float64).tiny  # the filters' zero-variance test (correction_statistic)
_CHECK_BLOCK = 1 << 19  # values of the statistic's (runs, T, n) arrays per block of :func:`_correction_check`


def _limits(est: Any) -> tuple[float, ...]:
    """The thresholds for a window of 1..W checked steps (cached on the estimator: one chi-square quantile each)."""
    cached = est.__dict__.get("_correction_limits")
    if cached is None:
        cached = est.__dict__["_correction_limits"] = tuple(
            correction_threshold(est.m, w) for w in range(1, CORRECTION_WINDOW + 1)
        )
    return cached


def _statistic(est: Any, prev: Any, new: Any, u: Any, xp: Any, Pp: Any) -> list[float] | np.ndarray:
    """:func:`~tobitkf.filters.core.correction_statistic` of one step, per run, over the first ``n`` components
    (the reported state): from the step's prediction ``xp``/``Pp`` when given, else from the previous state
    and the step's transition (only the reported block of the prediction: its mean and variances). One run
    of a small state: Python floats (a list of one value); else numpy, shape (N,)."""
    n = new.n
    if xp is None or Pp is None:
        x, P = prev.x, prev.P
        assert P is not None, "checked by the caller"
        fixed = _fixed_transition(est, new.k, u, prev.carry) if x.shape[0] == 1 and P.shape[0] == 1 else None
        if fixed is not None:  # one run, a transition that does not change: A, diag(Q) as lists, cached
            sl, A_l, q_l, A, q = fixed
            if sl is not None:
                x, P = x[:, sl], P[:, sl, sl]
            if n * x.shape[-1] <= 16:
                return [_one_run(A_l, x[0].tolist(), P[0].tolist(), q_l, 0.0, new.x[0, :n].tolist())]
            var_l = ((A @ P[0]) * A).sum(axis=1) + q  # one run: numpy's products, then Python floats
            return [_one_run_moments((A @ x[0]).tolist(), var_l.tolist(), new.x[0, :n].tolist())]
        tr = est._transition(new.k, u, prev.carry)
        A = tr.A
        if tr.shift:  # the block shift: the reported block is A times block `source`, plus the noise of the top
            sl = slice(tr.source * A.shape[-1], (tr.source + 1) * A.shape[-1])
            x, P = x[:, sl], P[:, sl, sl]
        A = A[:n]
        q = tr.Qd.diagonal()[:n]
        b = tr.b
        if x.shape[0] == 1 and P.shape[0] == 1 and n * x.shape[-1] <= 16:
            return [_one_run(A.tolist(), x[0].tolist(), P[0].tolist(), q.tolist(), b, new.x[0, :n].tolist())]
        mean = x @ A.T + (b[:, :n] if isinstance(b, np.ndarray) and b.ndim == 2 else b)
        var = np.einsum("ij,njk,ik->ni", A, P, A) + q
    else:
        mean, var = xp[:, :n], Pp.diagonal(0, -2, -1)[:, :n]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d = new.x[:, :n] - mean
        c = np.where(var > _TINY, d * d / np.where(var > _TINY, var, 1.0), 0.0)
    c = np.where(np.isfinite(c), c, 0.0)
    return c.max(axis=-1) if n else np.zeros(new.x.shape[0])


def _fixed_transition(est: Any, k: int, u: Any, carry: Any) -> tuple | None:
    """The transition of a check as ``(block slice or None, A, diag(Q), A, diag(Q))`` (lists, then arrays; the
    reported rows) when it is the same at every step, cached on the estimator (keyed on its system); None
    otherwise. The same at every step: no input, a time-invariant system and the transition of the Kalman-type
    families (KF, TKF, dropping KF, the assumed-density families on a linear system, the fading TKF's block
    shift), which depends on the system only. Building it costs a few µs of a checked step."""
    if u is not None:
        return None
    sys_ = est.system if hasattr(est, "system") else None
    cached = est.__dict__.get("_check_transition")
    if cached is not None and cached[0] is sys_:
        return cached[1]
    fixed = None
    if getattr(type(est)._transition, "system_only", False) and getattr(sys_, "time_invariant", False):
        tr = est._transition(k, None, carry)
        A = tr.A
        sl = slice(tr.source * A.shape[-1], (tr.source + 1) * A.shape[-1]) if tr.shift else None
        A = np.array(A[: est.n])
        q = tr.Qd.diagonal()[: est.n].copy()
        fixed = (sl, A.tolist(), q.tolist(), A, q)
    est.__dict__["_check_transition"] = (sys_, fixed)
    return fixed


def system_only(transition):
    """Mark a family's ``_transition`` as depending on the system only (no carry, no step-dependent choice), so that
    on a time-invariant system without input the check caches it (:func:`_fixed_transition`); a subclass that
    overrides ``_transition`` is not marked unless it says so too."""
    transition.system_only = True
    return transition


def _one_run_moments(mean: list, var: list, post: list) -> float:
    """:func:`_one_run` from the predicted mean and variances of the reported block (lists)."""
    best = 0.0
    for m, v, p in zip(mean, var, post):
        if v > _TINY and math.isfinite(v):
            d = p - m
            c = d * d / v
            if c > best and math.isfinite(c):
                best = c
    return best


def _one_run(A: list, x: list, P: list, q: list, b: Any, post: list) -> float:
    """:func:`_statistic` of one run in Python floats: the predicted mean and variances of the reported block,
    :math:`\\bar x_i = A_i x + b_i`, :math:`\\bar P_{ii} = A_i P A_i^T + Q_{ii}`, then the largest
    :math:`(\\hat x_i - \\bar x_i)^2 / \\bar P_{ii}` (0 for a non-positive or non-finite variance or value)."""
    bb = b.ravel().tolist() if isinstance(b, np.ndarray) else None
    best = 0.0
    idx = range(len(x))
    for i, row in enumerate(A):
        m = bb[i] if bb is not None else float(b)
        var = q[i]
        for j in idx:
            a = row[j]
            if a:
                m += a * x[j]
                Pj = P[j]
                acc = 0.0
                for l in idx:
                    acc += Pj[l] * row[l]
                var += a * acc
        if var > _TINY and math.isfinite(var):
            d = post[i] - m
            c = d * d / var
            if c > best and math.isfinite(c):
                best = c
    return best


def check_step(
    est: Any,
    prev: Any,
    new: Any,
    u: np.ndarray | None = None,
    xp: np.ndarray | None = None,
    Pp: np.ndarray | None = None,
) -> Any:
    """Carry the check's memory from ``prev`` into ``new`` (the state ``step`` made from it) and, on a checked
    step, update it and warn once when a run's window sum exceeds its threshold. ``xp``/``Pp``: the step's
    prediction when it computed one (its numpy path); else, on a checked step, it is recomputed from ``prev``
    and ``u`` (the step's input). Returns ``new`` (its ``carry`` replaced by a new dict when the memory
    changed; the states are not otherwise touched)."""
    memo = prev.carry.get(KEY)
    if new.k % STRIDE or prev.carry.get("_diverged"):
        return _keep(new, memo)
    N = new.x.shape[0]
    W = CORRECTION_WINDOW
    valid = _valid(memo, N)
    if valid and memo[0, W] < 0:  # this lineage warned
        return _keep(new, memo)
    if prev.P is None or _fixed_gain(est, new.k, u, prev.carry):
        return new  # a fixed-gain filter's nominal covariance claims no consistency
    c = _statistic(est, prev, new, u, xp, Pp)
    count = int(memo[0, W]) if valid else 0  # 0: none yet, or not this check's (a state edited by hand)
    w = min(count + 1, W)
    limit = _limits(est)[w - 1]
    cap = CORRECTION_CAP * limit
    if N == 1:  # one run: Python floats
        vals = memo[0].tolist() if valid else [0.0] * (W + 1)
        vals[count % W] = float(c[0])
        vals[W] = count + 1.0
        total = sum(vals[:W])  # the capped sum is no larger: capped only when the plain one is not below the limit
        if not total <= limit:
            total = sum(v if v < cap else cap for v in vals[:W])
        runs = int(total > limit and all(map(math.isfinite, new.x[0].tolist())))
        window = np.array([vals])
    else:
        window = memo.copy() if valid else np.zeros((N, W + 1))
        window[:, count % W] = c
        window[:, W] = count + 1.0
        over = (np.minimum(window[:, :W], cap).sum(axis=-1) > limit) & np.isfinite(new.x).all(axis=-1)
        runs = int(over.sum())
    if runs:
        _warn(est, new.k, runs, N, w, limit)
        window[:, W] = -1.0
    _set_carry(new, window)
    return new


def has_warned(state: Any) -> bool:
    """Whether the lineage of ``state`` has given the online divergence warning (its memory says so)."""
    memo = state.carry.get(KEY)
    return _valid(memo, state.x.shape[0]) and bool(memo[0, CORRECTION_WINDOW] < 0)


def _keep(new: Any, memo: Any) -> Any:
    """``new`` with ``memo`` in its carry (a step that rebuilt its carry would drop it)."""
    if memo is not None and new.carry.get(KEY) is not memo:
        _set_carry(new, memo)
    return new


def _valid(memo: Any, N: int) -> bool:
    """Whether ``memo`` is this check's memory for N runs: a float64 array (N, W + 1), the last W checked values
    of each run then the count of checked steps (-1 once it warned)."""
    return (
        isinstance(memo, np.ndarray)
        and memo.dtype == np.float64
        and memo.shape == (N, CORRECTION_WINDOW + 1)
        and (memo[0, CORRECTION_WINDOW] == -1.0 or 0.0 <= memo[0, CORRECTION_WINDOW] < 2.0**53)
    )


def _fixed_gain(est: Any, k: int, u: Any, carry: Any) -> bool:
    """Whether ``est`` predicts a fixed (nominal) covariance (its transition's ``P_fixed``): asked once per
    estimator; a family without a transition (a nonlinear model's sigma points) has none."""
    cached = est.__dict__.get("_fixed_gain")
    if cached is None:
        try:
            cached = est._transition(k, u, carry).P_fixed is not None
        except NotImplementedError:
            cached = False
        est.__dict__["_fixed_gain"] = cached
    return bool(cached)


def _set_carry(state: Any, memo: Any) -> None:
    carry = dict(state.carry)
    carry[KEY] = memo
    state.__dict__["carry"] = carry  # a frozen dataclass: its fields live in __dict__ (as ``step_state`` sets them)


def _warn(est: Any, k: int, runs: int, N: int, w: int, limit: float) -> None:
    warnings.warn(
        f"{est._name}: its updates became far larger than its own covariance allows by step k={k} in {runs} of "
        f"{plural(N, 'run')} (the sum over the last {w} checked steps, every {STRIDE}th, of the squared updates in "
        f"predicted variances, each capped at {CORRECTION_CAP * limit:.3g}, exceeds {limit:.3g}): the estimate no "
        f"longer follows the readings while its covariance says it should (a diverging filter, or a model or "
        f"readings with gross errors). Remedy: {_correction_remedy(est)}",
        RuntimeWarning,
        stacklevel=_caller_level(),
    )


# --------------------------------------------------------------------------- a filter that stopped listening


def correction_statistic(mean: np.ndarray, pred_mean: np.ndarray, pred_cov: np.ndarray) -> np.ndarray:
    r"""Size of each update relative to the prediction's spread: :math:`c_k = \max_i (\hat x_{k|k} -
    \hat x_{k|k-1})_i^2 / (P_{k|k-1})_{ii}`, shape ``mean.shape[:-1]``.

    For a consistent Kalman-type update :math:`\hat x_{k|k} - \hat x_{k|k-1} = Ke_k`, and each component's
    :math:`c` is at most the Mahalanobis size :math:`(Ke)^T\bar P^{-1}Ke = e^TR_{ee}^{-1}H\bar PH^T R_{ee}^{-1}e
    \le e^TR_{ee}^{-1}e`, the normalised innovation squared (:math:`\chi^2_m`). So a sum of c over W steps is
    below a :math:`\chi^2_{mW}` variable. Rows without a reading give 0; a component of zero predicted
    variance, or non-finite values (a diverged run), count 0 here (the covariance check reports those).
    """
    d = mean - pred_mean
    v = np.diagonal(pred_cov, axis1=-2, axis2=-1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        c = np.where(v > _FLOAT_TINY, d * d / np.where(v > _FLOAT_TINY, v, 1.0), 0.0)
    c = np.where(np.isfinite(c), c, 0.0)
    return c.max(axis=-1) if c.shape[-1] else np.zeros(c.shape[:-1])


def _nominal_covariance(pc: np.ndarray) -> bool:
    """Whether the predicted covariance is the same at every step of every run (a fixed-gain filter's nominal
    one). The first, second and last steps are compared before the whole record, so a filter whose covariance
    changes pays three small comparisons, not a pass over every covariance."""
    if pc.shape[-3] < 2:
        return False
    first = pc[..., :1, :, :]
    if not ((pc[..., 1:2, :, :] == first).all() and (pc[..., -1:, :, :] == first).all()):
        return False
    return bool((pc == first).all())


def _correction_check(est: Any, result: Any) -> None:
    r"""Warn once when a ``filter`` run's updates are far larger than its own covariance allows: the window sum
    over :data:`CORRECTION_WINDOW` steps of :func:`correction_statistic`, each step capped at
    :data:`CORRECTION_CAP` of the threshold (so one outlier never suffices), above :func:`correction_threshold`
    (the capped sum is below the plain one, so the bound for a consistent filter still holds).
    A diverging filter whose covariance stays finite and small (confidently wrong, e.g. the TKF's
    ``noise_term="total_variance"`` deep in the censored region) is caught here; the non-finite covariance
    check (:func:`_divergence_warning`) catches the others. Needs the recorded ``mean``, ``pred_mean`` and
    ``pred_cov`` (``outputs="all"``, the default); a fixed-gain filter (its covariance the same at every
    step, a nominal one) is not checked."""
    mean, pm, pc = result.mean, result.pred_mean, result.pred_cov
    if mean is None or pm is None or pc is None or mean.ndim < 2 or mean.shape[-2] < 1:
        return
    if _nominal_covariance(pc):
        return  # a fixed-gain filter's nominal covariance (the same at every step) claims no consistency
    T, n = mean.shape[-2:]
    W = min(CORRECTION_WINDOW, T)
    limit = correction_threshold(est.m, W)
    mean2, pm2, pc2 = mean.reshape(-1, T, n), pm.reshape(-1, T, n), pc.reshape(-1, T, n, n)
    N = mean2.shape[0]
    # blocks of runs of about 4 MB of statistics: the check's temporaries stay in cache and are never fresh pages
    # (over a whole record they were larger than the filter's own work)
    B = max(1, _CHECK_BLOCK // max(T * n, 1))
    hit = np.zeros(N, dtype=bool)
    ends = np.full(N, T - W + 1)
    for lo in range(0, N, B):
        hi = min(lo + B, N)
        c = np.minimum(correction_statistic(mean2[lo:hi], pm2[lo:hi], pc2[lo:hi]), CORRECTION_CAP * limit)
        cs = np.cumsum(c, axis=-1)
        win = cs[:, W - 1 :].copy()
        win[:, 1:] -= cs[:, : T - W]
        over = win > limit
        if not over.any():
            continue
        # a run whose means stopped being finite is the non-finite check's to report (one warning per event)
        over &= np.isfinite(mean2[lo:hi]).all(axis=(-2, -1))[:, None]
        hit[lo:hi] = over.any(axis=-1)
        ends[lo:hi] = np.where(hit[lo:hi], np.argmax(over, axis=-1), T - W + 1)
    if not hit.any():
        return
    run = int(np.argmin(ends))  # the run that crossed first; its window ends at row ends[run] + W - 1
    end = int(ends[run]) + W
    row = np.minimum(correction_statistic(mean2[run], pm2[run], pc2[run]), CORRECTION_CAP * limit)
    first = end - W + int(np.argmax(row[end - W : end]))  # the largest update of that window
    runs = int(hit.sum())
    k = int(result.times[first]) if result.times is not None else first + 1
    warnings.warn(
        f"{est._name}: its updates became far larger than its own covariance allows at step k={k} in {runs} of "
        f"{plural(N, 'run')} (the sum over {W} steps of the squared updates, in predicted variances and "
        f"each capped at {CORRECTION_CAP * limit:.3g}, exceeds {limit:.3g}): the estimate no longer follows the readings while its covariance "
        f"says it should (a diverging filter, or a model or readings with gross errors). Remedy: "
        f"{_correction_remedy(est)}",
        RuntimeWarning,
        stacklevel=_caller_level(),
    )
