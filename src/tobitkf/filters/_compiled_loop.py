r"""The compiled time loop of the assumed-density filters: one loop, a family's moments passed in.

Every assumed-density family (censoring one-/two-sided and multi-region, Rice fading, the protocol channel's
failure mixture, random saturation) updates its Gaussian channel by channel, and each channel's update is a
rank-one change along :math:`\bar Ph^T` (:mod:`tobitkf.filters._compiled_moments`):

.. math::

    \bar x, \bar P \text{ (predict: plain, or the block shift of an augmented state)}, \qquad
    \text{for each channel } l:\ \hat x = \bar x + \alpha\,\bar Ph_l^T,\quad
    P = \bar P - \beta\,\bar Ph_l^T h_l\bar P,

with :math:`(\alpha, \beta)` per run from the family's block function (:func:`~tobitkf.filters._compiled_moments.
family_block`). :func:`adf_loop` is that loop, written once: the predict of the TKF kernel
(:func:`~tobitkf.filters._kernels_block.predict_block`) or of the fading kernel
(:func:`~tobitkf.filters._kernels_fading.shift_predict_block`), the channel rows :math:`h_l` per step, a
multiplicative-noise term (the fading variance :math:`\sum_q f_q\bar Pf_q^T + (f_q\bar x)^2`), the runs in
blocks (runs on the last axis, vectorised), outputs carved from the output pool
(:func:`~tobitkf.filters.kalman.output_arrays`).

What a family gives the loop (:class:`CompiledSpec`, built by the ``*_spec`` functions below from an estimator
and a record; :func:`channel_spec` for any channel of the measurement contract that names its compiled block,
so that the generic :class:`~tobitkf.AssumedDensityFilter` of such a channel needs no spec of its own): its code, the rows ``H`` (TH, m, n_x), the fading rows ``F`` (TF, m, Q, n_x), the noise
variances ``r`` (TR, m), the limits ``lo``/``hi`` (TL, m), its parameters ``par`` (TP, m, K), the number of
mixture components ``J`` whose posterior weights are returned; per-step arrays are indexed by
``min(t, len - 1)`` (one row: constant). Covered: the standard covariance form, time-invariant system
matrices (control inputs through constant ``Bu``/``D``), the channel-order update; anything else (the Joseph
and square-root forms, time-varying matrices, per-step limits given to
``step``) runs the numpy path (``backend="auto"``) or is refused (``backend="numba"``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from ._backend import system_gap, use_kernel
from ._compiled_moments import (
    CENSORED,
    FAMILIES,
    INTERIOR,
    LOWER,
    MISSING,
    PROTOCOL,
    SATURATION,
    UPPER,
    classify,
    family_block,
)
from ._kernels import GL_W, GL_X
from ._kernels_block import _mirror, predict_block, runs_per_block
from ._kernels_fading import shift_predict_block
from ._readings import classify_readings
from .core import FilterState
from .kalman import kernel_result, output_arrays, state_specs

__all__ = [
    "adf_loop",
    "CompiledSpec",
    "compiled_filter",
    "censoring_spec",
    "fading_spec",
    "protocol_spec",
    "saturation_spec",
    "channel_spec",
]


@njit(cache=True, error_model="numpy", nogil=True)
def adf_loop(
    family,
    y,
    cls,
    A,
    Qd,
    H,
    F,
    r,
    lo,
    hi,
    par,
    J,
    npass,
    bu,
    du,
    x0,
    P0,
    means,
    covs,
    pmeans,
    pcovs,
    pu,
    ll,
    comp,
    x_last,
    P_last,
):
    r"""The assumed-density filter of ``family`` over N runs x T steps (module docstring); fills the outputs.

    ``y`` (N, T, m) readings (NaN: missing); ``cls`` (N, T, m) int8 their classes, or (N, 0, m): by the limit
    rule; ``A``, ``Qd`` (n, n) acting on the top block of the state (n_x = ``x0.shape[1]`` > n: the block
    shift); ``H``, ``F``, ``r``, ``lo``, ``hi``, ``par`` the family's per-step arrays; ``J`` its mixture
    components; ``bu`` (N, T, n) / ``du`` (N, T, m) the input terms (T axis 0: none); ``x0`` (N, n_x),
    ``P0`` (N or 1, n_x, n_x). Outputs (T axis 0: not written): ``means``, ``pmeans`` (N, T, n), ``covs``
    (N, T, n, n) or (N, T, n, 1) (the variances), ``pcovs`` (N, T, n, n), ``pu`` (N, T, m), ``ll`` (N, T),
    ``comp`` (N, T, m, J); ``x_last``, ``P_last`` the state after the last step."""
    N, T, m = y.shape
    nx = x0.shape[1]
    n = A.shape[0]
    B = min(runs_per_block(nx), N)
    x, xp = np.empty((nx, B)), np.empty((nx, B))
    P, Pp = np.empty((nx, nx, B)), np.empty((nx, nx, B))
    X = np.empty((nx, n, B))
    Pc = np.empty((nx, B))
    hx, hph, rb = np.empty(B), np.empty(B), np.empty(B)
    yv, lov, hiv = np.empty(B), np.empty(B), np.empty(B)
    cv = np.empty(B, dtype=np.int8)
    member = np.empty(B, dtype=np.bool_)
    alpha, beta, llb, pub = np.empty(B), np.empty(B), np.empty(B), np.empty(B)
    compb = np.zeros((J, B))
    buf = np.empty((2, GL_X.shape[0]))
    glx, glw = GL_X, GL_W
    has_cls, has_bu, has_du = cls.shape[1] > 0, bu.shape[1] > 0, du.shape[1] > 0
    w_mean, w_cov, w_pmean, w_pcov = means.shape[1] > 0, covs.shape[1] > 0, pmeans.shape[1] > 0, pcovs.shape[1] > 0
    w_pu, w_ll, w_comp = pu.shape[1] > 0, ll.shape[1] > 0, comp.shape[1] > 0
    var_only = covs.shape[3] == 1 and n > 1
    one_p = P0.shape[0] == 1
    Q = F.shape[2]
    for r0 in range(0, N, B):
        nb = min(B, N - r0)
        for b in range(nb):
            rp = 0 if one_p else r0 + b
            for i in range(nx):
                x[i, b] = x0[r0 + b, i]
                for j in range(nx):
                    P[i, j, b] = P0[rp, i, j]
        for t in range(T):
            if nx == n:
                predict_block(A, Qd, x, P, xp, Pp, X, nb)
            else:
                shift_predict_block(A, Qd, x, P, xp, Pp, X, nb)
            if has_bu:
                for i in range(n):
                    for b in range(nb):
                        xp[i, b] += bu[r0 + b, t, i]
            if w_pmean:
                for b in range(nb):
                    for i in range(n):
                        pmeans[r0 + b, t, i] = xp[i, b]
            if w_pcov:
                for b in range(nb):
                    for i in range(n):
                        for j in range(n):
                            pcovs[r0 + b, t, i, j] = Pp[i, j, b]
            for b in range(nb):
                llb[b] = 0.0
            th, tf, tr = min(t, H.shape[0] - 1), min(t, F.shape[0] - 1), min(t, r.shape[0] - 1)
            tl, tp = min(t, lo.shape[0] - 1), min(t, par.shape[0] - 1)
            for pl in range(npass * m):  # npass = 2: the readings inside their limits first, then the others
                ps, l = pl // m, pl % m
                h = H[th, l]
                lo_l, hi_l, r_l = lo[tl, l], hi[tl, l], r[tr, l]
                # P h^T, h x + d, h P h^T
                for i in range(nx):
                    for b in range(nb):
                        Pc[i, b] = 0.0
                for k in range(nx):
                    c = h[k]
                    if c != 0.0:
                        for i in range(nx):
                            for b in range(nb):
                                Pc[i, b] += Pp[k, i, b] * c
                for b in range(nb):
                    s = 0.0
                    q = 0.0
                    for k in range(nx):
                        s += h[k] * xp[k, b]
                        q += h[k] * Pc[k, b]
                    hx[b] = s + du[r0 + b, t, l] if has_du else s
                    hph[b] = q
                    rb[b] = r_l
                # the fading variance: sum_q f_q P f_q^T + (f_q x)^2
                for qq in range(Q):
                    f = F[tf, l, qq]
                    for k in range(nx):
                        fk = f[k]
                        if fk != 0.0:
                            for b in range(nb):
                                acc = 0.0
                                for j in range(nx):
                                    acc += Pp[k, j, b] * f[j]
                                rb[b] += fk * acc
                    for b in range(nb):
                        s = 0.0
                        for k in range(nx):
                            s += f[k] * xp[k, b]
                        rb[b] += s * s
                for b in range(nb):
                    yb = y[r0 + b, t, l]
                    yv[b] = yb
                    lov[b] = lo_l
                    hiv[b] = hi_l
                    c = cls[r0 + b, t, l] if has_cls else classify(yb, lo_l, hi_l)
                    member[b] = npass == 1 or ((c == INTERIOR) == (ps == 0))
                    cv[b] = c if member[b] else MISSING
                family_block(
                    family, nb, yv, cv, hx, hph, rb, lov, hiv, par[tp, l], alpha, beta, llb, pub, compb, glx, glw, buf
                )
                # the rank-one update along P h^T
                for i in range(nx):
                    for b in range(nb):
                        xp[i, b] += alpha[b] * Pc[i, b]
                for i in range(nx):
                    for j in range(i, nx):
                        for b in range(nb):
                            Pp[i, j, b] -= beta[b] * Pc[i, b] * Pc[j, b]
                _mirror(Pp, nb)
                if w_pu:
                    for b in range(nb):
                        if member[b]:
                            pu[r0 + b, t, l] = pub[b]
                if w_comp:
                    for b in range(nb):
                        for j in range(J):
                            comp[r0 + b, t, l, j] = compb[j, b]
            if w_ll:
                for b in range(nb):
                    ll[r0 + b, t] = llb[b]
            if w_mean:
                for b in range(nb):
                    for i in range(n):
                        means[r0 + b, t, i] = xp[i, b]
            if w_cov:
                for b in range(nb):
                    if var_only:
                        for i in range(n):
                            covs[r0 + b, t, i, 0] = Pp[i, i, b]
                    else:
                        for i in range(n):
                            for j in range(n):
                                covs[r0 + b, t, i, j] = Pp[i, j, b]
            x, xp = xp, x
            P, Pp = Pp, P
        for b in range(nb):
            for i in range(nx):
                x_last[r0 + b, i] = x[i, b]
                for j in range(nx):
                    P_last[r0 + b, i, j] = P[i, j, b]


@dataclass
class CompiledSpec:
    """What a family gives :func:`adf_loop` (module docstring); ``extras`` turns the loop's ``pu`` (N, T, m),
    ``ll`` (N, T) and ``comp`` (N, T, m, J) into the family's extras dict (batch shape restored)."""

    family: int
    H: np.ndarray
    r: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    par: np.ndarray
    J: int
    extras: Any
    F: np.ndarray | None = None
    cls: np.ndarray | None = None
    bu: np.ndarray | None = None
    du: np.ndarray | None = None
    npass: int = 1


