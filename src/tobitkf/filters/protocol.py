r"""Protocol-based Tobit Kalman filter with integral measurements and sensor failures (PBTKF-IMSF).

Source: Geng, Wang, Zou, Mousavi, Cheng, "Protocol-Based Tobit Kalman Filter under
Integral Measurements and Probabilistic Sensor Failures", (9)–(30), Theorems 1–5, Table I and Sec. IV;
our deviations: docs/sources/geng-protocol.md. Channel:
:class:`tobitkf.channels.protocol.ProtocolChannel`.

Model (augmented form (9)–(10)), :math:`\xi_k = [x_k^T\; x_{k-1}^T \cdots x_{k-\ell}^T]^T`:

.. math::

    \xi_{k+1} &= \mathcal A_k \xi_k + \mathcal B\omega_k, \qquad
    y_k = \gamma_k\big(\Lambda_{h,k}\mathcal C_{h,k}\xi_k + v_{h,k}\big) + (1-\gamma_k)\tau, \\
    \mathcal C_{h,k} &= \mathbf 1_{\ell+1}^T\otimes C_{h,k},\qquad h = \bar h_k = \mathrm{mod}(k-1,p)+1,
    \qquad \mathbf H_k = \bar\Lambda_{h}\mathcal C_{h,k}

One step (Table I order; :math:`\gamma_k = \mathbb 1[y_k > \tau]` is known to the filter):

.. math::

    \hat\xi^-_k &= \mathcal A_{k-1}\hat\xi_{k-1}, \qquad
    P^-_k = \mathcal A_{k-1}P_{k-1}\mathcal A_{k-1}^T + \mathcal BQ_{k-1}\mathcal B^T   &(17)\text{–}(18)\\
    \bar\vartheta_k &= (\tau - \mathbf H_k\hat\xi^-_k)/\sqrt{\mathcal R_k}, \quad
    \lambda_k = \frac{\phi(\bar\vartheta_k)}{1-\Phi(\bar\vartheta_k)}, \quad
    \varphi_k = \lambda_k(\lambda_k - \bar\vartheta_k)   &(13)\text{–}(16)\\
    \hat y^-_k &= \gamma_k(\mathbf H_k\hat\xi^-_k + \sqrt{\mathcal R_k}\lambda_k) + (1-\gamma_k)\tau   &(21)\\
    P_{\tilde\xi\tilde y} &= \gamma_kP^-_k\mathbf H_k^T, \quad
    P_{\tilde y} = \gamma_k(\mathbf H_kP^-_k\mathbf H_k^T + F_k) + \mathcal R_k(1-\varphi_k)   &(23)\text{–}(24)\\
    K_k &= P_{\tilde\xi\tilde y}P_{\tilde y}^{-1}, \quad \hat\xi_k = \hat\xi^-_k + K_k(y_k - \hat y^-_k), \quad
    P_k = P^-_k - K_kP_{\tilde\xi\tilde y}^T   &(19), (20), (22)\\
    \hat x_k &= \Pi\hat\xi_k, \quad P_{\tilde x_k} = \Pi P_k\Pi^T   &(25)

A censored step (:math:`\gamma_k = 0`) gives :math:`K_k = 0` and an innovation
:math:`\tau - \tau = 0`; the code returns :math:`\hat\xi^-_k, P^-_k` unchanged, bit for bit.

The failure term :math:`F_k` of (24) (``failure_term``, docs/sources GP-01):

========================  ==============================================================
``"variance"`` (default)  :math:`\check\Lambda_h\,\mathcal C_hP^-_k\mathcal C_h^T`
``"literal"``             :math:`(\bar\Lambda_h^2+\check\Lambda_h)\,\mathcal C_hP^-_k\mathcal C_h^T`
``"second_moment"``       :math:`\check\Lambda_h\,\mathcal C_h(P^-_k+\hat\xi^-_k\hat\xi^{-T}_k)\mathcal C_h^T`
``"lmmse_unconditional"`` :math:`\check\Lambda_h\,\mathcal C_h\mathfrak X_k\mathcal C_h^T`, :math:`\mathfrak X_k = E[\xi_k\xi_k^T]`
========================  ==============================================================

In the terms of the shared core (:mod:`tobitkf.filters.core`): the state is the augmented
:math:`\xi_k`, the transition the block shift of (17)–(18), and the measurement prediction is
:math:`\hat y^-_k` of the uncensored branch of (21) with :math:`H_0 = \mathbf H_k`, the noise
:math:`F_k + \mathcal R_k(1-\varphi_k)` of (24) and the channel taking part only when
:math:`\gamma_k = 1` (a censored reading leaves the prediction unchanged, bit for bit). The shared
update in Joseph form is App. D (44); ``"square_root"`` (not in the source) is available too.

Time convention: :math:`x_0 \sim N(\bar x_0, P_0)` with the pre-history
:math:`x_{-1..-\ell}` independent with the same law (docs/sources GP-05); no measurement at k = 0;
``y`` index k-1 holds :math:`y_k`; output index k-1 holds :math:`\hat x_k` (posterior) and
``pred_mean`` :math:`\hat x^-_k`.

Readings: ``y`` is ``(..., T, 1)`` like every estimator's (one scalar per step, the scheduled
sensor's); ``uncensored`` (the detection device's :math:`\gamma_k`, default ``y > threshold``) is laid
out like ``y``.

Code names -> paper: ``window`` ℓ, ``threshold`` τ, ``uncensored`` γ_k,
``p_uncensored`` :math:`1-\Phi(\bar\vartheta_k)` (the diagnostic (8), GP-06), ``theta_bar``
:math:`\bar\vartheta_k`, ``inverse_mills`` λ, ``trunc_var_factor`` φ, ``scheduled`` :math:`\bar h_k`,
``aug_*`` the ξ-space quantities, ``failure_mean`` :math:`\bar\Lambda`, ``failure_variance``
:math:`\check\Lambda`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._validation import (
    ShapeError,
    ValidationError,
    as_float_array,
    check_option,
    check_psd,
)
from ..channels.protocol import NO_FAILURE, ProtocolChannel
from ..models.linear import LinearSystem
from ._backend import BACKENDS, compiled_module, system_gap, use_compiled
from ._online_check import check_step
from ._outputs import compiled_result, loop_array, loop_input, output_arrays, state_specs
from .core import (
    FilterResult,
    FilterState,
    Transition,
    check_keywords,
    is_trusted,
    mark_trusted,
    step_state,
    symmetrize,
)
from .kalman import LinearGaussianFamily, _finite_or_none
from .protocol_model import (
    FAILURE_CODES,
    FAILURE_TERMS,
    PREHISTORY_PRIORS,
    _check_parts,
    _initial,
    _prediction,
    _protocol_info,
    _sensor_stats,
    augmented_transition,
    noise_input,
    stacked_measurement,
)
from .registry import family_entry, register

__all__ = [
    "ProtocolTobitKalmanFilter",
    "protocol_tobit_kalman_filter",
    "baseline_channel",
]

_OPTIONS = {
    "failure_term": FAILURE_TERMS,
    "prehistory_prior": PREHISTORY_PRIORS,
    "covariance_update": ("joseph", "standard", "square_root"),
}


def _check_options(failure_term, prehistory_prior, covariance_update):
    check_keywords(
        {"failure_term": failure_term, "prehistory_prior": prehistory_prior, "covariance_update": covariance_update},
        _OPTIONS,
    )
    return prehistory_prior


class ProtocolTobitKalmanFilter(LinearGaussianFamily):
    r"""PBTKF-IMSF: Tobit Kalman filter under Round-Robin scheduling, integral measurements
    and probabilistic sensor failures (Geng et al., Theorems 1–2, Table I).

    Parameters
    ----------
    system : LinearSystem
        Plant; ``C`` has one row per sensor, ``R`` is diagonal.
    channel : ProtocolChannel
        The channel the filter assumes.
    failure_term : {"variance", "literal", "second_moment", "lmmse_unconditional"}, default "variance"
    prehistory_prior : {"x0", "zero_mean"}, default "x0"
        The filter's prior of the pre-history :math:`x_{-1..-\ell}`: independent
        :math:`N(\bar x_0, P_0)` (``"x0"``) or :math:`N(0, P_0)` (``"zero_mean"``). (The channel's
        ``prehistory`` says how the *simulator* draws them.)
    covariance_update : {"joseph", "standard", "square_root"}, default "joseph"
        Joseph form (App. D (44), the source's), (20), or the QR array form (not in the source).
    P0_aug : array_like, optional
        :math:`M_0`.
    backend : {"auto", "numpy", "numba"}, default "auto"
        ``filter`` runs the one compiled time loop of the Gaussian-update families
        (:mod:`tobitkf.filters._compiled_loop`, its protocol TKF code; equal to the numpy path to rounding) where it covers the case (a time-invariant system, the standard or Joseph form,
        every failure term, ``keep_augmented=False``) and numba imports (``"auto"``), insists on it
        (``"numba"``), or runs the numpy reference path (``"numpy"``). The online ``step`` runs the same loop
        for one reading in those cases without an input or ``failure_term="lmmse_unconditional"``. Lost readings
        (NaN) take the loop too. Elsewhere (the other steps, the cases the loop does not cover) ``"auto"`` and
        ``"numba"`` run the shared predict and update compiled (:mod:`tobitkf.filters._compiled_step`). Both
        paths take the moments of (13)-(16), (21), (23)-(24) from the same compiled function
        (:func:`~tobitkf.filters._compiled_moments.protocol_tkf_block`).

    Raises
    ------
    ValidationError
        Unknown option or wrong argument types; at ``filter``, ``backend="numba"`` for a case the compiled
        loop does not cover.
    ImportError
        ``backend="numba"`` without numba installed.

    Notes
    -----
    See :func:`protocol_tobit_kalman_filter` for the equations and the deviations from the
    source. :meth:`baseline` builds the paper's comparison filter PBTKF. Online use:
    ``step(state, y_k, uncensored=g_k)`` (``g_k`` defaults to ``y_k > threshold``).
    """

    _name = "ProtocolTobitKalmanFilter"
    _filter_doc = """Run the PBTKF-IMSF (Geng et al., Theorem 1, Table I; the update (21)–(24)) over a batch of received
    records ``y`` (..., T, 1); see :func:`protocol_tobit_kalman_filter`. ``extras["scheduled"]`` (T,): the sensor
    the schedule gave each step."""
    _filter_params = {
        "y": "(..., T, 1) array_like\n"
        "    Received scalar readings y_1..y_T (a censored reading equals τ). A NaN reading (a packet lost on the\n"
        "    link, not in the source's model) only predicts, whatever ``uncensored`` says there (it is reported\n"
        "    as not uncensored).",
        "u": "(..., T, p) array_like, optional\n"
        "    The control inputs u(0..T-1) of a system with ``Bu`` (the prediction of step k adds B_u u(k-1) to the\n"
        "    current state's block; not in the source, whose plant has no input).",
        "uncensored": "(..., T, 1) bool array_like, optional\n"
        "    :math:`\\gamma_k` from the detection device, laid out like ``y``; default ``y > threshold``.",
        "keep_augmented": "bool, default False\n"
        "    Also return the ξ-space covariances ``aug_cov``, ``aug_pred_cov`` (memory: N T n_ξ²).",
    }
    _filter_raises = "a reading below τ (``check_limits``); ``uncensored`` not laid out like ``y`` (a ShapeError)"
    _step_options = ("uncensored",)
    _loop_ctx: tuple  # what every call of the compiled loop takes from the estimator (_loop_constants)
    _compiled_static: bool  # whether the compiled loop runs (decided on the first call)

    def __init__(
        self,
        system: LinearSystem,
        channel: ProtocolChannel,
        *,
        failure_term: str = "variance",
        prehistory_prior: str = "x0",
        covariance_update: str = "joseph",
        P0_aug: Any = None,
        check_limits: bool = True,
        backend: str = "auto",
    ):
        prehistory_prior = _check_options(failure_term, prehistory_prior, covariance_update)
        check_option(backend, "backend", BACKENDS)
        if backend == "numba":
            compiled_module()  # raises ImportError without numba
        self.backend = backend
        _check_parts(system, channel)
        self._setup_system(system)
        self.m = 1
        self.channel = channel
        self.failure_term, self.prehistory_prior, self.covariance_update = (
            failure_term,
            prehistory_prior,
            covariance_update,
        )
        self.P0_aug = P0_aug
        self.check_limits = check_limits
        self._ell = channel.window
        self._nxi = system.n * (self._ell + 1)
        _initial(system, self._ell, prehistory_prior, P0_aug)  # validates P0_aug once
        self._lam_mean, self._lam_var = channel.failure_mean, channel.failure_variance
        self._tau = float(channel.threshold)
        self._order = tuple(int(o) - 1 for o in np.asarray(channel.schedule.order).ravel())
        self._constant_C = not (system.C.varying or system.R.varying)
        self._constant_AQ = not (system.A.varying or system.Q.varying or (system.B is not None and system.B.varying))
        self._transition_cache: Transition | None = None
        self.options = {
            "failure_term": failure_term,
            "prehistory_prior": prehistory_prior,
            "covariance_update": covariance_update,
            "P0_aug": P0_aug,
        }

    @classmethod
    def baseline(cls, system: LinearSystem, channel: ProtocolChannel, **options: Any) -> ProtocolTobitKalmanFilter:
        """The PBTKF of the paper's comparisons: this filter with ℓ = 0 and no failures."""
        return cls(system, baseline_channel(channel), **options)

    def _state_dim(self) -> int:
        return self._nxi

    def _initial(self, N, x0, P0, batch):
        n = self.n
        x0a = None if x0 is None else as_float_array(x0, "x0", ndim=1)
        P0a = None if P0 is None else as_float_array(P0, "P0", ndim=2)
        if x0a is not None and x0a.shape != (n,):
            raise ShapeError(f"x0: expected ({n},) (one prior for every run), got {x0a.shape}")
        if P0a is not None:
            if P0a.shape != (n, n):
                raise ShapeError(f"P0: expected ({n}, {n}), got {P0a.shape}")
            check_psd(P0a, "P0")
        xi0, M0 = _initial(self.system, self._ell, self.prehistory_prior, self.P0_aug, x0a, P0a)
        carry = {}
        if self.failure_term == "lmmse_unconditional":
            carry["X"] = M0 + np.outer(xi0, xi0)
        xi = np.broadcast_to(xi0, (N, self._nxi)).copy()
        return xi, symmetrize(M0)[None], carry  # exactly symmetric (the shift prediction needs it)

    def _transition(self, k, u, carry):
        sys_ = self.system
        controlled = u is not None and sys_.Bu is not None
        if self._transition_cache is not None and not controlled:  # a constant A and Q: built once
            return self._transition_cache
        G = self._roots(k - 1) if self.covariance_update == "square_root" else None
        # (17)-(18): the block shift of (10), the noise in its top block; a control input B_u u(k-1) (not in
        # the source, whose plant has none) enters the top block's mean, as in the fading family
        b = u @ sys_.Bu.at(k).T if controlled else 0.0
        tr = Transition(A=sys_.transition(k - 1), Qd=sys_.process_cov(k - 1), b=b, shift=True, G=G)
        if self._constant_AQ and not controlled:
            self._transition_cache = tr
        return tr

    def _sensor(self, k: int) -> int:
        order = self._order
        return order[(k - 1) % len(order)]

    def _sensor_terms(self, k: int, h: int) -> tuple[np.ndarray, float]:
        r""":math:`\mathcal C_{h,k}` and :math:`\mathcal R_k` of sensor h; for a constant C and R computed
        (and checked) once per sensor and kept, instead of at every step."""
        sys_ = self.system
        constant = not (sys_.C.varying or sys_.R.varying)
        cache = self.__dict__.setdefault("_sensor_cache", {}) if constant else None
        if cache is not None and h in cache:
            return cache[h]
        C_row, r = _sensor_stats(sys_, k, h)
        terms = (stacked_measurement(C_row, self._ell), r)
        if cache is not None:
            cache[h] = terms
        return terms

    def _step_terms(self, k: int, h: int) -> tuple:
        """``(Cc, r, H, H[None, :], lam_mean, lam_var)`` of sensor h at step k; for a constant C and R
        computed once per sensor and kept (the constants of :func:`protocol_measurement`)."""
        cache = self.__dict__.setdefault("_terms_cache", {}) if self._constant_C else None
        if cache is not None and h in cache:
            return cache[h]
        Cc, r = self._sensor_terms(k, h)
        lam_mean, lam_var = float(self._lam_mean[h]), float(self._lam_var[h])
        H = lam_mean * Cc
        H0 = H[None, :]
        for a in (Cc, H, H0):
            a.flags.writeable = False  # shared by every step's prediction
        terms = (Cc, r, H, H0, lam_mean, lam_var)
        if cache is not None:
            cache[h] = terms
        return terms

    def _measurement(self, k, xp, Pp, y, u, carry, uncensored=None, **_):
        if u is not None and self.system.D is not None:
            raise ValidationError(
                "u: the protocol TKF's received reading (4) has no feedthrough D u; "
                "give the system no D (a control input enters through Bu only)"
            )
        h = self._sensor(k)
        Cc, r, H, H0, lam_mean, lam_var = self._step_terms(k, h)
        X = None
        if "X" in carry:
            carry = dict(carry)
            Aa = augmented_transition(self.system.transition(k - 1), self._ell)
            Bn = noise_input(self.n, self._ell)
            carry["X"] = X = Aa @ carry["X"] @ Aa.T + Bn @ self.system.process_cov(k - 1) @ Bn.T
        yk = y[:, 0]
        tau = self._tau
        # a lost reading (NaN) is never uncensored (NaN > tau is False; _prediction masks a given gamma): the step
        # only predicts
        gam = yk > tau if uncensored is None else uncensored[:, 0]
        mp = _prediction(xp, Pp, yk, gam, Cc, r, H, H0, tau, lam_mean, lam_var, self.failure_term, X)
        return mp, carry

    def _extras(self, k, xp, Pp, x, P, mp, K, Ree, options):
        info = _protocol_info(mp)
        info["aug_mean"], info["aug_pred_mean"] = x, xp
        info["uncensored"] = mp.extras["_gamma"]
        if options.get("keep_augmented"):
            N = x.shape[0]
            info["aug_cov"] = np.broadcast_to(P, (N,) + P.shape[1:])
            info["aug_pred_cov"] = np.broadcast_to(Pp, (N,) + Pp.shape[1:])
        return info

    def _prepare_record(self, y, name="y"):
        arr = as_float_array(y, name, allow_nan=True)  # NaN: a lost reading, which only predicts
        if arr.ndim < 2 or arr.shape[-1] != 1:
            raise ShapeError(
                f"{name}: expected (..., T, 1) received scalars (the scheduled sensor's reading), got shape {arr.shape}"
            )
        return super()._prepare_record(arr, name)

    def _check_record(self, y2, u2, k0, name="y"):
        self.system.check_horizon(k0 + y2.shape[1])
        tau = self.channel.threshold
        if self.check_limits and (y2 < tau).any():
            raise ValidationError(
                f"{name}: readings below the threshold tau={tau} cannot come from (4), found {y2[y2 < tau][:3]}"
            )

    def _prepare_step_options(self, state, options):
        g = options.get("uncensored")
        if g is None:
            return {}
        arr = np.asarray(g)
        if arr.dtype != bool:
            raise ValidationError(f"uncensored: expected booleans (the detection device's gamma_k), got {arr.dtype}")
        try:
            arr = np.broadcast_to(arr, state.batch_shape + (1,))
        except ValueError:
            raise ShapeError(
                f"uncensored: expected shape {state.batch_shape + (1,)} (like y), got {arr.shape}"
            ) from None
        return {"uncensored": arr.reshape(state.runs, 1)}

    def filter(
        self,
        y: Any,
        *,
        u: Any = None,
        uncensored: Any = None,
        keep_augmented: bool = False,
        x0: Any = None,
        P0: Any = None,
        outputs: Any = "all",
        state: FilterState | None = None,
    ) -> FilterResult:
        # the shared loop with the recorded indicator as step data (``super().filter`` takes none)
        y2, batch = self._prepare_record(y)
        N, T, _ = y2.shape
        step_data = None
        if uncensored is not None:
            gam = np.asarray(uncensored)
            if gam.shape != batch + (T, 1):
                raise ShapeError(f"uncensored: expected shape {batch + (T, 1)} (like y), got {gam.shape}")
            step_data = {"uncensored": np.asarray(gam, dtype=bool).reshape(N, T, 1)}
        res = self._run(
            y2.reshape(batch + (T, 1)),
            u,
            x0,
            P0,
            outputs=outputs,
            state=state,
            step_options={"keep_augmented": keep_augmented, "uncensored_record": step_data},
            step_data=step_data,
        )
        if res.extras:
            assert res.times is not None, "the estimation loop records the time index"
            k0 = res.times[0] - 1
            res.extras["scheduled"] = self.channel.schedule.scheduled(k0 + T)[k0:]
        return res

    def step(self, state: FilterState, y: Any, *, u: Any = None, **options: Any) -> FilterState:
        """One predict + update with the reading ``y`` (``batch_shape + (1,)``; NaN: a lost reading, which
        only predicts).

        ``uncensored`` (keyword, laid out like ``y``): the detection device's :math:`\\gamma_k`, default
        ``y > threshold``. A plain call (no input, no keyword, float64 readings in [τ, ∞), the compiled
        loop's case) goes straight to the compiled step (:func:`_protocol_plain_step`, the same loop call
        the general step makes, without the checks such a call passes); every other call takes the
        general step.
        """
        if u is None and not options:
            fast = _protocol_plain_step(self, state, y)
            if fast is not None:
                return fast
        return super().step(state, y, u=u, **options)

    # ---- the compiled path (``filter``, and ``step`` through _protocol_loop_step) -------------------
    def _compiled_online_step(self, state, y, u, options):
        """One online step through the compiled loop (T = 1, :func:`_protocol_loop_step`); None (the numpy
        step runs) with an input, ``failure_term="lmmse_unconditional"`` (its X_k is
        carried on the numpy path), a case the loop does not cover, or a covariance that stopped being
        finite. Never raises for ``backend="numba"``: the numpy step has always run those cases."""
        if u is not None or self.failure_term == "lmmse_unconditional":
            return None
        ok = self.__dict__.get("_compiled_static")
        if ok is None:
            ok = self._compiled_static = use_compiled(
                self.backend, _protocol_compiled_gap(self, None), "the protocol Tobit Kalman filter"
            )
        if not ok:
            return None
        return _protocol_loop_step(self, y, options.get("uncensored"), state)

    def _compiled_filter(self, y2, u2, state, want, batch, step_options=None):
        what = "the protocol Tobit Kalman filter"
        step_options = step_options or {}
        if "uncensored_record" not in step_options:  # a loop not started by filter(): gamma unknown here
            gap = "a loop without the uncensored record"
        elif step_options.get("keep_augmented"):
            gap = "keep_augmented=True"
        else:
            # decided once for the case without input
            ok = self.__dict__.get("_compiled_static") if u2 is None else None
            if ok is None:
                ok = use_compiled(self.backend, _protocol_compiled_gap(self, u2), what)
                if u2 is None:
                    self._compiled_static = ok
            if not ok:
                return None
            return _finite_or_none(_protocol_loop_run(self, y2, step_options["uncensored_record"], state, want, batch))
        use_compiled(self.backend, gap, what)  # raises for backend="numba"
        return None

    def __repr__(self) -> str:
        opts = ", ".join(f"{k}={v!r}" for k, v in self.options.items() if k != "P0_aug")
        return f"ProtocolTobitKalmanFilter({self.system!r}, {self.channel!r}, {opts})"


# --------------------------------------------------------------------------- the compiled path


def _protocol_compiled_gap(est: ProtocolTobitKalmanFilter, u) -> str | None:
    """Why the compiled loop cannot run ``est`` (None when it can); ``keep_augmented`` and the uncensored record
    are checked by the caller."""
    if est.covariance_update == "square_root":
        return "covariance_update='square_root'"
    return system_gap(est.system, u)


def _loop_constants(est: ProtocolTobitKalmanFilter) -> tuple:
    r"""What every call of the compiled loop takes from the estimator, built once (arrays and numbers only: the
    estimator still pickles): one table per sensor h (p, 2 n_ξ + 4), filled as the sensors are first scheduled
    (:func:`_sensor_rows`), whose row is :math:`\mathbf H_h`, :math:`\mathcal C_h`, :math:`\mathcal R_h`,
    :math:`\bar\Lambda_h`, :math:`\check\Lambda_h`, 0 (the online step's ``row`` of
    :func:`~tobitkf.filters._compiled_entries.protocol_tkf_step`), its columns ``Hs``, ``Cs``, ``rs``, ``pars``
    (views), its rows (views), the set of the filled sensors, the transition ``A`` and noise ``Qd`` (1, 1, n, n),
    the threshold ``lo``, ``hi`` (1, 1, 1), the names of the step's scalars
    (:data:`~tobitkf.filters._compiled_moments.PROTOCOL_TKF_EXTRAS`), the loop's module, the failure-term code and
    the covariance form, the loop's named arguments (:class:`~tobitkf.filters._loop_specs.LoopArguments`), the
    entries' module (the modules imported here, with numba, on first use) and the step's flat constants."""
    ctx = est.__dict__.get("_loop_ctx")
    if ctx is None:
        from . import _compiled_entries, _compiled_loop, _loop_specs
        from ._compiled_moments import PROTOCOL_TKF_EXTRAS

        p, nxi = len(est._lam_mean), est._nxi
        table = np.zeros((p, 2 * nxi + 4))
        table[:, 2 * nxi] = 1.0  # the noise variance of a sensor not yet scheduled (never read)
        Hs, Cs, rs, pars = table[:, :nxi], table[:, nxi : 2 * nxi], table[:, 2 * nxi], table[:, 2 * nxi + 1 :]
        A, Qd = _loop_specs._system_arrays(est.system, 0, 1)
        lohi = (np.full((1, 1, 1), est._tau), np.full((1, 1, 1), math.inf))
        codes = (FAILURE_CODES[est.failure_term], est.covariance_update == "joseph")
        flat = np.concatenate([A.ravel(), Qd.ravel(), [est._tau, codes[0], float(codes[1])]])
        ctx = (Hs, Cs, rs, pars, tuple(table), set(), A, Qd) + lohi
        ctx += (PROTOCOL_TKF_EXTRAS, _compiled_loop, codes, _loop_specs.LoopArguments, _compiled_entries, flat)
        est._loop_ctx = ctx
    return ctx


def _sensor_rows(est: ProtocolTobitKalmanFilter, h: int, k: int, ctx: tuple) -> None:
    """Fill sensor h's row of the table of :func:`_loop_constants` at its first scheduled step k: the terms of
    :meth:`ProtocolTobitKalmanFilter._step_terms`, which checks the sensor's noise variance then, as the numpy
    loop would."""
    Hs, Cs, rs, pars, _, filled = ctx[:6]
    if h not in filled:
        Cc, r, H, _, lam_mean, lam_var = est._step_terms(k, h)
        Hs[h], Cs[h], rs[h], pars[h, :2] = H, Cc, r, (lam_mean, lam_var)
        filled.add(h)


def _protocol_plain_step(est: ProtocolTobitKalmanFilter, state: Any, y: Any) -> FilterState | None:
    """:meth:`ProtocolTobitKalmanFilter.step` of a plain call (no input, no keyword) straight to the compiled
    step, :func:`_protocol_loop_step`, when the general step's checks would pass it unchanged and its
    :meth:`~ProtocolTobitKalmanFilter._compiled_online_step` would run that loop: the compiled loop decided on for
    the estimator (at its first step), a failure term other than ``"lmmse_unconditional"``, a state this
    estimator made (:func:`~tobitkf.filters.core.is_trusted`), not a prediction, of the augmented dimension,
    and ``y`` a float64 array of shape ``batch_shape + (1,)`` whose (at most 16) readings all lie in [τ, ∞) (no NaN: nothing lost, none
    below τ). None otherwise (the general step then runs, with its checks and messages), or when the
    covariance stopped being finite."""
    if not (
        est.__dict__.get("_compiled_static")
        and is_trusted(est, state)  # a state this estimator made (any other takes the general step's checks)
        and not state.carry.get("_predicted")
        and type(y) is np.ndarray
        and y.dtype == np.float64
        and y.shape == state.batch_shape + (1,)
        and y.size <= 16
        and state.x.shape[-1] == est._nxi
        and est.failure_term != "lmmse_unconditional"
    ):
        return None
    tau = est._tau
    if not all(tau <= v < math.inf for v in y.ravel().tolist()):
        return None
    new = _protocol_loop_step(est, y.reshape(-1, 1), None, state)
    return None if new is None else mark_trusted(est, check_step(est, state, new))


def _received(y: np.ndarray, tau: float, gamma: Any) -> np.ndarray:
    """γ of the compiled loop, laid out like ``y`` (C order, bool): ``y > τ``, or the given ``gamma``; a lost
    reading (NaN) is never uncensored (the loop's class ``MISSING``: the step only predicts), as on the numpy
    path (:func:`~tobitkf.filters.protocol_model._prediction`)."""
    if gamma is None:
        return y > tau  # NaN > tau is False
    return np.array(gamma, dtype=np.bool_, order="C").reshape(y.shape) & ~np.isnan(y)


def _protocol_loop_step(est: ProtocolTobitKalmanFilter, y: np.ndarray, gamma, state: FilterState):
    """One online step (y (N, 1), ``gamma`` (N, 1) bool or None for y > τ) through the compiled loop with T = 1:
    the scheduled sensor's rows kept per sensor (:func:`_loop_constants`), no state outputs, the extras of the
    step (the posterior mean ``x_last`` is also ``aug_mean``, as the numpy step's ``x`` is). None when the
    covariance stopped being finite (the numpy step then reruns it and reports the divergence)."""
    ctx = est.__dict__.get("_loop_ctx") or _loop_constants(est)
    N = y.shape[0]
    n, nxi = est.n, est._nxi
    order = est._order
    h = order[state.k % len(order)]  # the sensor of step k + 1 (_sensor)
    if h not in ctx[5]:
        _sensor_rows(est, h, state.k + 1, ctx)
    assert state.P is not None, "the compiled loop runs the Joseph and standard forms, which carry P"
    yk = loop_input(y).reshape(N, 1, 1)
    gam = _received(yk, est._tau, gamma)
    P = state.P if state.P.shape[0] in (1, N) else np.broadcast_to(state.P, (N, nxi, nxi))
    names = ctx[10]
    nex = len(names)
    comp, x_last, P_last = np.empty((N, 1, 1, nex + 2 * nxi)), np.empty((N, nxi)), np.empty((N, nxi, nxi))
    x, P = loop_input(state.x), loop_input(P)
    if not ctx[14].protocol_tkf_step(yk, gam.view(np.int8), ctx[15], ctx[4][h], x, P, comp, x_last, P_last):
        return None  # the check of _finite_or_none, made in the entry
    ext = comp[:, 0, 0]
    extras: dict[str, Any] = dict(zip(names, ext[:, :nex].T))
    extras["aug_mean"], extras["aug_pred_mean"], extras["uncensored"] = x_last, ext[:, nex + nxi :], gam[:, 0, 0]
    return step_state(state.k + 1, state.batch_shape, x_last, P_last, n, None, state.carry, extras)


def _protocol_loop_run(est: ProtocolTobitKalmanFilter, y2, step_data, state: FilterState, want, batch):
    r"""The compiled loop over a record from ``state`` (augmented ξ, P): the schedule's rows per step, the
    deterministic recursion of :math:`\\mathfrak X_k` of ``"lmmse_unconditional"`` (its failure term, the same for
    every run) run here; outputs on request, as the numpy path's."""
    N, T, _ = y2.shape
    n, nxi = est.n, est._nxi
    order = est._order
    sched = np.asarray(order, dtype=np.int64)[(state.k + np.arange(T)) % len(order)]
    ctx = _loop_constants(est)
    for t in np.sort(np.unique(sched, return_index=True)[1]).tolist():  # each sensor's first step, in time order
        _sensor_rows(est, int(sched[t]), state.k + t + 1, ctx)
    Hs, Cs, rs, pars = ctx[:4]
    par = pars[sched][:, None]
    carry = state.carry
    if est.failure_term == "lmmse_unconditional":  # the deterministic X_k of _measurement, run here
        Xk = carry["X"]
        Aa = augmented_transition(est.system.transition(0), est._ell)  # a time-invariant system (covered case)
        Bn = noise_input(n, est._ell)
        BQB = Bn @ est.system.process_cov(0) @ Bn.T
        for t in range(T):
            Xk = Aa @ Xk @ Aa.T + BQB
            h = int(sched[t])
            par[t, 0, 2] = float(pars[h, 1]) * float(Cs[h] @ Xk @ Cs[h])
        carry = dict(carry)
        carry["X"] = Xk
    y3 = np.require(y2, dtype=np.float64, requirements=("C", "W"))
    gam = _received(y3, est._tau, None if step_data is None else step_data["uncensored"])
    assert state.P is not None, "the compiled loop runs the Joseph and standard forms, which carry P"
    ext = "extras" in want
    names = ctx[10]
    nex = len(names)
    means, covs, pmeans, pcovs, comp = output_arrays(N, T, *state_specs(want, n), (ext, (1, nex + 2 * nxi)))
    x_last, P_last = np.empty((N, nxi)), np.empty((N, nxi, nxi))
    P = state.P if state.P.shape[0] in (1, N) else np.broadcast_to(state.P, (N, nxi, nxi))
    H, F, r = Hs[sched][:, None], Cs[sched][:, None, None], rs[sched][None, :, None]
    mode, joseph = ctx[12]
    loop = ctx[11]
    args = ctx[13](
        loop.PROTOCOL_TKF_KIND, y3, cls=gam.view(np.int8), A=ctx[6], Qd=ctx[7], H=H, F=F, r=r, lo=ctx[8], hi=ctx[9], par=par,
        noise_code=mode, joseph=joseph, x0=loop_input(state.x), P0=loop_input(P), means=means, covs=covs,
        pmeans=pmeans, pcovs=pcovs, comp=comp, x_last=x_last, P_last=P_last,
    )  # fmt: skip
    loop.compiled_loop(*args.filled())  # the arrays the protocol TKF does not use: made by filled()

    def out(a):
        return loop_array(a, batch)

    extras: dict[str, Any] = {}
    if ext:
        extras = {name: out(comp[:, :, 0, i]) for i, name in enumerate(names)}
        extras.update(
            aug_mean=out(comp[:, :, 0, nex : nex + nxi]),
            aug_pred_mean=out(comp[:, :, 0, nex + nxi :]),
            uncensored=out(gam[..., 0]),
        )
    final = FilterState(k=state.k + T, batch_shape=batch, x=x_last, P=P_last, n=n, carry=carry)
    return compiled_result(want, batch, T, means, covs, pmeans, pcovs, extras, final)


def protocol_tobit_kalman_filter(
    system: LinearSystem,
    channel: ProtocolChannel,
    y: Any,
    *,
    uncensored: Any = None,
    failure_term: str = "variance",
    prehistory_prior: str = "x0",
    covariance_update: str = "joseph",
    P0_aug: Any = None,
    keep_augmented: bool = False,
    check_limits: bool = True,
) -> FilterResult:
    r"""Run the PBTKF-IMSF (Theorem 1, Table I) over a batch of received records.

    Parameters
    ----------
    system : LinearSystem
        Plant (1) with ``C`` of p rows (row m is sensor m's :math:`C_{m,k}`) and diagonal
        ``R`` (:math:`R_{m,k}` on the diagonal). ``x0``, ``P0`` are :math:`\bar x_0`, :math:`P_0`.
    channel : ProtocolChannel
        Window ℓ, failure laws (only their means and variances are used), schedule, τ.
    y : (..., T, 1) array_like
        Received scalar measurements :math:`y_1..y_T` (censored readings equal τ).
    uncensored : (..., T, 1) bool array_like, optional
        :math:`\gamma_k` from the detection device, laid out like ``y``; default ``y > threshold``.
    failure_term : {"variance", "literal", "second_moment", "lmmse_unconditional"}, default "variance"
        The failure term of (24) (docs/sources GP-01).
    prehistory_prior : {"x0", "zero_mean"}, default "x0"
        Prior of :math:`x_{-1..-\ell}`: :math:`N(\bar x_0, P_0)` or :math:`N(0, P_0)`, independent.
    covariance_update : {"joseph", "standard", "square_root"}, default "joseph"
        Joseph form (App. D (44)) or (20), equal for the optimal gain; or the QR array form.
    P0_aug : (n_ξ, n_ξ) array_like, optional
        :math:`P_{\tilde\xi_0} = M_0`; default :math:`I_{\ell+1}\otimes P_0` (docs/sources GP-05).
    keep_augmented : bool, default False
        Also return the ξ-space covariances ``aug_cov``, ``aug_pred_cov`` (memory: N T n_ξ²).
    check_limits : bool, default True
        Raise if a reading lies below τ.

    Returns
    -------
    FilterResult
        ``mean``/``cov`` :math:`\hat x_k, P_{\tilde x_k}` (..., T, n[, n]); ``pred_mean``/``pred_cov``
        the priors. ``extras``: ``aug_mean``, ``aug_pred_mean`` (..., T, n_ξ); ``uncensored``,
        ``p_uncensored``, ``theta_bar``, ``inverse_mills``, ``trunc_var_factor``, ``expected_y``,
        ``innovation``, ``innovation_var`` (..., T); ``scheduled`` (T,); ``times`` 1..T.

    Raises
    ------
    ValidationError
        Unknown option, a reading below τ, non-positive sensor variance, bad ``P0_aug``.
    ShapeError
        ``y`` not (..., T, 1); ``C`` not p rows.

    Notes
    -----
    Deviations from the source (each an option; defaults: docs/sources GP-01, GP-05, GP-12):

    * ``failure_term="variance"`` (default; GP-01) reads the coefficient of the second term of
      (24) as the failure *variance* :math:`\check\Lambda` (the value the example prints,
      0.065); the paper's definition :math:`\tilde\Lambda = \bar\Lambda^2 + \check\Lambda`
      is ``"literal"``, which does not reduce to the Kalman filter without failures (it keeps
      :math:`\mathcal CP\mathcal C^T`). ``"second_moment"`` uses the state second moment that
      the paper's own (35) calls for; ``"lmmse_unconditional"`` the unconditional one
      (exact LMMSE when τ = -inf).
    * (17) is read with :math:`\mathcal A_{k-1}` (GP-11); (18) with the posterior :math:`P_{k-1}`.
    * :math:`\vartheta` is divided by :math:`\sqrt{\mathcal R_k}`, not :math:`\mathcal R_k` (GP-03).
    * The censored step is implemented as "unchanged" (K = 0), avoiding 0/0 (GP-12).

    Examples
    --------
    Without failures, integral or censoring, and one sensor, this is the Kalman filter:

    >>> import numpy as np, tobitkf as tk
    >>> from tobitkf.channels.protocol import ProtocolChannel
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.5], [1.0], [-0.2]])
    >>> a = protocol_tobit_kalman_filter(sys, ProtocolChannel(1), y).mean
    >>> bool(np.allclose(a, tk.KalmanFilter(sys).filter(y).mean, rtol=0, atol=1e-12))
    True
    """
    est = ProtocolTobitKalmanFilter(
        system,
        channel,
        failure_term=failure_term,
        prehistory_prior=prehistory_prior,
        covariance_update=covariance_update,
        P0_aug=P0_aug,
        check_limits=check_limits,
    )
    return est.filter(y, uncensored=uncensored, keep_augmented=keep_augmented)


def baseline_channel(channel: ProtocolChannel) -> ProtocolChannel:
    r"""The PBTKF baseline's (mis-specified) channel model (docs/sources GP-16).

    Same schedule and τ, but :math:`\ell_{model} = 0` and no failures
    (:math:`\bar\Lambda \equiv 1`, :math:`\check\Lambda \equiv 0`, so :math:`F_k = 0`).
    """
    return channel.replace(window=0, failures=NO_FAILURE)


def _baseline(system, parts, o):
    return ProtocolTobitKalmanFilter.baseline(system, parts["protocol"], **o)


register(
    family_entry(
        ProtocolTobitKalmanFilter,
        "protocol-based TKF: Round-Robin, integral readings, failures (Geng et al.)",
        ("protocol",),
        options={**_OPTIONS, "backend": BACKENDS},
    ),
    family_entry(
        ProtocolTobitKalmanFilter,
        "the protocol paper's PBTKF baseline: no window, no failures modelled",
        ("protocol",),
        options={"covariance_update": _OPTIONS["covariance_update"]},
        name="ProtocolBaselineTobitKalmanFilter",
        factory=_baseline,  # ProtocolTobitKalmanFilter.baseline
    ),
)
