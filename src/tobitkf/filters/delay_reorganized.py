r"""Algorithm D of the delay family: the source's reorganized-innovation filter (Lemmas 1–3, Theorems 1–3).

:class:`ReorganizedInnovationLMMSE` / :func:`reorganized_lmmse`, with the source's errata LD-E3 to
LD-E7 corrected (docs/sources/li2018-delay.md), any prior, O(d²) per step. The model, the time
convention and the code names of every delay estimator: :mod:`tobitkf.filters.delay` (which also
holds the pieces the three algorithms share).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._validation import ValidationError
from ..models.delay import DelayFadingSystem, HistoryPrior
from . import delay as _shared  # _WHOLE_STEP_MAX_RUNS read at call time: one knob for C and D
from ._backend import BACKENDS, use_compiled
from .core import (
    FilterResult,
    FilterState,
    check_keywords,
    step_state,
)
from .delay import (
    _DECORRELATION,
    _ERRATA,
    _NO_LAYOUTS,
    _NOTHING,
    _REORG_DICTS,
    _RING_FIELDS,
    _cached_layout,
    _compiled_gap,
    _compiled_moment_args,
    _DelayEstimator,
    _flat_views,
    _moments_at,
    _packed_moment_args,
    _ring_layout,
    _ring_views,
    _solve_small,
    register_delay,
)
from .delay_augmented import AugmentedLMMSE, _aug_step, _augmented_matrices, _blk
from .delay_chain import ChainLMMSE

__all__ = [
    "ReorganizedInnovationLMMSE",
    "reorganized_lmmse",
]


# --------------------------------------------------------------------------- Algorithm D


class ReorganizedInnovationLMMSE(_DelayEstimator):
    """Algorithm D, the source's reorganized-innovation estimator (see :func:`reorganized_lmmse`).

    Online ``init()``/``step(state, y_t)``: the state's mean/cov are x̂(t|t), P(t|t); the recursions'
    gains, Ψ and the smoother outputs they need are carried in the state (pruned to the last 2d+2
    times). The steps before ``warmup`` run Algorithm A, as in :func:`reorganized_lmmse`. The
    reorganized recursions are the source's algorithm, kept as its faithful (corrected) reference:
    they are not a Gaussian update of one state, so only its delayed-filter update and predictor
    correspond to the shared core's (Algorithms C and A use it).

    Parameters
    ----------
    system : DelayFadingSystem
    prior : HistoryPrior
    decorrelation : {"optimal", "paper"}, default "optimal"
    warmup : int, optional
    reinsert_errata : iterable of {"E5", "E6", "E7"}
        The printed LD-E5, LD-E6, LD-E7; see :func:`reorganized_lmmse`.
    """

    _name = "ReorganizedInnovationLMMSE"

    def __init__(
        self,
        system: DelayFadingSystem,
        prior: HistoryPrior,
        *,
        decorrelation: str = "optimal",
        warmup: int | None = None,
        reinsert_errata: Any = (),
        backend: str = "auto",
    ):
        check_keywords(
            {"decorrelation": decorrelation, "backend": backend}, {"decorrelation": _DECORRELATION, "backend": BACKENDS}
        )
        errata = frozenset(reinsert_errata)
        bad = errata - set(_ERRATA)
        if bad:
            raise ValidationError(f"reinsert_errata: expected a subset of {_ERRATA}, got {sorted(bad)}")
        self._setup(system, prior)
        if not system.is_pure_delay:
            raise ValidationError("system: Algorithm D needs the pure-delay model (no extra_lags); use augmented_lmmse")
        self.decorrelation, self.errata, self.warmup_arg = decorrelation, errata, warmup
        self._t0(self.prior)
        self._HT = system.H.T
        self.backend = backend
        gap = _compiled_gap(system)
        # the compiled whole step (covariances and means) and its arguments after (ring, t); d = 0 is
        # Algorithm C (its chain's own step)
        self._whole = None
        if system.d and use_compiled(backend, gap, "the reorganized LMMSE's covariance step"):
            self._whole = self._compiled_step()
            self._compiled_cov, self._compiled_cov_args = self._compiled_cov_step()
        self._eps_back = tuple(range(1, system.d - 1))  # the whole step reads ε(t-k), k = 1..d-2
        self._lag_keys = (f"lag{system.d - 1}_mean", f"lag{system.d - 1}_cov")
        if system.d == 0:
            self._chain = ChainLMMSE(system, self.prior, decorrelation=decorrelation, backend=backend)
        # γ̄(s), read about 2d times per step: the law's one mean when it does not change with s
        self._g_const = None if system.fading.varying else system.gamma_mean(0)

    def _whole_takes(self, state, options):
        return (
            self._whole is not None
            and state.k + 1 >= state.carry["t0"]
            and state.x.shape[0] <= _shared._WHOLE_STEP_MAX_RUNS
        )

    def _compiled_cov_step(self):
        """The compiled covariance step (:func:`~tobitkf.filters._compiled_delay.reorg_cov_step`) and its
        constant arguments after ``(ring, t)``, for many runs (their means on numpy)."""
        from ._compiled_delay import reorg_cov_step

        sys_ = self.system
        W, layout = _ring_layout(sys_.d, self.n, self.m)
        offs = np.array([layout[k][0] for k in _RING_FIELDS], dtype=np.int64)
        args = (offs, sys_.d, W) + _compiled_moment_args(sys_, self.decorrelation)
        return reorg_cov_step, args + tuple(e in self.errata for e in ("E5", "E6", "E7"))

    def _compiled_step(self):
        """The compiled whole step (:func:`~tobitkf.filters._compiled_delay.reorg_step`: the covariance step
        :func:`~tobitkf.filters._compiled_delay.reorg_cov_step` and the means) and its packed constants
        ``(cb, ib)`` (:func:`_packed_moment_args` with d, W, the errata flags and the ring's offsets)."""
        from ._compiled_delay import reorg_step

        sys_ = self.system
        W, layout = _ring_layout(sys_.d, self.n, self.m)
        offs = tuple(int(layout[k][0]) for k in _RING_FIELDS)
        flags = tuple(int(e in self.errata) for e in ("E5", "E6", "E7"))
        return reorg_step, _packed_moment_args(sys_, self.decorrelation, sys_.d, W, *flags, *offs)

    def _gbar(self, s: int) -> float:
        """γ̄(s) (one call, not two, when the fading law does not change with s)."""
        return self._g_const if self._g_const is not None else self.system.gamma_mean(s)

    def _warmup_matrices(self):
        """The augmented matrices of the warm-up steps (Algorithm A, W = d), formed on first use."""
        mats = self.__dict__.get("_aug_mats")
        if mats is None:
            mats = self._aug_mats = _augmented_matrices(self.system, self.system.d)
        return mats

    def _t0(self, prior: HistoryPrior) -> int:
        d = self.system.d
        zero_init = prior.is_uncorrelated
        t0 = (0 if zero_init else 2 * d + 1) if self.warmup_arg is None else self.warmup_arg
        lowest = 0 if zero_init else 2 * d + 1
        if isinstance(t0, bool) or not isinstance(t0, (int, np.integer)) or t0 < lowest:
            raise ValidationError(
                f"warmup: expected an integer >= {lowest} "
                f"({'uncorrelated' if zero_init else 'correlated'} prior; 2d+1 = {2 * d + 1}), "
                f"got {self.warmup_arg!r}"
            )
        return int(t0)

    def _initial(self, N, prior, P0, batch):
        sys_ = self.system
        d, n = sys_.d, self.n
        if d == 0:
            x, P, carry = self._chain._initial(N, prior, P0, batch)
            return x, P, {"chain": carry}
        t0 = self._t0(prior)
        W, layout = self._layout
        ring = np.zeros(layout["size"][0])
        R = _ring_views(ring, layout)
        xf, xsm = {}, {}
        # Exact initialization from an uncorrelated prior: every Ψ and every gain K(a|s), s ≠ a+d, is zero
        # (the ring's zeros); the elements x(-k) keep their prior until measured.
        for k in range(d + 1):
            xf[-k] = np.broadcast_to(prior.block_mean(k), (N, n)).copy()  # x̂(-k|-k) = prior (no data before t = 0)
            m0 = prior.block_mean(k)
            R["pf"][-k % W] = prior.block_cov(k)
            R["lam"][-k % W] = prior.block_cov(k) + np.outer(m0, m0)
        xsm[-1] = xf[-d]  # x̂(-d|-1)
        R["psm"][-1 % W] = R["pf"][-d % W]
        R["pp"][0] = R["pf"][0]
        carry = {"xf": xf, "xsm": xsm, "xm": {}, "xp": {0: xf[0]}, "eps": {}, "ring": ring, "t0": t0}
        if t0 > 0:
            aug = AugmentedLMMSE(sys_, prior, window=d)
            Xa, Pa, ca = aug._initial(N, prior, None, batch)
            carry["aug"] = (Xa, Pa, ca["LamX"])
        return xf[0], R["pf"][0][None].copy(), carry

    @property
    def _layout(self):
        """(W, field offsets) of the ring buffer (:func:`_ring_layout`), formed once."""
        lay = self.__dict__.get("_ring_lay")
        if lay is None:
            lay = self._ring_lay = _ring_layout(self.system.d, self.n, self.m)
        return lay

    def _state_dim(self) -> int:
        return self.n

    def _step_arrays(self, t, x, P, S, carry, y, u, options=None):
        sys_ = self.system
        d = sys_.d
        if d == 0:
            xn, Pn, Sn, cn, xp, Pp, ex = self._chain._step_arrays(t, x, P, S, carry["chain"], y, u, {"lags": (0,)})
            return xn, Pn, Sn, {"chain": cn}, xp, Pp, ex
        # a new carry: the ring buffer is copied once (the caller's state stays unchanged), the per-time
        # dicts of the (batched) means are copied and grown
        c = dict(carry)
        for key in _REORG_DICTS:
            c[key] = dict(carry[key])
        xf, xsm, xm, xp, eps = c["xf"], c["xsm"], c["xm"], c["xp"], c["eps"]
        W, layout = self._layout
        ring = c["ring"] = carry["ring"].copy()
        if t >= c["t0"] and self._whole is not None and y.shape[0] <= _shared._WHOLE_STEP_MAX_RUNS:
            return self._whole_step(t, y, c, xf, xsm, xm, xp, eps, ring)
        R = _ring_views(ring, layout)
        xpred = xp[t]
        if t < c["t0"]:
            self._warmup_step(t, y, c, R)
        elif self._whole is not None:  # many runs: the compiled covariance step, the numpy means
            self._compiled_cov(ring, t, *self._compiled_cov_args)
            self._means_step(t, y, xf, xsm, xm, xp, eps, R)
        else:
            self._cov_step(t, R)
            self._means_step(t, y, xf, xsm, xm, xp, eps, R)
        s1 = (t + 1) % W
        st = t % W
        extras = {
            "measured_mean": xm[t],
            "measured_cov": R["pmeas"][st][None],
            "next_mean": xp[t + 1],
            "next_cov": R["pp"][s1][None],
            "innovation": eps[t],
            "innovation_cov": R["qe"][st][None],
            f"lag{d - 1}_mean": xsm[t],
            f"lag{d - 1}_cov": R["psm"][st][None],
            "_lam": R["lam"][st][None],
        }
        c["lam"] = {t + 1: R["lam"][s1]}  # Λ(t+1), read by the result assembly (_group_extras)
        # drop what is no longer needed (the recursions read back at most 2d+1 steps): the ring's Ψ_i(old)
        # and K(a|old)H are zeroed (a vanishing Ψ or gain reads as zero), the means of time old - 1 go
        old = t - 2 * d - 2
        R["psi"][old % W] = 0.0
        R["kh"][old % W] = 0.0
        _drop_means(old - 1, xf, xsm, xm, xp, eps)
        return xf[t], R["pf"][st][None], None, c, xpred, R["pp"][st][None], extras

    def _whole_step(self, t, y, c, xf, xsm, xm, xp, eps, ring):
        """:meth:`_step_arrays` at t >= warmup as one compiled call (:func:`~tobitkf.filters._compiled_delay.reorg_step`:
        the covariance step, the means and the ring's pruning) on the step's own copies of the carry."""
        xpred = xp[t]
        buf, lay = self._whole_compiled_step(t, y, xf, xsm, xp, eps, ring)
        x, P, Pprior, extras = self._whole_assemble(t, buf, lay, c, xf, xsm, xm, xp, eps)
        return x, P, None, c, xpred, Pprior, extras

    def _whole_compiled_step(self, t, y, xf, xsm, xp, eps, ring):
        """The compiled whole step's flat output (the trace of P(t|t) last) and the layout of its arrays."""
        d, n, m = self.system.d, self.n, self.m
        step, args = self._whole
        N = y.shape[0]
        lay = self.__dict__.get("_flat_layouts", _NO_LAYOUTS).get(N) or _cached_layout(
            self, N, lambda: ((4, N, n), (N, m), (7, 1, n, n), (1, m, m))
        )
        size, lay = lay
        # C-ordered arguments (the warm-up's means are column blocks of Algorithm A's, the loop's readings
        # columns of the record): one compiled signature, and a tuple of one array type
        # (the warm-up stores its means C-ordered too)
        back = self._eps_back  # ε(t-1), ..., ε(t-d+2)
        prev = tuple([eps[t - k] if t >= k else _NOTHING for k in back]) if back else (_NOTHING,)
        xf_a = xf[t - d + 1] if d > 1 else xp[t]  # for d = 1 the compiled step's own x̂(t|t)
        buf = np.empty(size)
        step(ring, t, *args, np.ascontiguousarray(y), xp[t], xsm[t - 1], xf_a, prev, buf)  # prev: ε(t-1)..ε(t-d+2)
        return buf, lay

    def _whole_assemble(self, t, buf, lay, c, xf, xsm, xm, xp, eps):
        """The means of the compiled step's output into the step's per-time dicts (those of time t-2d-3 dropped: the
        compiled step zeroed the ring's Ψ, K H of t-2d-2), Λ(t+1) into ``c``; x̂(t|t), P(t|t), P(t|t-1) and the
        extras."""
        M, e_t, C, Qe = _flat_views(buf, lay)
        extras = self._store_step(t, c, xf, xsm, xm, xp, eps, M, e_t, C, Qe)
        return M[0], C[0], C[1], extras

    def _store_step(self, t, c, xf, xsm, xm, xp, eps, M, e_t, C, Qe):
        """The compiled step's outputs of step t (views of its buffer) into the per-time dicts of the means (those of
        time t-2d-3 dropped: the compiled step zeroed the ring's Ψ, K H of t-2d-2) and Λ(t+1) into ``c``; returns the
        step's extras."""
        m0, m1, m2, m3 = M[0], M[1], M[2], M[3]  # (indexing: a third of the cost of iterating)
        xf[t], xsm[t], xm[t], xp[t + 1], eps[t] = m0, m1, m2, m3, e_t
        lag_mean, lag_cov = self._lag_keys
        extras = {
            "measured_mean": m2,
            "measured_cov": C[2],
            "next_mean": m3,
            "next_cov": C[3],
            "innovation": e_t,
            "innovation_cov": Qe,
            lag_mean: m1,
            lag_cov: C[4],
            "_lam": C[5],
        }
        c["lam"] = {t + 1: C[6, 0]}  # Λ(t+1), read by the result assembly (_group_extras)
        old = t - 2 * self.system.d - 3
        xf.pop(old, None), xsm.pop(old, None), xm.pop(old, None), xp.pop(old, None), eps.pop(old, None)
        return extras

    def _whole_online(self, state, y):
        """:meth:`_step_arrays`' compiled branch as the online step: the new carry (the ring copied once, the
        per-time dicts of the means copied and grown), the compiled step, and the checked trace of P(t|t)."""
        t, carry = state.k + 1, state.carry
        c = dict(carry)
        xf = c["xf"] = carry["xf"].copy()
        xsm = c["xsm"] = carry["xsm"].copy()
        xm = c["xm"] = carry["xm"].copy()
        xp = c["xp"] = carry["xp"].copy()
        eps = c["eps"] = carry["eps"].copy()
        ring = c["ring"] = carry["ring"].copy()
        # :meth:`_whole_compiled_step` and the views of :meth:`_whole_assemble` written out (their calls and the list of
        # views are a tenth of this step; the test of the reorganized compiled step's loop holds the two forms equal)
        N = y.shape[0]
        d = self.system.d
        lay = self.__dict__.get("_flat_layouts", _NO_LAYOUTS).get(N)
        if lay is None:
            return self._whole_online_first(state, y)
        size, ((_, z0, s0), (o1, z1, s1), (o2, z2, s2), (o3, z3, s3)) = lay
        back = self._eps_back
        prev = tuple([eps[t - k] if t >= k else _NOTHING for k in back]) if back else (_NOTHING,)
        buf = np.empty(size)
        step, args = self._whole
        step(ring, t, *args, np.ascontiguousarray(y), xp[t], xsm[t - 1], xf[t - d + 1] if d > 1 else xp[t], prev, buf)
        if not math.isfinite(buf[-1]):
            return None
        M, e_t = buf[:z0].reshape(s0), buf[o1 : o1 + z1].reshape(s1)
        C, Qe = buf[o2 : o2 + z2].reshape(s2), buf[o3 : o3 + z3].reshape(s3)
        extras = self._store_step(t, c, xf, xsm, xm, xp, eps, M, e_t, C, Qe)
        return step_state(t, state.batch_shape, M[0], C[0], self.n, None, c, extras)

    def _whole_online_first(self, state, y):
        """:meth:`_whole_online` by the two methods it writes out, at the first step for a number of runs (which
        forms the layout of the compiled step's output)."""
        t, carry = state.k + 1, state.carry
        c = dict(carry)
        for key in _REORG_DICTS:
            c[key] = dict(carry[key])
        ring = c["ring"] = carry["ring"].copy()
        xf, xsm, xm, xp, eps = c["xf"], c["xsm"], c["xm"], c["xp"], c["eps"]
        buf, lay = self._whole_compiled_step(t, y, xf, xsm, xp, eps, ring)
        if not math.isfinite(buf[-1]):
            return None
        x, P, _, extras = self._whole_assemble(t, buf, lay, c, xf, xsm, xm, xp, eps)
        return step_state(t, state.batch_shape, x, P, self.n, None, c, extras)

    def _warmup_step(self, t, y, c, R):
        """A step t < warmup by Algorithm A, from which every stored Ψ, gain and covariance is read (LD-05)."""
        sys_ = self.system
        d, n = sys_.d, self.n
        W = self._layout[0]
        st = t % W
        _, dec, R["lam"][(t + 1) % W] = _moments_at(sys_, t, R["lam"][(t - d) % W], self.decorrelation)
        R["j"][st], R["abar"][st], R["sig"][st] = dec
        Xa, Pa, LamX = c["aug"]
        Xf, PfA, Xp_, PpA, KA, e_t, Q_t, LamX, _, _ = _aug_step(sys_, self._warmup_matrices(), Xa, Pa, LamX, y, t)
        Pprior = Pa[0]
        PfA, PpA, KA, Q_t = PfA[0], PpA[0], KA[0], Q_t[0]
        # the means C-ordered (copies of the column blocks), as the compiled whole step reads them
        c_ = np.ascontiguousarray
        c["xf"][t], R["pf"][st] = c_(_blk(Xf, 0, None, n)), _blk(PfA, 0, 0, n)
        c["xsm"][t], R["psm"][st] = c_(_blk(Xf, d - 1, None, n)), _blk(PfA, d - 1, d - 1, n)
        c["xm"][t], R["pmeas"][st] = c_(_blk(Xf, d, None, n)), _blk(PfA, d, d, n)
        c["xp"][t + 1], R["pp"][(t + 1) % W] = c_(_blk(Xp_, 0, None, n)), _blk(PpA, 0, 0, n)
        R["pm"][st] = _blk(Pprior, d, d, n)  # P(t-d|t-1)
        for k in range(d + 1):
            R["kh"][st, k] = _blk(KA.T, k, None, n).T.dot(sys_.H)  # K(t-k|t) H: K(t-k|t) the rows of block k
        c["eps"][t], R["qe"][st] = c_(e_t), Q_t
        # Ψ_i(t') = block (d, d-i) of P(j|j-1) with j = t'-i+1
        for j, Pj in ((t, Pprior), (t + 1, PpA)):
            for i in range(1, d + 1):
                R["psi"][(j + i - 1) % W, i] = _blk(Pj, d, d - i, n)
        c["aug"] = (Xp_, PpA[None], LamX)
        if t + 1 == c["t0"]:
            del c["aug"]

    def _cov_step(self, t, R):
        """The data-independent part of a reorganized step t >= warmup on the ring (numpy reference of
        :func:`tobitkf.filters._compiled_delay.reorg_cov_step`): (a)–(f) of :func:`reorganized_lmmse`
        without the means, and Λ(t+1) (LD-E2); the gains the means read go to the ring's ``kf``, ``ks``,
        ``ke``."""
        sys_ = self.system
        d = sys_.d
        W = self._layout[0]
        H, HT, A = sys_.H, self._HT, sys_.A
        gbar = self._gbar
        psi, kh = R["psi"], R["kh"]
        st = t % W
        # what time t needs of Λ(t-d), each formed once: R(t) of (15), J(t), Ā(t), Σ(t) of (50)-(52), Λ(t+1) (LD-E2)
        R_t, dec, R["lam"][(t + 1) % W] = _moments_at(sys_, t, R["lam"][(t - d) % W], self.decorrelation)
        R["j"][st], R["abar"][st], R["sig"][st] = dec
        errata = self.errata
        # ndarray.dot on these 2-D blocks: bitwise the products of @ (checked), at a fraction of its call overhead
        gb = gbar(t)
        # (a) innovation covariance (15); P(t-d|t-1) is last step's smoother covariance P(t-d+1|t) shifted
        Pmp = R["psm"][(t - 1) % W]
        R["pm"][st] = Pmp
        Q = gb * gb * (H.dot(Pmp).dot(HT)) + R_t  # R(t) = Q_v + σ² H Λ(t-d) H^T
        if Q.shape[0] > 1:  # a 1 x 1 Q_ε is its own symmetric part (0.5 (q + q) = q exactly)
            Q = 0.5 * (Q + Q.T)
        R["qe"][st] = Q
        HtQi = _solve_small(Q, H).T  # H^T Q_ε(t)^{-1}
        # (b) filter, (35)-(38) shifted by one
        Psd = psi[(t + d - 1) % W, d]
        Kf = R["kf"][...] = gb * (Psd.T.dot(HtQi))
        kh[st, 0] = KfH = Kf.dot(H)
        Pq = R["pp"][st] - gb * (KfH.dot(Psd))
        R["pf"][st] = 0.5 * (Pq + Pq.T)
        # (c) Ψ_i(t), i = d-1..1, corrected (58)
        # Before t = d (zero initialization only) the terms below are all zero: Ψ and the
        # gains of not-yet-measured elements vanish; times < 0 carry no measurement (γ̄ = 0 there).
        if t - d >= 0:
            AbarT_td = R["abar"][(t - d) % W].T
            g_md = gbar(t - d)
        else:
            AbarT_td, g_md = A.T, 0.0
        g_md1 = gbar(t - d + 1) if t - d + 1 >= 0 else 0.0
        e5, e6, e7 = "E5" in errata, "E6" in errata, "E7" in errata
        psi_dt = psi[st, d]
        psi_d = psi_dt.T if e6 else psi_dt  # source prints Ψ_d(t)^T (LD-E6)
        Pm_td = R["pm"][(t - d) % W]  # zero before t = d (no reading of x(t-2d) yet)
        for i in range(d - 1, 0, -1):
            a = t - d - i + 1
            a5 = a - 1 if e5 else a  # source (30)/(58) print K(t-d-i|t-d) (LD-E5)
            # K(a|s)H sits at offset s - a of time s
            val = (psi[(t - i) % W, d - i + 1].T - g_md * kh[(t - d) % W, t - d - a5].dot(Pm_td)).dot(AbarT_td)
            val = val - g_md1 * kh[(t - d + 1) % W, t - d + 1 - a].dot(psi_d)
            top = d - 1 - i if e7 else d - 2 - i  # source's limit d-1-i double counts (LD-E7)
            for j in range(0, top + 1):
                s = t - i - j
                g_s = gbar(s) if s >= 0 else 0.0
                val = val - g_s * kh[s % W, s - a].dot(psi[st, i + j + 1])
            psi[st, i] = val
        # (d) fixed-lag d-1 smoother (55)-(57), a = t-d+1
        a = t - d + 1
        Ps_ = R["pf"][a % W]
        for i in range(1, d):
            s = t - i + 1
            if s < 0:
                continue
            g_s = gbar(s)
            psi_i = psi[st, i]
            Ks = R["ks"][i - 1] = g_s * (psi_i.T.dot(_solve_small(R["qe"][s % W], H).T))
            kh[s % W, s - a] = KsH = Ks.dot(H)
            Ps_ = Ps_ - g_s * (KsH.dot(psi_i))
        R["psm"][st] = 0.5 * (Ps_ + Ps_.T)
        # (e) delayed filter and predictor (50)-(52)
        Ke = R["ke"][...] = gb * (Pmp.dot(HtQi))
        kh[st, d] = KeH = Ke.dot(H)
        Pq = Pmp - gb * (KeH.dot(Pmp))
        Pmeas = R["pmeas"][st] = 0.5 * (Pq + Pq.T)
        Abar = R["abar"][st]
        Pq = Abar.dot(Pmeas).dot(Abar.T) + R["sig"][st]
        R["pp"][(t + 1) % W] = 0.5 * (Pq + Pq.T)
        # (f) corrected (39)
        psi1 = psi[st, 1]
        psi[(t + d) % W, d] = Abar.dot(psi1 - gb * KeH.dot(psi1)).T

    def _means_step(self, t, y, xf, xsm, xm, xp, eps, R):
        """The means of a reorganized step t >= warmup from the gains of :meth:`_cov_step`: ε(t) (14), the
        filter (35), the fixed-lag smoother (55), the delayed filter (51) and the predictor (50)."""
        d = self.system.d
        W = self._layout[0]
        gb = self._gbar(t)
        xmp = xsm[t - 1]  # x̂(t-d|t-1): last step's smoother output x̂(t-d+1|t) shifted
        e_t = eps[t] = y - gb * (xmp.dot(self._HT))
        xf[t] = xp[t] + e_t.dot(R["kf"].T)
        xs_ = xf[t - d + 1]
        for i in range(1, d):
            s = t - i + 1
            if s >= 0:
                xs_ = xs_ + eps[s].dot(R["ks"][i - 1].T)
        xsm[t] = xs_
        xm[t] = xmp + e_t.dot(R["ke"].T)
        st = t % W
        xp[t + 1] = xm[t].dot(R["abar"][st].T) + y.dot(R["j"][st].T)

    def filter(  # type: ignore[override]  # the delay family: a prior of its own
        self, y: Any, *, prior: Any = None, outputs: Any = "all", state: FilterState | None = None
    ) -> FilterResult:
        """Run Algorithm D over ``y`` (..., T, m); see :func:`reorganized_lmmse`."""
        if self.system.d == 0:
            res = self._chain.filter(y, lags=(0,), prior=prior, outputs=outputs, state=state)
            return res
        res = self._run_delay(y, prior, state, outputs, {})
        res.extras["warmup"] = int(res.final.carry["t0"])
        return res


def _drop_means(j: int, *dicts: dict) -> None:
    """Algorithm D's means of time j, no longer read, out of the step's own copies of the per-time dicts."""
    for dct in dicts:
        dct.pop(j, None)


def reorganized_lmmse(
    system: DelayFadingSystem,
    prior: HistoryPrior,
    y: Any,
    *,
    decorrelation: str = "optimal",
    warmup: int | None = None,
    reinsert_errata: Any = (),
) -> FilterResult:
    r"""Algorithm D: the source's reorganized-innovation estimator (Theorems 1–3), LD-E3 to LD-E7 corrected.

    Streaming order at time t (Ψ_i(t) := Φ_{t-i}(t-d-i+1, t-d+1), i = 1..d):

    (a) ε(t), Q_ε(t) from x̂(t-d|t-1) (14), (15);
    (b) filter (35)–(38): K(t|t) = γ̄ Ψ_d(t+d-1)^T H^T Q_ε^{-1}, P(t|t) = P(t|t-1) - γ̄ K H Ψ_d(t+d-1);
    (c) Ψ_i(t), i = d-1..1, by the corrected (58):

    .. math::

        \Psi_i(t) = [\Psi_{d-i+1}(t-i)^T - \bar\gamma K(a|t-d)HP(t-2d|t-d-1)]\bar A(t-d)^T
          - \bar\gamma K(a|t-d+1)H\Psi_d(t) - \sum_{j=0}^{d-2-i}\bar\gamma K(a|t-i-j)H\Psi_{i+j+1}(t),
          \quad a = t-d-i+1;

    (d) fixed-lag-(d-1) smoother (55)–(57) for a = t-d+1;
    (e) K(t-d|t) (51), x̂(t-d|t), predictor (50), (52) with Ā(t), J(t), Σ(t);
    (f) Ψ_d(t+d) = {Ā(t)[Ψ_1(t) - γ̄ K(t-d|t) H Ψ_1(t)]}^T (39);
    (g) Λ(t+1) by the corrected recursion (LD-E2).

    Initialization (the source's list is garbled, docs/sources LD-05): with a prior uncorrelated
    across lags, D starts at t = 0 with every Ψ and every gain K(a|s), s ≠ a+d, equal to zero
    (exact). Otherwise the steps t < ``warmup`` (default 2d+1, the source's "ε(i) = 0,
    i = 1..2d+1" range) are computed by Algorithm A, from which every stored Ψ, gain and
    covariance is read (LD-05). For d = 0 this is Algorithm C.

    Parameters
    ----------
    system, prior, y
        As :func:`augmented_lmmse` (pure-delay model, any joint prior).
    decorrelation : {"optimal", "paper"}
        J(t) corrected (LD-E3) or the source's constant J = ΓS Q_v^{-1} (everywhere Ā appears).
    warmup : int, optional
        First step done by the reorganized recursions; >= 2d+1 for a correlated prior
        (default 2d+1), >= 0 for an uncorrelated one (default 0). The steps before it are
        exact (Algorithm A) in both ``decorrelation`` modes.
    reinsert_errata : iterable of {"E5", "E6", "E7"}
        For regression tests only: put back the source's printed (30)/(58): ``"E5"`` (LD-E5) uses
        K(t-d-i|t-d) for K(t-d-i+1|t-d), ``"E6"`` (LD-E6) the transposed Ψ_d(t)^T, ``"E7"`` (LD-E7) the upper
        summation limit d-1-i (double counts the update at t-d+1). Each breaks optimality.

    Returns
    -------
    FilterResult
        ``lagged[d-1]`` is Theorem 3's smoother x̂(t-d+1|t) (d >= 1).

    Raises
    ------
    ValidationError
        Extra lags, an unknown option or erratum, ``warmup`` too small for a correlated prior.

    Notes
    -----
    Deviations from the source (each a correction of the source: LD-E3 to LD-E7): γ̄, σ² indexed by the
    measurement's own time (LD-E4); Ψ_d(t) untransposed (LD-E6); K(t-d-i+1|t-d) (LD-E5); summation limit
    d-2-i (LD-E7); J(t) corrected (LD-E3) unless ``decorrelation="paper"``; streaming order (a)–(g) (LD-06).
    The cost is O(d²) per step, not independent of d as the source claims.
    """
    est = ReorganizedInnovationLMMSE(
        system, prior, decorrelation=decorrelation, warmup=warmup, reinsert_errata=reinsert_errata
    )
    return est.filter(y)


register_delay(
    ReorganizedInnovationLMMSE,
    "the source's reorganized-innovation estimator (Li, Li & Wang 2018)",
    {"decorrelation": _DECORRELATION, "warmup": int, "backend": BACKENDS},
)