def _c(a: Any) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float)


def _input_terms(est, u2: np.ndarray | None, N: int, n: int, m: int, *, feedthrough: bool = True):
    """``bu`` (N, T, n) and ``du`` (N, T, m) of a time-invariant system's inputs (T axis 0: none)."""
    sys_ = est.system
    bu = np.empty((N, 0, n))
    du = np.empty((N, 0, m))
    if u2 is not None:
        if sys_.Bu is not None:
            bu = _c(u2 @ sys_.Bu.at(1).T)
        if feedthrough and sys_.D is not None:
            du = _c(u2 @ sys_.D.at(1).T)
    return bu, du


def _per_batch(a: np.ndarray, batch: tuple[int, ...]) -> np.ndarray:
    return a.reshape(batch + a.shape[1:])


def censoring_spec(est, y2: np.ndarray, u2, state: FilterState, want, batch, step_data) -> CompiledSpec | None:
    """The :class:`~tobitkf.filters.assumed_density.AssumedDensityTobitFilter`'s arrays, or None when its
    options are not covered (time-varying R). ``order="uncensored_first"``: two passes over the channels, the
    readings inside their limits in the first, the others in the second."""
    if est._r is None:
        return None
    N, T, m = y2.shape
    lo, hi = est.censoring.all_limits(T, m, start=state.k + 1, check=False)
    flags = None if not step_data else step_data.get("censored")
    cls = None
    if flags is not None or "extras" in want:
        cls = classify_readings(y2, lo[None], hi[None])
        if flags is not None:
            at_limit = (cls == LOWER) | (cls == UPPER)
            cls = np.where(at_limit & ~flags, INTERIOR, cls).astype(np.int8)
    side = None if cls is None else np.where(cls == LOWER, -1, np.where(cls == UPPER, 1, 0)).astype(np.int8)

    def extras(pu, ll, comp):
        return {
            "p_uncensored": _per_batch(pu, batch),
            "log_likelihood": _per_batch(ll, batch),
            "side": _per_batch(side, batch),
        }

    bu, du = _input_terms(est, u2, N, est.n, m)
    return CompiledSpec(
        CENSORED,
        _c(est.system.measurement(1))[None],
        _c(est._r)[None],
        _c(lo),
        _c(hi),
        np.zeros((1, m, 0)),
        0,
        extras,
        cls=cls if flags is not None else None,
        bu=bu,
        du=du,
        npass=1 if est.order == "channels" else 2,
    )


