r"""What each assumed-density family hands the one compiled loop, and the call of that loop for ``filter``.

:func:`compiled_filter` decides with the estimator's ``backend`` whether the compiled loop
(:func:`tobitkf.filters._compiled_loop.compiled_loop`) runs the call, builds the family's arrays with its ``*_spec``
function (a :class:`CompiledSpec`: the update code, the rows ``H``, the fading rows ``F``, the noise variances, the
limits, the parameters and the number of mixture components, per step or constant; see the loop's module docstring)
and runs the loop into outputs carved from the output pool. Plain Python: the compiled functions are in
:mod:`tobitkf.filters._compiled_loop`, read through the module at each call (so that a test can watch them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from . import _compiled_loop
from ._backend import system_gap, use_compiled
from ._boundary import _noise_variances
from ._compiled_moments import (
    CENSORED,
    LOWER,
    PROTOCOL,
    SATURATION,
    UPPER,
    channel_kind,
    kind,
)
from ._compiled_soa import censored_entry
from ._outputs import _empty, compiled_result, output_arrays, state_specs
from ._readings import classify_readings, interval_classes
from .core import FilterState

__all__ = [
    "LoopArguments",
    "CompiledSpec",
    "compiled_filter",
    "censoring_spec",
    "fading_spec",
    "protocol_spec",
    "saturation_spec",
    "channel_spec",
]


class LoopArguments(NamedTuple):
    """The arguments of :func:`~tobitkf.filters._compiled_loop.compiled_loop` in its order and by its names (its
    docstring says what each is), for a call from Python: give what the family uses, :meth:`filled` makes the rest
    as the loop reads an absent array (``cls`` (N, 0, m) int8, ``F`` (1, m, 0, n_x), ``r``/``lo``/``hi``
    (1, 1, m), ``par`` (1, m, 0), ``bu`` (N, 0, n), ``du`` (N, 0, m); outputs with a T axis of length 0: not
    written) and ``J`` = 0, ``npass`` = 1, ``noise_code`` = 0, ``joseph`` False. ``family`` is a kind
    (:func:`~tobitkf.filters._compiled_moments.kind`: the loop's version for that family alone). The compiled
    entries do the same in compiled code (:func:`~tobitkf.filters._compiled_entries.loop_call`)."""

    family: tuple[Any, ...]
    y: np.ndarray
    cls: np.ndarray | None = None
    A: np.ndarray | None = None
    Qd: np.ndarray | None = None
    H: np.ndarray | None = None
    F: np.ndarray | None = None
    r: np.ndarray | None = None
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    par: np.ndarray | None = None
    J: int = 0
    npass: int = 1
    noise_code: int = 0
    joseph: bool = False
    bu: np.ndarray | None = None
    du: np.ndarray | None = None
    x0: np.ndarray | None = None
    P0: np.ndarray | None = None
    means: np.ndarray | None = None
    covs: np.ndarray | None = None
    pmeans: np.ndarray | None = None
    pcovs: np.ndarray | None = None
    pu: np.ndarray | None = None
    ey: np.ndarray | None = None
    ll: np.ndarray | None = None
    comp: np.ndarray | None = None
    x_last: np.ndarray | None = None
    P_last: np.ndarray | None = None

    def filled(self) -> LoopArguments:
        """These arguments with every absent one made (see the class)."""
        assert self.A is not None and self.x0 is not None
        N, _, m = self.y.shape
        nx, n = self.x0.shape[1], self.A.shape[2]
        absent = {
            "cls": lambda: np.empty((N, 0, m), dtype=np.int8),
            "F": lambda: _empty((1, m, 0, nx)),
            "r": lambda: _empty((1, 1, m)),
            "lo": lambda: _empty((1, 1, m)),
            "hi": lambda: _empty((1, 1, m)),
            "par": lambda: _empty((1, m, 0)),
            "bu": lambda: _empty((N, 0, n)),
            "du": lambda: _empty((N, 0, m)),
            "means": lambda: _empty((N, 0, n)),
            "covs": lambda: _empty((N, 0, n, n)),
            "pmeans": lambda: _empty((N, 0, n)),
            "pcovs": lambda: _empty((N, 0, n, n)),
            "pu": lambda: _empty((N, 0, m)),
            "ey": lambda: _empty((N, 0, m)),
            "ll": lambda: _empty((N, 0)),
            "comp": lambda: _empty((N, 0, m, self.J)),
        }
        if not isinstance(self.family, tuple):
            raise TypeError(
                f"LoopArguments.family: expected a kind (_compiled_moments.kind(code)), got {self.family!r}"
            )
        made: dict[str, Any] = {k: make() for k, make in absent.items() if getattr(self, k) is None}
        return self._replace(**made)


@dataclass
class CompiledSpec:
    """What an assumed-density family gives :func:`~tobitkf.filters._compiled_loop.compiled_loop` (its module docstring); ``extras`` turns the loop's ``pu`` (N, T, m),
    ``ll`` (N, T) and ``comp`` (N, T, m, J) into the family's extras dict (batch shape restored)."""

    family: int | tuple[Any, ...]
    """The family's code, or its kind (a channel's own block, :func:`~tobitkf.filters._compiled_moments.block_kind`)."""
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


def _per_step(at: Any, k0: int, T: int, varying: bool, shape: tuple[int, ...], seq: Any = None) -> np.ndarray:
    """``at(k0 + i)`` for the T steps (one step when not ``varying``) as one (N', T or 1, *shape) array,
    N' the runs of the widest step (1: shared), for the compiled loop's run- and step-indexed matrices.
    ``seq``: the :class:`~tobitkf._validation.TimeSequence` behind ``at`` when ``at`` returns its matrices as
    they are (then an array is sliced at once instead of step by step)."""
    if seq is not None and seq.fn is None and len(seq.batch_shape) <= 1:
        arr = seq.array
        if seq.varying:
            i0 = k0 - seq.offset
            arr = arr[..., i0 : i0 + T, :, :] if len(shape) == 2 else arr[..., i0 : i0 + T, :]
        else:
            arr = arr[..., None, :, :] if len(shape) == 2 else arr[..., None, :]
        return _c(arr if seq.batch_shape else arr[None])
    mats = [np.asarray(at(k0 + i), dtype=float) for i in range(T if varying else 1)]
    Nr = max(M.shape[0] if M.ndim > len(shape) else 1 for M in mats)
    out = np.empty((Nr, len(mats)) + shape)
    for i, M in enumerate(mats):
        out[:, i] = M if M.ndim > len(shape) else M[None]
    return out


def _system_arrays(sys_, k0: int, T: int) -> tuple[np.ndarray, np.ndarray]:
    """The transitions ``A`` and noise covariances ``Qd`` (N', T', n, n) of steps k0 + 1 .. k0 + T: one of each
    for a time-invariant system, else per step (and per run for a system with run axes)."""
    n = sys_.n
    if sys_.time_invariant:
        return _c(sys_.transition(0))[None, None], _c(sys_.process_cov(0))[None, None]
    q_varying = sys_.Q.varying or (sys_.B is not None and sys_.B.varying)
    A = _per_step(sys_.transition, k0, T, sys_.A.varying, (n, n), sys_.A)
    Qd = _per_step(sys_.process_cov, k0, T, q_varying, (n, n), sys_.Q if sys_.B is None else None)
    return A, Qd


def _c(a: Any) -> np.ndarray:
    """``a`` as a C-contiguous, writable float64 array (a read-only one, e.g. cached limits, is copied: numba types
    read-only arrays apart, and each would compile the loop once more)."""
    return np.require(a, dtype=float, requirements=("C", "W"))


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
    options are not covered (a measurement matrix given per run). ``order="uncensored_first"``: two passes over
    the channels, the readings inside their limits in the first, the others in the second. Covers time-varying
    and per-run systems (rows per step, noise variances per run and step) and limits given per run
    (``step_data`` ``lower``/``upper`` (N, T, m))."""
    N, T, m = y2.shape
    sys_ = est.system
    if sys_.C.batch_shape and int(np.prod(sys_.C.batch_shape)) > 1:
        return None
    k0 = state.k
    H = _per_step(sys_.measurement, k0 + 1, T, sys_.C.varying, (m, est.n), sys_.C)[0]
    if est._r is not None and not sys_.R.batch_shape:
        r = _c(est._r)[None]
    else:
        Rs = _per_step(sys_.measurement_cov, k0 + 1, T, sys_.R.varying, (m, m), sys_.R)
        r = _c(_noise_variances(Rs, "R"))  # (runs or 1, steps, m)
    data = step_data or {}
    if data.get("lower") is not None:
        lo, hi = _c(data["lower"]), _c(data["upper"])
        lo3, hi3 = lo, hi
    else:
        lo, hi = est.censoring.all_limits(T, m, start=k0 + 1, check=False)
        lo3, hi3 = lo[None], hi[None]
    flags = data.get("censored")
    cls = None
    if flags is not None or "extras" in want:
        cls = classify_readings(y2, lo3, hi3)
        if flags is not None:  # a flagged reading inside its limits: an interval reading
            cls = interval_classes(cls, flags, lo3, hi3)
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
        _c(H),
        r,
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
    """The generic :class:`~tobitkf.AssumedDensityFilter`'s arrays for a channel with compiled moments
    (:mod:`tobitkf.channels.base`): its own block ``channel.compiled_block`` or one of the package's that
    ``channel.compiled_moments`` names (:func:`~tobitkf.filters._compiled_moments.channel_kind`), and
    ``channel.compiled_parameters(k, steps, m)``, the block's ``par`` (TP, m, K) for the steps k..k+steps-1
    (TP = 1: constant). The rows are C, the noise variances R's diagonal, no limits (every reading but a
    missing one goes to the block). None (the numpy path) for a channel without compiled moments or a
    time-varying R.

    Raises
    ------
    ValidationError
        Compiled moments that name no block function, or parameters of another shape.
    """
    from .._validation import ValidationError

    if est._r is None:
        return None
    family = channel_kind(est.channel)
    if family is None:
        return None
    N, T, m = y2.shape
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
    estimator's ``backend`` (:func:`~tobitkf.filters._backend.use_compiled`), builds its arrays with
    ``spec_of`` (one of the ``*_spec`` functions) and runs :func:`~tobitkf.filters._compiled_loop.compiled_loop`. A covariance that stops being
    finite also returns None, so that the numpy loop reruns the call and reports where it diverged."""
    what = f"the {est._name}"
    gap = None
    if est.covariance_update != "standard":
        gap = f"covariance_update={est.covariance_update!r} (the compiled path runs the standard form)"
    # a family whose spec takes time-varying and per-run systems (rows and noise per step and run) checks
    # only the inputs; the others need one system for every run and step
    varying_ok = spec_of is censoring_spec
    gap = gap or system_gap(est.system, u2, inputs=True, matrices=not varying_ok)
    spec = None
    if gap is None:
        spec = spec_of(est, y2, u2, state, want, batch, step_data)
        if spec is None:
            gap = "these options"
    if not use_compiled(getattr(est, "backend", "auto"), gap, what):
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
    A, Qd = _system_arrays(est.system, state.k, T)
    if (A.shape[0] > 1 or Qd.shape[0] > 1) and nx != n:  # pragma: no cover - no family has both
        return None
    r, lo, hi = (a if a.ndim == 3 else a[None] for a in (spec.r, spec.lo, spec.hi))  # (runs or 1, steps, m)
    F = spec.F if spec.F is not None else np.zeros((1, m, 0, nx))
    cls = spec.cls if spec.cls is not None else np.empty((N, 0, m), dtype=np.int8)
    # the censored family, one channel of up to 4 states, one system, no extras: the step vectorised over runs
    # a code, or a kind (whose length is its code)
    code, family = (spec.family, kind(spec.family)) if isinstance(spec.family, int) else (len(spec.family), spec.family)
    loop = censored_entry(
        _compiled_loop.compiled_loop, code, A, Qd, spec.H, F, r, lo, hi, x0, pu.shape[1] + ll.shape[1] > 0
    )
    args = LoopArguments(
        family, _c(y2), np.require(cls, dtype=np.int8, requirements=("C", "W")), A, Qd, _c(spec.H), _c(F), _c(r),
        _c(lo), _c(hi), _c(spec.par), spec.J, spec.npass, x0=x0, P0=P0, bu=spec.bu, du=spec.du, means=means,
        covs=covs, pmeans=pmeans, pcovs=pcovs, pu=pu, ll=ll, comp=comp if comp.shape[1] > 0 else None,
        x_last=x_last, P_last=P_last,
    )  # fmt: skip
    loop(*args.filled())
    if not np.isfinite(np.diagonal(P_last, axis1=-2, axis2=-1)).all():
        return None
    final = FilterState(k=state.k + T, batch_shape=batch, x=x_last, P=P_last, n=n, carry=state.carry)
    extras = spec.extras(pu, ll, comp) if ext else {}
    return compiled_result(want, batch, T, means, covs, pmeans, pcovs, extras, final)
