r"""Panels: many short irregular series (subjects) sharing one continuous-time model, fitted jointly.

A :class:`Panel` holds N subjects with their own sample times, readings, per-reading censoring limits
(left and right in the same series), recorded indicators and known inputs. The filters run the subjects
as the runs of one batch: every subject's readings are placed on the union of all the subjects' sample
times (each subject's clock starting at its first visit with ``align="first"``, the default, or one
clock for all with ``align="common"``), the other times being missing readings (NaN). On the union
:math:`s_0 < s_1 < \dots < s_U` every gap has one exact discretisation
(:class:`~tobitkf.ContinuousLinearSystem`), shared by the runs, and a subject's missing readings leave its
posterior, likelihood and smoothed states exactly as on its own times (a gap split in two with no
reading between is the same transition: :math:`A(\Delta_1)A(\Delta_2) = A(\Delta_1 + \Delta_2)`, likewise
Q and the held input). So the panel log-likelihood is the sum of the subjects' own,

.. math::

    \ell(\theta) = \sum_{i=1}^N \log p_\theta(y^{(i)}_{1:T_i}),

each term exact (Kalman) without censoring and the assumed-density approximation
(:class:`~tobitkf.AssumedDensityTobitFilter`, uncensored readings first) with it; :func:`fit_panel`
maximises it (BFGS, standard errors from the observed information) over a map
:math:`\theta \mapsto` :class:`~tobitkf.ContinuousLinearSystem`. The prior is the state at a subject's
first visit (``align="first"``) or at the panel's start (``align="common"``: the earliest visit, or
``start``). Inputs are held over each gap (zero-order hold): the value given with a reading acts over
the gap ending at it, so on the union a subject's rows between two of its readings take the later one's.

The cost is that of N runs over U steps (U the number of distinct times after alignment): a panel
sampled on whole days has U no larger than its longest follow-up in days.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from .._validation import ShapeError, ValidationError, as_float_array
from ..channels.censoring import Censoring
from ..filters._readings import censoring_sides
from ..filters.assumed_density import assumed_density_filter
from ..filters.kalman import KalmanFilter
from ..filters.likelihood import prediction_log_densities
from ..filters.smoothing import rts_smooth
from ..models.continuous import ContinuousLinearSystem, check_increasing, time_values
from ..models.linear import LinearSystem
from ._direct import checked_map, fit_map, start_values, system_or_none
from ._results import FitResult, _progress_callback

__all__ = ["Panel", "PanelArrays", "PanelModel", "panel_log_likelihood", "panel_smooth", "panel_forecast", "fit_panel"]

ALIGN = ("first", "common")


def _per_subject(value: Any, N: int, name: str) -> list[Any]:
    """``value`` as one entry per subject: a sequence of N entries, or one value (scalar / (m,)) for all."""
    if value is None:
        return [None] * N
    if isinstance(value, (list, tuple)) and len(value) == N:
        return list(value)
    arr = np.asarray(value, dtype=object if isinstance(value, (list, tuple)) else None)
    if arr.dtype != object and arr.ndim <= 1:
        return [value] * N
    raise ShapeError(f"{name}: expected one entry per subject ({N}) or one value for all, got {type(value).__name__}")


def _column(a: Any, T: int, m: int, name: str, *, fill: float | None = None, allow_nan: bool = True) -> np.ndarray:
    if a is None:
        assert fill is not None, "a missing column needs a fill value"
        return np.full((T, m), fill)
    arr = as_float_array(a, name, allow_nan=allow_nan, allow_inf=fill is not None)
    if arr.ndim == 0:
        return np.full((T, m), float(arr))
    if arr.ndim == 1 and m == 1 and arr.size == T:
        return arr[:, None].copy()
    if arr.ndim == 1 and arr.size == m:
        return np.broadcast_to(arr, (T, m)).copy()
    if arr.shape != (T, m):
        raise ShapeError(f"{name}: expected ({T}, {m}) (one row per reading) or one value, got {arr.shape}")
    return arr.copy()


class Panel:
    r"""N subjects, each with its own sample times and readings (module docstring).

    Parameters
    ----------
    times : sequence of N (T_i,) array_like
        Each subject's strictly increasing sample times: floats in the model's time unit, or dates.
    y : sequence of N (T_i,) or (T_i, m) array_like
        Readings; a censored reading holds its limit; NaN = missing.
    lower, upper : optional
        Censoring limits: one value (scalar or (m,)) for all, or per subject a value or (T_i,) / (T_i, m)
        per reading; ``-inf`` / ``+inf`` (or NaN) for none. Left and right limits may both be present.
    censored : sequence of N bool array_like, optional
        The recorded censoring indicator (default: the limit rule, a reading at a limit is censored). A
        flagged reading strictly inside its limits is an interval reading (its value known only to lie
        between them; the assumed-density likelihood scores the interval's predictive probability).
    u : sequence of N (T_i, p) array_like, optional
        Known inputs with each reading (held over the gap ending at it).
    ids : sequence of N labels, optional

    Raises
    ------
    ValidationError
        A subject without readings, unordered or duplicate times, lower >= upper, a reading outside its
        limits, a flag on a reading inside its limits.
    ShapeError
        Lists of different lengths, a column that does not match its subject's readings.

    Examples
    --------
    >>> import tobitkf as tk
    >>> p = tk.Panel([[0.0, 1.5], [0.0, 0.5, 2.0]], [[1.0, 0.2], [0.3, 0.1, 0.1]], lower=0.1)
    >>> p.n_subjects, p.counts.tolist(), p.n_obs
    (2, [2, 3], 5)
    """

    def __init__(
        self,
        times: Sequence[Any],
        y: Sequence[Any],
        *,
        lower: Any = None,
        upper: Any = None,
        censored: Any = None,
        u: Any = None,
        ids: Sequence[Any] | None = None,
    ):
        if isinstance(times, np.ndarray) and times.dtype != object:
            raise ShapeError("times: expected one sequence of times per subject (a list), got one array")
        N = len(times)
        if N == 0:
            raise ValidationError("times: expected at least one subject")
        if len(y) != N:
            raise ShapeError(f"y: expected one record per subject ({N}), got {len(y)}")
        ys = []
        for i, yi in enumerate(y):
            a = as_float_array(yi, f"y[{i}]", allow_nan=True)
            ys.append(a[:, None] if a.ndim == 1 else a)
        m = ys[0].shape[1]
        los, his, cs, us = (
            _per_subject(v, N, k) for v, k in ((lower, "lower"), (upper, "upper"), (censored, "censored"), (u, "u"))
        )
        self.times: list[np.ndarray] = []
        self.y: list[np.ndarray] = []
        self.lower: list[np.ndarray] = []
        self.upper: list[np.ndarray] = []
        self.censored: list[np.ndarray] = []
        self.u: list[np.ndarray | None] = []
        for i in range(N):
            yi = ys[i]
            if yi.ndim != 2 or yi.shape[1] != m:
                raise ShapeError(f"y[{i}]: expected ({yi.shape[0]}, {m}) like the first subject, got {yi.shape}")
            T = yi.shape[0]
            if T == 0:
                raise ValidationError(f"y[{i}]: subject {i} has no readings")
            ti = np.asarray(times[i])
            if ti.ndim != 1 or ti.size != T:
                raise ShapeError(f"times[{i}]: expected {T} times (one per reading), got shape {ti.shape}")
            vals = time_values(ti, name=f"times[{i}]")  # the order check does not depend on the unit
            check_increasing(vals, f"times[{i}]")
            lo = _column(los[i], T, m, f"lower[{i}]", fill=-np.inf)
            hi = _column(his[i], T, m, f"upper[{i}]", fill=np.inf)
            lo, hi = np.where(np.isnan(lo), -np.inf, lo), np.where(np.isnan(hi), np.inf, hi)
            Censoring(lower=lo, upper=hi).check_measurements(yi, f"y[{i}]")  # lower < upper, readings inside
            ci = None if cs[i] is None else np.asarray(cs[i])
            if ci is not None and ci.size == T * m:
                ci = ci.reshape(T, m)
            side = censoring_sides(yi, lo, hi, ci, name=f"censored[{i}]", intervals=True)
            if ci is not None:  # a flagged reading inside its limits: an interval reading (side 0)
                side = np.where(np.broadcast_to(np.asarray(ci, dtype=bool), side.shape) & (side == 0), 2, side)
            ui = None
            if us[i] is not None:
                ui = as_float_array(us[i], f"u[{i}]")
                ui = ui[:, None] if ui.ndim == 1 else ui
                if ui.shape[0] != T:
                    raise ShapeError(f"u[{i}]: expected {T} rows (one per reading), got {ui.shape}")
            self.times.append(ti)
            self.y.append(yi)
            self.lower.append(lo)
            self.upper.append(hi)
            self.censored.append(side != 0)
            self.u.append(ui)
        if any(v is None for v in self.u) and any(v is not None for v in self.u):
            raise ValidationError("u: give the inputs for every subject or for none")
        self.m = m
        self.ids = list(range(N)) if ids is None else list(ids)
        if len(self.ids) != N:
            raise ShapeError(f"ids: expected {N} labels, got {len(self.ids)}")

    @classmethod
    def from_long(
        cls,
        subject: Any,
        times: Any,
        y: Any,
        *,
        lower: Any = None,
        upper: Any = None,
        censored: Any = None,
        u: Any = None,
    ) -> Panel:
        """A panel from long-format columns (one row per reading): ``subject`` labels, ``times``, ``y`` and
        optional per-row ``lower``, ``upper`` (scalars allowed), ``censored``, ``u`` (rows, p). Subjects in
        order of first appearance; each subject's rows must be in time order."""
        sub = np.asarray(subject)
        n = sub.shape[0]
        ids, first = np.unique(sub, return_index=True)
        order = ids[np.argsort(first)]

        def cut(col: Any, name: str) -> Any:
            if col is None or np.ndim(col) == 0:
                return col
            arr = np.asarray(col)
            if arr.shape[0] != n:
                raise ShapeError(f"{name}: expected {n} rows like subject, got {arr.shape[0]}")
            return [arr[sub == s] for s in order]

        return cls(
            cut(times, "times"),
            cut(y, "y"),
            lower=cut(lower, "lower"),
            upper=cut(upper, "upper"),
            censored=cut(censored, "censored"),
            u=cut(u, "u"),
            ids=list(order),
        )

    @classmethod
    def from_records(
        cls, records: Any, *, regressors: Sequence[str] = (), intercept: bool = False, ids: Sequence[Any] | None = None
    ) -> Panel:
        """A panel from read records: a :class:`~tobitkf.data.CensoredPanel` (``read_censored_panel``) or a
        sequence of :class:`~tobitkf.data.CensoredSeries` with ``times``, each subject's readings, limits and
        recorded indicator as read; the inputs ``u`` are a column of ones (``intercept``) and the named
        covariates (``regressors``), or none.

        Raises
        ------
        ValidationError
            A record without times, an unknown covariate, or a blank regressor (named by its line and column
            when the record was read from a file).

        Examples
        --------
        >>> import tobitkf as tk
        >>> from tobitkf.data import read_censored_panel
        >>> recs = read_censored_panel({"id": ["a", "a", "b"], "day": [0, 7, 3], "v": ["1.0", "<0.5", "2.0"]},
        ...                            id="id", time="day", y="v")
        >>> p = tk.Panel.from_records(recs, intercept=True)
        >>> p.ids, p.counts.tolist(), p.lower[0][:, 0].tolist(), p.u[1].tolist()
        (['a', 'b'], [2, 1], [-inf, 0.5], [[1.0]])
        """
        if hasattr(records, "series") and hasattr(records, "ids"):
            ids = records.ids if ids is None else ids
            records = list(records.series.values())
        records = list(records)
        us = []
        for i, r in enumerate(records):
            if getattr(r, "times", None) is None:
                raise ValidationError(f"records[{i}]: {r.name!r} has no sample times (read it with time=...)")
            cols = [np.ones(r.steps)] if intercept else []
            for name in regressors:
                if name not in r.covariates:
                    raise ValidationError(
                        f"regressors: {r.name!r} has no covariate {name!r}; known: {', '.join(r.covariates) or 'none'}"
                    )
                v = np.asarray(r.covariates[name], dtype=float)
                if np.isnan(v).any():
                    k = int(np.argmax(np.isnan(v)))
                    at = r.where(k, name) if hasattr(r, "where") else f"{r.name!r} reading {k + 1}, column {name!r}"
                    raise ValidationError(f"{at}: a blank regressor; regressors must be known for every reading")
                cols.append(v)
            us.append(np.column_stack(cols) if cols else None)
        return cls(
            [r.times for r in records],
            [r.y for r in records],
            lower=[r.lower for r in records],
            upper=[r.upper for r in records],
            censored=[r.censored for r in records],
            u=us if us and us[0] is not None else None,
            ids=ids,
        )

    @property
    def n_subjects(self) -> int:
        return len(self.y)

    @property
    def counts(self) -> np.ndarray:
        """Readings per subject (N,)."""
        return np.array([yi.shape[0] for yi in self.y])

    @property
    def n_obs(self) -> int:
        """Readings present (not NaN) in the whole panel."""
        return int(sum(int((~np.isnan(yi)).sum()) for yi in self.y))

    def __repr__(self) -> str:
        return f"Panel({self.n_subjects} subjects, {self.n_obs} readings, m={self.m})"

    def arrays(
        self, system: ContinuousLinearSystem, *, align: str = "first", start: Any = None, grid: Any = None
    ) -> PanelArrays:
        """The padded arrays on the union of the (aligned) sample times, in ``system``'s time unit; ``grid``
        (floats in that unit, on the aligned clock) adds times without readings (rows ``grid_rows``).

        Raises
        ------
        ValidationError
            Unknown ``align``, ``start`` with ``align="first"`` or after the first visit.
        """
        if align not in ALIGN:
            raise ValidationError(f"align: expected 'first' or 'common', got {align!r}")
        if align == "first" and start is not None:
            raise ValidationError("start: only with align='common' (with 'first' each prior is at the first visit)")
        dated = [np.asarray(t).dtype.kind in "MOUS" for t in self.times]
        if any(dated) and not all(dated):
            raise ValidationError("times: give every subject's times as dates or every subject's as numbers")
        if all(dated):
            origin = min(np.asarray(t, dtype="datetime64[ns]").min() for t in self.times)
            if start is not None:
                origin = min(origin, np.asarray([start], dtype="datetime64[ns]")[0])
            ts = [system.time_values(t, origin=origin) for t in self.times]
            s0 = None if start is None else float(system.time_values([start], origin=origin)[0])
        else:
            ts = [as_float_array(t, "times", ndim=1) for t in self.times]
            s0 = None if start is None else float(as_float_array(start, "start", ndim=0))
        offsets = np.array([t[0] if align == "first" else 0.0 for t in ts])
        ts = [t - o for t, o in zip(ts, offsets)]
        g = None if grid is None else as_float_array(grid, "grid", ndim=1)
        if g is not None:
            check_increasing(g, "grid")
        union = np.unique(np.concatenate(ts + ([] if g is None else [g])))
        t0 = union[0] if s0 is None else s0
        if t0 > union[0]:
            raise ValidationError("start: the prior's time must be at or before the first visit")
        N, U, m = self.n_subjects, union.size, self.m
        y = np.full((N, U, m), np.nan)
        lo, hi = np.full((N, U, m), -np.inf), np.full((N, U, m), np.inf)
        flags = np.zeros((N, U, m), dtype=bool)
        p = None if self.u[0] is None else self.u[0].shape[1]
        u = None if p is None else np.zeros((N, U, p))
        rows = []
        for i, t in enumerate(ts):
            r = np.searchsorted(union, t)
            rows.append(r)
            y[i, r], lo[i, r], hi[i, r], flags[i, r] = self.y[i], self.lower[i], self.upper[i], self.censored[i]
            if u is not None:
                ui = self.u[i]
                assert ui is not None, "inputs are given for every subject or for none"
                nxt = np.minimum(np.searchsorted(r, np.arange(U)), r.size - 1)  # the next reading's row (hold)
                u[i] = ui[nxt]
        grid_rows = None if g is None else np.searchsorted(union, g)
        return PanelArrays(
            times=union,
            t0=float(t0),
            y=y,
            lower=lo,
            upper=hi,
            censored=flags,
            u=u,
            rows=rows,
            offsets=offsets,
            grid_rows=grid_rows,
        )


@dataclass
class PanelArrays:
    """A panel on the union of its aligned sample times: ``times`` (U,) in the model's unit, ``t0`` the
    prior's time, ``y``/``lower``/``upper``/``censored`` (N, U, m), ``u`` (N, U, p) or None, ``rows`` each
    subject's rows in the union, ``offsets`` (N,) each subject's time shift (its first visit with
    ``align="first"``, else 0), ``grid_rows`` the rows of the requested grid (or None)."""

    times: np.ndarray
    t0: float
    y: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    censored: np.ndarray
    u: np.ndarray | None
    rows: list[np.ndarray]
    offsets: np.ndarray
    grid_rows: np.ndarray | None = None

    @property
    def censoring_present(self) -> bool:
        return bool(self.censored.any())


def _run(system: ContinuousLinearSystem, arr: PanelArrays, likelihood: str):
    """The panel's filter on the union: (FilterResult, the discrete system, per-step log-likelihood (N, U))."""
    disc = system._system_on(arr.times, arr.t0)
    if likelihood == "kalman":
        res = KalmanFilter(disc, backend="numpy").filter(arr.y, u=arr.u)
        return res, disc, prediction_log_densities(disc, arr.y, res, u=arr.u)
    est = assumed_density_filter(disc, Censoring())
    # per-reading limits of each subject (runs): the filter's per-step options, row i of each array
    step_data = {"lower": arr.lower, "upper": arr.upper, "censored": arr.censored}
    res = est._run(arr.y, arr.u, None, None, step_data=step_data)
    return res, disc, res.extras["log_likelihood"]


def _likelihood_kind(likelihood: str, arr: PanelArrays) -> str:
    if likelihood not in ("auto", "kalman", "adf"):
        raise ValidationError(f"likelihood: expected 'auto', 'kalman' or 'adf', got {likelihood!r}")
    if likelihood == "auto":
        finite = np.isfinite(arr.lower).any() or np.isfinite(arr.upper).any()
        return "adf" if finite else "kalman"
    return likelihood


def _check_model(system: Any) -> ContinuousLinearSystem:
    if not isinstance(system, ContinuousLinearSystem):
        raise ValidationError(
            f"system: a panel needs a model in continuous time (tk.ContinuousLinearSystem), got {type(system).__name__}"
        )
    return system


def _check_panel(panel: Any) -> Panel:
    if not isinstance(panel, Panel):
        raise ValidationError(f"panel: expected a tk.Panel, got {type(panel).__name__}")
    return panel


def panel_log_likelihood(
    system: ContinuousLinearSystem,
    panel: Panel,
    *,
    likelihood: str = "auto",
    align: str = "first",
    start: Any = None,
    per_subject: bool = False,
) -> Any:
    """The panel log-likelihood (module docstring): a float, or (N,) per subject with ``per_subject``.

    ``likelihood``: ``"kalman"`` (every reading exact), ``"adf"`` (assumed density, censored readings by
    their limits), ``"auto"`` (``"adf"`` when any limit is finite).

    Raises
    ------
    ValidationError
        A discrete-time system, not a panel, an unknown option.
    """
    arr = _check_panel(panel).arrays(_check_model(system), align=align, start=start)
    _, _, terms = _run(system, arr, _likelihood_kind(likelihood, arr))
    per = terms.sum(-1)
    return per if per_subject else float(per.sum())


def panel_smooth(
    system: ContinuousLinearSystem,
    panel: Panel,
    *,
    likelihood: str = "auto",
    align: str = "first",
    start: Any = None,
    grid: Any = None,
) -> list[dict[str, Any]]:
    """Each subject's smoothed states at its own sample times: a list of N dicts with ``id``, ``times`` (as
    given), ``mean`` (T_i, n), ``cov`` (T_i, n, n), and the latent reading's ``reading_mean`` (T_i, m) and
    ``reading_sd`` (T_i, m) (:math:`C\\hat x + Du`, :math:`\\sqrt{\\mathrm{diag}(CPC^T + R)}`).

    ``grid`` (G,): floats in the model's unit on the aligned clock (with ``align="first"`` the time since
    each subject's first visit): each dict gains ``grid_mean`` (G, n) and ``grid_cov`` (G, n, n), the
    subject's smoothed state at those times (the grid joins the union as missing readings; a grid time
    before the first visit moves every prior there, as the single-series grid smoother does).

    Raises
    ------
    ValidationError
        As :func:`panel_log_likelihood`.
    """
    arr = _check_panel(panel).arrays(_check_model(system), align=align, start=start, grid=grid)
    res, disc, _ = _run(system, arr, _likelihood_kind(likelihood, arr))
    sm = rts_smooth(res, disc)
    assert sm.mean is not None and sm.cov is not None
    C, R = system.measurement(1), system.measurement_cov(1)
    D = None if system.D is None else system.D.at(1)
    out = []
    for i, r in enumerate(arr.rows):
        mean, cov = np.asarray(sm.mean[i, r]), np.asarray(sm.cov[i, r])
        ym = mean @ C.T
        if D is not None and arr.u is not None:
            ym = ym + arr.u[i, r] @ D.T
        sd = np.sqrt(np.einsum("ij,tjk,ik->ti", C, cov, C) + np.diagonal(R))
        out.append(
            {
                "id": panel.ids[i],
                "times": panel.times[i],
                "mean": mean,
                "cov": cov,
                "reading_mean": ym,
                "reading_sd": sd,
            }
        )
        if arr.grid_rows is not None:
            out[-1]["grid_mean"] = np.asarray(sm.mean[i, arr.grid_rows])
            out[-1]["grid_cov"] = np.asarray(sm.cov[i, arr.grid_rows])
    return out


def panel_forecast(
    system: ContinuousLinearSystem,
    panel: Panel,
    ahead: Any,
    *,
    u: Any = None,
    likelihood: str = "auto",
    align: str = "first",
    start: Any = None,
) -> dict[str, np.ndarray]:
    r"""Each subject's state and latent reading ``ahead`` time units after its last visit, from the filter:
    :math:`\hat x = A(h)\hat x_{T_i} + B(h)u`, :math:`P = A(h)P_{T_i}A(h)^T + Q(h)`, reading
    :math:`N(C\hat x + Du, CPC^T + R)`.

    Parameters
    ----------
    ahead : float or (N,) array_like
        Lead times (> 0) in the model's unit, one for all or one per subject.
    u : (p,) or (N, p) array_like, optional
        The input held over the lead time (needed when the model has inputs).

    Returns
    -------
    dict
        ``mean`` (N, n), ``cov`` (N, n, n), ``reading_mean`` (N, m), ``reading_sd`` (N, m).

    Raises
    ------
    ValidationError
        A lead time not above 0, missing inputs, and as :func:`panel_log_likelihood`.
    """
    arr = _check_panel(panel).arrays(_check_model(system), align=align, start=start)
    h = np.broadcast_to(as_float_array(ahead, "ahead", ndim=(0, 1)), (panel.n_subjects,))
    if not (h > 0).all():
        raise ValidationError("ahead: expected lead times > 0")
    res, _, _ = _run(system, arr, _likelihood_kind(likelihood, arr))
    assert res.mean is not None and res.cov is not None
    last = np.array([r[-1] for r in arr.rows])
    idx = np.arange(panel.n_subjects)
    x, P = np.asarray(res.mean)[idx, last], np.asarray(res.cov)[idx, last]
    A, Q, B = system.discretize(h)
    x = np.einsum("nij,nj->ni", A, x)
    P = A @ P @ np.swapaxes(A, -1, -2) + Q
    uu = None
    if system.p is not None:
        if u is None:
            raise ValidationError(f"u: the model has inputs; give the input held over the lead time ({system.p},)")
        uu = np.broadcast_to(as_float_array(u, "u", ndim=(1, 2)), (panel.n_subjects, system.p))
        if B is not None:
            x = x + np.einsum("nij,nj->ni", B, uu)
    C, R = system.measurement(1), system.measurement_cov(1)
    ym = x @ C.T
    if system.D is not None and uu is not None:
        ym = ym + uu @ system.D.at(1).T
    sd = np.sqrt(np.einsum("ij,njk,ik->ni", C, P, C) + np.diagonal(R))
    return {"mean": x, "cov": P, "reading_mean": ym, "reading_sd": sd}


class PanelModel:
    """A continuous-time model fitted to a panel: ``fitted`` the :class:`~tobitkf.ContinuousLinearSystem`
    at the estimates, and how the panel was aligned. :meth:`smooth` and :meth:`forecast` act per subject."""

    kind = "continuous_panel"

    def __init__(self, fitted: ContinuousLinearSystem, likelihood: str, align: str, start: Any = None):
        self.fitted, self.likelihood, self.align, self.start = fitted, likelihood, align, start

    def __repr__(self) -> str:
        return f"PanelModel(n={self.fitted.n}, m={self.fitted.m}, align={self.align!r})"

    def system(self, theta: Any = None, l: int = 0) -> LinearSystem:
        return self.fitted

    def smooth(self, res: FitResult) -> list[dict[str, Any]]:
        """:func:`panel_smooth` of the fitted model over the panel it was fitted to."""
        return panel_smooth(self.fitted, res.data, likelihood=self.likelihood, align=self.align, start=self.start)

    def forecast(self, res: FitResult, steps: int, *, X: Any = None, level: float = 0.95, lower=None, upper=None):
        """Each subject's latent reading 1..``steps`` time units after its last visit, with central ``level``
        intervals: ``mean``, ``sd``, ``lower``, ``upper`` (N, steps, m); ``X`` the held input ((p,) or (N, p))."""
        from scipy.special import ndtri

        z = float(ndtri(0.5 + level / 2))
        outs = [
            panel_forecast(
                self.fitted, res.data, h, u=X, likelihood=self.likelihood, align=self.align, start=self.start
            )
            for h in range(1, steps + 1)
        ]
        mean = np.stack([o["reading_mean"] for o in outs], axis=1)
        sd = np.stack([o["reading_sd"] for o in outs], axis=1)
        return {"mean": mean, "sd": sd, "lower": mean - z * sd, "upper": mean + z * sd, "level": level}

    def residuals(self, res: FitResult, seed: int = 0):
        raise ValidationError("residuals: not available for a panel fit; use the per-subject smoothed readings")

    @classmethod
    def from_spec(cls, spec: dict[str, Any]) -> PanelModel:
        """The model written by :meth:`to_spec` (``tk.load_fit``)."""
        S = spec["system"]
        fitted = ContinuousLinearSystem(
            S["Ac"], S["Qc"], S["C"], S["R"], S["x0"], S["P0"], Bc=S.get("Bc"), D=S.get("D"), unit=spec["unit"]
        )
        return cls(fitted, spec["likelihood"], spec["align"], spec.get("start"))

    def to_spec(self) -> dict[str, Any]:
        s = self.fitted
        return {
            "kind": self.kind,
            "align": self.align,
            "start": None
            if self.start is None
            else float(self.start)
            if isinstance(self.start, (int, float, np.number))
            else str(self.start),
            "likelihood": self.likelihood,
            "unit": s.unit,
            "system": {
                "Ac": s.Ac.tolist(),
                "Qc": s.Qc.tolist(),
                "C": s.measurement(1).tolist(),
                "R": s.measurement_cov(1).tolist(),
                "x0": s.x0.tolist(),
                "P0": s.P0.tolist(),
                "Bc": None if s.Bc is None else s.Bc.tolist(),
                "D": None if s.D is None else s.D.at(1).tolist(),
            },
        }


def fit_panel(
    model: Any,
    panel: Any,
    *,
    theta0: Any = None,
    names: Any = None,
    likelihood: str = "auto",
    align: str = "first",
    start: Any = None,
    method: str = "auto",
    maxiter: int = 500,
    gtol: float = 1e-3,
    standard_errors: bool = True,
    progress: Any = None,
) -> FitResult:
    r"""Maximum likelihood for a panel (module docstring): BFGS over :math:`\theta` of the summed
    log-likelihood of the subjects, standard errors from the observed information (central-difference
    Hessian). Called by :func:`tobitkf.fit` for a :class:`Panel` or a record with ``times``.

    Parameters
    ----------
    model : callable
        :math:`\theta \mapsto` :class:`~tobitkf.ContinuousLinearSystem`.
    panel : Panel
    theta0 : (k,) array_like
        Starting values.
    names : sequence of str, optional
    likelihood : {"auto", "kalman", "adf"}
    align : {"first", "common"}
        Each subject's prior at its first visit, or every subject on one clock from ``start``.
    method : {"auto", "direct"}
        Direct maximisation (the only method for continuous-time panels).

    Returns
    -------
    FitResult
        ``model`` a :class:`PanelModel` (``smooth()`` per subject, ``forecast(steps)`` per subject);
        ``data`` the panel.

    Raises
    ------
    ValidationError
        A model that is not a callable returning a ContinuousLinearSystem, no ``theta0``, ``method="em"``,
        a log-likelihood of -inf at ``theta0``.
    """
    t_start = time.perf_counter()
    panel = _check_panel(panel)
    if method not in ("auto", "direct"):
        raise ValidationError(f"method: a continuous-time panel is fitted directly ('direct'), got {method!r}")
    if not callable(model) or isinstance(model, LinearSystem):
        raise ValidationError("model: expected a callable theta -> ContinuousLinearSystem (with theta0)")
    if theta0 is None:
        raise ValidationError("theta0: a callable model needs starting values theta0")
    th0, names = start_values(theta0, names)
    sys_of = checked_map(model, ContinuousLinearSystem)

    s0 = sys_of(th0)
    arr = panel.arrays(s0, align=align, start=start)  # the union and the padded arrays, once
    kind = _likelihood_kind(likelihood, arr)

    def ll_of(th: np.ndarray) -> float:
        s = system_or_none(sys_of, th)
        if s is None:
            return -np.inf
        if s.unit != s0.unit:
            raise ValidationError("model: the map changed the time unit between parameter values")
        try:
            _, _, terms = _run(s, arr, kind)
        except (ValidationError, np.linalg.LinAlgError, FloatingPointError):
            return -np.inf
        return float(terms.sum())

    # converged means what it means for tk.fit's other models: the Newton step with the observed information
    # is below gtol standard errors in every parameter (checked also when no standard errors are reported)
    return fit_map(
        ll_of,
        th0,
        names,
        gtol=gtol,
        maxiter=maxiter,
        progress=_progress_callback(progress, "fit panel"),
        standard_errors=standard_errors,
        check_always=True,
        started=t_start,
        model_of=lambda th: PanelModel(sys_of(th), kind, align, start),
        n_obs=panel.n_obs,
        likelihood=kind,
        data=panel,
        extra={"subjects": panel.n_subjects, "union_steps": int(arr.times.size)},
    )


def single_series_panel(
    y: Any,
    times: Any,
    *,
    u: Any = None,
    censoring: Censoring | None = None,
    censored: Any = None,
    lower: Any = None,
    upper: Any = None,
) -> Panel:
    """One record ``y`` (T,) or (T, m) at ``times`` as a panel of one subject (what ``tk.fit(..., times=)`` fits);
    limits from ``censoring`` (scalar, (m,) or (T, m)) or ``lower``/``upper``."""
    if censoring is not None:
        if lower is not None or upper is not None:
            raise ValidationError("censoring: give either censoring or lower/upper, not both")
        lower, upper = censoring.lower, censoring.upper
    return Panel(
        [times],
        [y],
        lower=[lower],
        upper=[upper],
        censored=None if censored is None else [censored],
        u=None if u is None else [u],
    )