def fading_spec(est, y2: np.ndarray, u2, state: FilterState, want, batch, step_data) -> CompiledSpec | None:
    """The :class:`~tobitkf.filters.adf_fading.FadingAssumedDensityFilter`'s arrays: the rows
    :math:`H_l = [\\bar\\vartheta(s)_lC_{k-s}(l)]_s` and the fading rows :math:`\\sqrt{\\tilde\\vartheta(s)_l}C_{k-s}(l)`
    in block s, for the first steps until all L + 1 terms exist (then constant)."""
    from ..channels.fading import measurement_matrix_at

    if est._r is None:
        return None
    N, T, m = y2.shape
    n, L, nx = est.n, est.L, est.nx
    TH = min(T, max(L - state.k, 0) + 1)
    H = np.zeros((TH, m, nx))
    F = np.zeros((TH, m, L + 1, nx))
    for t in range(TH):
        k = state.k + t + 1
        for s in range(min(L, k) + 1):
            Cs = measurement_matrix_at(est.system, k - s)
            for l in range(m):
                H[t, l, s * n : (s + 1) * n] = est.mean_g[s, l] * Cs[l]
                if est.var_g[s, l] > 0:
                    F[t, l, s, s * n : (s + 1) * n] = np.sqrt(est.var_g[s, l]) * Cs[l]
    lo, hi = est.censoring.all_limits(T, m, start=state.k + 1, check=False)

    def extras(pu, ll, comp):
        return {"p_uncensored": _per_batch(pu, batch), "log_likelihood": _per_batch(ll, batch)}

    bu, du = _input_terms(est, u2, N, n, m)
    return CompiledSpec(
        CENSORED, H, _c(est._r)[None], _c(lo), _c(hi), np.zeros((1, m, 0)), 0, extras, F=F, bu=bu, du=du
    )


