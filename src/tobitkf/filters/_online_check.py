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
from operator import mul
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
_INF = math.inf
_F64 = np.dtype(np.float64)
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
    of a small state without the prediction: Python floats (:func:`_one_run`, a list of one value); else numpy,
    shape (N,)."""
    n = new.n
    if xp is None or Pp is None:
        x, P = prev.x, prev.P
        assert P is not None, "checked by the caller"
        fixed = _fixed_transition(est, new.k, u, prev.carry)
        if fixed is None:
            sl, A, q, b = _reported_rows(est._transition(new.k, u, prev.carry), n)
            rows = None
        else:
            sl, rows, A, q = fixed
            b = 0.0
        if sl is not None:
            x, P = x[:, sl], P[:, sl, sl]
        if x.shape[0] == 1 and P.shape[0] == 1:  # one run: Python floats
            if fixed is None and A.size <= _PYTHON_ROUTE:
                rows = _rows(A, q)
            post = new.x.ravel().tolist()  # (more than the reported n components for an augmented state)
            if isinstance(b, np.ndarray):  # the offset b_i moved to the other side: (x_i - b_i) - A_i x
                post = [p - bi for p, bi in zip(post, b.ravel().tolist())]
            elif b:
                post = [p - b for p in post]
            if rows is not None:
                return [_one_run(rows, x.ravel().tolist(), P.ravel().tolist(), post)]
            var_l = ((A @ P[0]) * A).sum(axis=1) + q  # a larger state: numpy's products, then Python floats
            return [_one_run_moments((A @ x[0]).tolist(), var_l.tolist(), post)]
        mean = x @ A.T + (b[:, :n] if isinstance(b, np.ndarray) and b.ndim == 2 else b)
        var = np.einsum("ij,njk,ik->ni", A, P, A) + q
    else:
        mean, var = xp[:, :n], Pp.diagonal(0, -2, -1)[:, :n]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        d = new.x[:, :n] - mean
        c = np.where(var > _TINY, d * d / np.where(var > _TINY, var, 1.0), 0.0)
    c = np.where(np.isfinite(c), c, 0.0)
    return c.max(axis=-1) if n else np.zeros(new.x.shape[0])


def _reported_rows(tr: Any, n: int) -> tuple[slice | None, np.ndarray, np.ndarray, Any]:
    """Of a transition: the block of the previous state the reported block is predicted from (a slice, for the
    block shift; None: the whole state), the reported rows of A and of diag(Q), and the offset b."""
    A = tr.A
    sl = slice(tr.source * A.shape[-1], (tr.source + 1) * A.shape[-1]) if tr.shift else None
    return sl, A[:n], tr.Qd.diagonal()[:n], tr.b


#: one run whose reported block times the state (n * n_x) has at most this many entries: the statistic in
#: Python floats (:func:`_one_run`); a larger one through numpy's products
_PYTHON_ROUTE = 16


def _rows(A: np.ndarray, q: np.ndarray) -> tuple[tuple[list[float], list[float], float], ...]:
    r"""The reported rows of a transition for :func:`_one_run`: per component i, the row :math:`A_i` and the
    flattened outer product :math:`A_i^T A_i` (so that :math:`A_iPA_i^T` is one dot product with the flattened
    P), and :math:`Q_{ii}`, as Python floats."""
    return tuple(zip(A.tolist(), (A[:, :, None] * A[:, None, :]).reshape(A.shape[0], -1).tolist(), q.tolist()))


def _fixed_transition(est: Any, k: int, u: Any, carry: Any) -> tuple | None:
    """The transition of a check as ``(block slice or None, rows or None, A, diag(Q))`` (``rows`` of
    :func:`_rows` for a state small enough for the Python route; ``A``, ``diag(Q)`` the reported rows as
    arrays) when it is the same at every step, cached on the estimator (keyed on its system); None otherwise.
    The same at every step: no input, a time-invariant system and the transition of the Kalman-type families
    (KF, TKF, dropping KF, the assumed-density families on a linear system, the fading TKF's block shift), which
    depends on the system only. Building it costs a few µs of a checked step."""
    if u is not None:
        return None
    sys_ = est.system if hasattr(est, "system") else None
    cached = est.__dict__.get("_check_transition")
    if cached is not None and cached[0] is sys_:
        return cached[1]
    fixed = None
    if getattr(type(est)._transition, "system_only", False) and getattr(sys_, "time_invariant", False):
        sl, A, q, _ = _reported_rows(est._transition(k, None, carry), est.n)
        A, q = np.array(A), q.copy()
        fixed = (sl, _rows(A, q) if A.size <= _PYTHON_ROUTE else None, A, q)
    est.__dict__["_check_transition"] = (sys_, fixed)
    return fixed


def system_only(transition):
    """Mark a family's ``_transition`` as depending on the system only (no carry, no step-dependent choice), so that
    on a time-invariant system without input the check caches it (:func:`_fixed_transition`); a subclass that
    overrides ``_transition`` is not marked unless it says so too."""
    transition.system_only = True
    return transition


def _one_run_moments(mean: list, var: list, post: list) -> float:
    """The largest :math:`(\\hat x_i - \\bar x_i)^2 / \\bar P_{ii}` from the predicted mean and variances of the
    reported block (lists; 0 for a non-positive or non-finite variance or value): :func:`_one_run` of a larger
    state, whose moments numpy's products give faster than the rows' dot products."""
    best = 0.0
    for m, v, p in zip(mean, var, post):
        if _TINY < v < _INF:
            d = p - m
            c = d * d / v
            if best < c < _INF:
                best = c
    return best


def _one_run(rows: tuple, x: list, Pf: list, post: list) -> float:
    """:func:`_statistic` of one run in Python floats: with the ``rows`` of :func:`_rows`, the predicted mean and
    variance of each reported component, :math:`\\bar x_i = A_i x`, :math:`\\bar P_{ii} = A_i P A_i^T + Q_{ii}`
    (``Pf`` the flattened P), then the largest :math:`(\\hat x_i - \\bar x_i)^2 / \\bar P_{ii}` (``post`` the
    :math:`\\hat x_i`; 0 for a non-positive or non-finite variance or value). Two dot products per component,
    each a single call (``sum(map(mul, ...))``): the checked step's largest cost is the interpreter's, not
    the arithmetic's."""
    best = 0.0
    for (a, aa, qi), p in zip(rows, post):
        v = qi + sum(map(mul, aa, Pf))
        if _TINY < v < _INF:  # (False for NaN)
            d = p - sum(map(mul, a, x))
            c = d * d / v
            if best < c < _INF:
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
    carry = prev.carry
    memo = carry.get(KEY)
    if new.k % STRIDE or carry.get("_diverged"):
        return _keep(new, memo)
    N = new.x.shape[0]
    W = CORRECTION_WINDOW
    count = _count(memo, N)  # None: no memory yet, or not this check's (a state edited by hand)
    if count is not None and count < 0:  # this lineage warned
        return _keep(new, memo)
    cache = est.__dict__
    fixed_gain = cache.get("_fixed_gain")
    if prev.P is None or (_fixed_gain(est, new.k, u, carry) if fixed_gain is None else fixed_gain):
        return new  # a fixed-gain filter's nominal covariance claims no consistency
    done = 0 if count is None else int(count)
    w = min(done + 1, W)
    limit = (cache.get("_correction_limits") or _limits(est))[w - 1]
    slot = done % W
    if N == 1:  # one run: Python floats, and the memory of the previous state copied with two entries changed
        vals = memo.tolist()[0] if done else [0.0] * (W + 1)
        vals[slot] = c0 = float(_statistic(est, prev, new, u, xp, Pp)[0])
        vals[W] = 0.0
        total = sum(vals)  # the capped sum is no larger: capped only when the plain one is not below the limit
        if not total <= limit:
            cap = CORRECTION_CAP * limit
            total = sum(v if v < cap else cap for v in vals)
        runs = int(total > limit and all(map(math.isfinite, new.x.ravel().tolist())))
        window = memo.copy() if done else np.zeros((1, W + 1))
        window[0, slot] = c0
        window[0, W] = -1.0 if runs else done + 1.0
    else:
        window = memo.copy() if done else np.zeros((N, W + 1))
        window[:, slot] = _statistic(est, prev, new, u, xp, Pp)
        cap = CORRECTION_CAP * limit
        over = (np.minimum(window[:, :W], cap).sum(axis=-1) > limit) & np.isfinite(new.x).all(axis=-1)
        runs = int(over.sum())
        window[:, W] = -1.0 if runs else done + 1.0
    if runs:
        _warn(est, new.k, runs, N, w, limit)
    _set_carry(new, window)
    return new


def has_warned(state: Any) -> bool:
    """Whether the lineage of ``state`` has given the online divergence warning (its memory says so)."""
    count = _count(state.carry.get(KEY), state.x.shape[0])
    return count is not None and count < 0


def _keep(new: Any, memo: Any) -> Any:
    """``new`` with ``memo`` in its carry (a step that rebuilt its carry would drop it)."""
    if memo is not None and new.carry.get(KEY) is not memo:
        _set_carry(new, memo)
    return new


def _count(memo: Any, N: int) -> float | None:
    """The count of checked steps in ``memo`` (-1 once the lineage warned) when it is this check's memory for N
    runs: a float64 array (N, W + 1), the last W checked values of each run then that count; None otherwise."""
    if not isinstance(memo, np.ndarray) or memo.shape != (N, CORRECTION_WINDOW + 1) or memo.dtype != _F64:
        return None
    count = memo.item(0, CORRECTION_WINDOW)
    return count if count == -1.0 or 0.0 <= count < 2.0**53 else None


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