def protocol_spec(est, y2: np.ndarray, u2, state: FilterState, want, batch, step_data) -> CompiledSpec | None:
    """The :class:`~tobitkf.filters.adf_protocol.ProtocolAssumedDensityFilter`'s arrays: per step the scheduled
    sensor's row :math:`\\mathbf 1^T \\otimes C_h`, its variance, the threshold and its failure law (the same
    number of outcomes for every sensor, else None)."""
    if len({v.size for v, _ in est.laws}) != 1 or (u2 is not None and est.system.D is not None):
        return None
    N, T, _ = y2.shape
    J = est.laws[0][0].size
    order = est.channel.schedule.order
    ks = state.k + 1 + np.arange(T)
    hs = order[(ks - 1) % order.size] - 1
    C = est.system.measurement(1)
    rdiag = est._variances(1)
    H = _c(np.tile(C[hs], (1, est.ell + 1)))[:, None, :]
    lam = np.stack([v for v, _ in est.laws])  # (p, J)
    with np.errstate(divide="ignore"):
        logp = np.log(np.stack([p for _, p in est.laws]))
    par = _c(np.concatenate([lam[hs], logp[hs]], axis=1))[:, None, :]
    tau = float(est.channel.threshold)

    def extras(pu, ll, comp):
        return {
            "failure_posterior": _per_batch(comp[:, :, 0], batch),
            "p_uncensored": _per_batch(pu[..., 0], batch),
            "log_likelihood": _per_batch(ll, batch),
        }

    bu, du = _input_terms(est, u2, N, est.n, 1, feedthrough=False)
    return CompiledSpec(
        PROTOCOL, H, _c(rdiag[hs])[:, None], np.full((1, 1), tau), np.full((1, 1), np.inf), par, J, extras, bu=bu, du=du
    )


def saturation_spec(est, y2: np.ndarray, u2, state: FilterState, want, batch, step_data) -> CompiledSpec | None:
    """The :class:`~tobitkf.filters.adf_saturation.SaturationAssumedDensityFilter`'s arrays: the levels and the
    log-probabilities of the three modes per sensor."""
    if u2 is not None and est.system.D is not None:
        return None
    N, T, m = y2.shape
    level = np.broadcast_to(est.channel.level, (m,))
    par = _c(np.concatenate([level[:, None], est._logp], axis=1))[None]

    def extras(pu, ll, comp):
        return {"mode_posterior": _per_batch(comp, batch), "log_likelihood": _per_batch(ll, batch)}

    bu, du = _input_terms(est, u2, N, est.n, m, feedthrough=False)
    inf = np.full((1, m), np.inf)
    return CompiledSpec(
        SATURATION,
        _c(est.system.measurement(1))[None],
        _c(est._variances(1))[None],
        -inf,
        inf,
        par,
        3,
        extras,
        bu=bu,
        du=du,
    )


def channel_spec(est, y2: np.ndarray, u2, state: FilterState, want, batch, step_data) -> CompiledSpec | None:
    """The generic :class:`~tobitkf.AssumedDensityFilter`'s arrays for a channel that names its compiled
    moments (:mod:`tobitkf.channels.base`): ``channel.compiled_moments``, a key of
    :data:`~tobitkf.filters._compiled_moments.FAMILIES` (the block function), and
    ``channel.compiled_parameters(k, steps, m)``, the block's ``par`` (TP, m, K) for the steps k..k+steps-1
    (TP = 1: constant). The rows are C, the noise variances R's diagonal, no limits (every reading but a
    missing one goes to the block). None (the numpy path) for a channel without compiled moments or a
    time-varying R.

    Raises
    ------
    ValidationError
        A ``compiled_moments`` that names no block of the compiled loop, or parameters of another shape.
    """
    from .._validation import ValidationError

    name = getattr(est.channel, "compiled_moments", None)
    if name is None or est._r is None:
        return None
    N, T, m = y2.shape
    family = FAMILIES.get(name) if isinstance(name, str) else None
    if family is None:
        raise ValidationError(
            f"compiled_moments: expected the name of a block of the compiled loop ({', '.join(FAMILIES)}) "
            f"for {type(est.channel).__name__}, got {name!r}"
        )
    par = _c(est.channel.compiled_parameters(state.k + 1, T, m))
    if par.ndim != 3 or par.shape[0] not in (1, T) or par.shape[1] != m:
        raise ValidationError(
            f"compiled_parameters: expected an array (1 or {T}, {m}, K) from {type(est.channel).__name__}, "
            f"got shape {par.shape}"
        )

    def extras(pu, ll, comp):
        return {"log_likelihood": _per_batch(ll, batch)}

    bu, du = _input_terms(est, u2, N, est.n, m)
    inf = np.full((1, m), np.inf)
    return CompiledSpec(
        family, _c(est.system.measurement(1))[None], _c(est._r)[None], -inf, inf, par, 0, extras, bu=bu, du=du
    )


def compiled_filter(est, y2, u2, state: FilterState, want, batch, step_data, spec_of) -> Any:
    """The compiled ``filter`` of an assumed-density family, or None (the numpy loop runs): decides with the
    estimator's ``backend`` (:func:`~tobitkf.filters._backend.use_kernel`), builds its arrays with
    ``spec_of`` (one of the ``*_spec`` functions) and runs :func:`adf_loop`. A covariance that stops being
    finite also returns None, so that the numpy loop reruns the call and reports where it diverged."""
    what = f"the {est._name}"
    gap = None
    if est.covariance_update != "standard":
        gap = f"covariance_update={est.covariance_update!r} (the compiled path runs the standard form)"
    gap = gap or system_gap(est.system, u2, inputs=True)
    spec = None
    if gap is None:
        spec = spec_of(est, y2, u2, state, want, batch, step_data)
        if spec is None:
            gap = "these options"
    if not use_kernel(getattr(est, "backend", "auto"), gap, what):
        return None
    assert spec is not None
    N, T, m = y2.shape
    n, nx = est.n, state.x.shape[-1]
    x0 = _c(state.x)
    P0 = _c(state.P)
    specs = state_specs(want, n)
    ext = "extras" in want
    means, covs, pmeans, pcovs, pu, ll, comp = output_arrays(
        N, T, *specs, (ext, (m,)), (ext, ()), (ext and spec.J > 0, (m, spec.J))
    )
    x_last, P_last = np.empty((N, nx)), np.empty((N, nx, nx))
    sys_ = est.system
    F = spec.F if spec.F is not None else np.zeros((1, m, 0, nx))
    cls = spec.cls if spec.cls is not None else np.empty((N, 0, m), dtype=np.int8)
    adf_loop(
        spec.family,
        np.ascontiguousarray(y2),
        np.ascontiguousarray(cls, dtype=np.int8),
        _c(sys_.transition(0)),
        _c(sys_.process_cov(0)),
        _c(spec.H),
        _c(F),
        _c(spec.r),
        _c(spec.lo),
        _c(spec.hi),
        _c(spec.par),
        spec.J,
        spec.npass,
        spec.bu,
        spec.du,
        x0,
        P0,
        means,
        covs,
        pmeans,
        pcovs,
        pu,
        ll,
        comp if comp.shape[1] > 0 else np.empty((N, 0, m, spec.J)),
        x_last,
        P_last,
    )
    if not np.isfinite(np.diagonal(P_last, axis1=-2, axis2=-1)).all():
        return None
    final = FilterState(k=state.k + T, batch_shape=batch, x=x_last, P=P_last, n=n, carry=state.carry)
    extras = spec.extras(pu, ll, comp) if ext else {}
    return kernel_result(want, batch, T, means, covs, pmeans, pcovs, extras, final)
