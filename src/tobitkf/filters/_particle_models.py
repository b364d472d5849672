r"""What each channel contributes to the particle filter: its reading model (internal).

The measurement models of :class:`tobitkf.ParticleFilter` (the equations are in
:mod:`tobitkf.filters.particle`'s docstring): for a linear system, the particles' dynamics, the
likelihood of a reading given a particle (``log_likelihood``) and, where it has a closed form, the
locally optimal proposal (``propose``) of linear readings with censoring (``_Linear``), Rice fading
(``_Fading``), the protocol channel (``_Protocol``, with its Rao-Blackwellised step), random
saturation (``_Saturation``) and any channel of the measurement contract (``_Contract``);
``_build_model`` chooses one from the channel pieces. Batched over runs and particles: arrays
``(N, Np, n_x)``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.special import log_ndtr, ndtri_exp

from .._linalg import psd_sqrt, symmetrize
from .._validation import ValidationError
from ..channels.base import Channel
from ..channels.censoring import Censoring
from ..channels.fading import RiceFading, measurement_matrix_at
from ..channels.laws import PMF, Gaussian
from ..channels.protocol import ProtocolChannel
from ..channels.saturation import RandomSaturation, saturate
from ..models.linear import LinearSystem
from ._readings import _INTERIOR, _LOG_SQRT_2PI, _LOWER, _MISSING, _RTOL_LIMIT, _UPPER
from ._readings import classify_readings as _classify
from .core import predict, shift_predict

# --------------------------------------------------------------------------- pure pieces


def logsumexp(a: np.ndarray, axis: int) -> np.ndarray:
    """log(sum(exp(a))) along ``axis`` (-inf where every term is -inf); lighter than scipy's for this loop."""
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(divide="ignore"):
        return np.log(np.sum(np.exp(a - m), axis=axis)) + np.squeeze(m, axis=axis)


def _mat(X: np.ndarray, M: np.ndarray) -> np.ndarray:
    """X @ M for particles X (..., k) and a matrix M (k, j), as one GEMM over the stacked rows."""
    return (X.reshape(-1, X.shape[-1]) @ M).reshape(X.shape[:-1] + M.shape[-1:])


def _shifted(mu: np.ndarray, b: Any) -> np.ndarray:
    """The particles' means ``mu`` (N, Np, d) plus each run's known term ``b`` (N, d) (an input's :math:`B^uu_k`,
    a feedthrough :math:`Du_k`); ``mu`` itself when there is none (``b`` the scalar 0.0)."""
    if np.isscalar(b) and b == 0.0:
        return mu
    return mu + b[:, None, :]


def _truncated_draw(mean: np.ndarray, sd: Any, log_mass: np.ndarray, u: np.ndarray, side: int) -> np.ndarray:
    r"""A draw of :math:`N(\mu, s^2)` truncated to :math:`(-\infty, l]` (``side=-1``) or :math:`[h, \infty)`
    (``side=+1``), by inversion in log space: :math:`z = \Phi^{-1}(u\,\Phi(a))` through ``ndtri_exp``
    (exact far in the tails), with ``log_mass`` :math:`= \log\Phi(a)` the log-mass of the kept side
    (:math:`a = (l-\mu)/s`, or :math:`(\mu-h)/s` for the upper side, drawn mirrored)."""
    with np.errstate(divide="ignore"):
        z = ndtri_exp(np.log(u) + log_mass)
    return mean + z * sd if side < 0 else mean - z * sd


# --------------------------------------------------------------------------- measurement models


class _Model:
    """What a channel contributes to the particle filter (internal).

    A model for a channel family with a reading model of its own (fading, the protocol channel, random
    saturation) names the channel class it serves (``serves``) and is found by it; every other channel
    goes through the measurement contract (:class:`_Contract`)."""

    nx: int  # state (history) dimension carried by the particles
    m: int  # reading dimension
    optimal: bool = False
    linearised: bool = False  # the linearised optimal proposal (a NonlinearSystem's region channel)
    steps: int = 1  # its linearisation point: the prediction (1), or after steps - 1 Gauss-Newton steps
    censoring: Censoring | None = None
    serves: type | None = None  # the channel class this model is the particle filter's reading model of
    feedthrough = True  # the reading carries D u (the protocol and saturation readings do not)
    _served: dict[type, type[_Model]] = {}

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("serves") is not None:
            _Model._served[cls.__dict__["serves"]] = cls

    @property
    def label(self) -> str:
        """The kind of readings, for messages."""
        return type(self).__name__[1:].lower()

    @classmethod
    def build(cls, system: LinearSystem, piece: Any, censoring: Censoring | None) -> _Model:
        """The model of ``piece`` with an optional censoring of its readings (the subclasses that serve a
        channel class take ``(system, piece, censoring)``)."""
        make: Any = cls
        return make(system, piece, censoring)

    def __init__(self, system: LinearSystem):
        self.system = system
        self.n = system.n

    # dynamics ---------------------------------------------------------------
    def initial(self, rng, N, Np, x0, P0) -> np.ndarray:
        L = psd_sqrt(P0)  # (N, n, n)
        z = rng.standard_normal((N, Np, self.n))
        return x0[:, None, :] + np.einsum("rij,rpj->rpi", L, z)

    def predict_moments(self, k, x, P, b):
        A, Qd = self.system.transition(k - 1), self.system.process_cov(k - 1)
        return predict(x, P, A, Qd, b)

    def propagate(self, rng, k, X, b):
        """Draw from p(x_k | x_{k-1}) (the bootstrap proposal)."""
        A, G = self.system.transition(k - 1), self._root(k - 1)
        Xn = _mat(X, A.T)
        if not (np.isscalar(b) and b == 0.0):
            Xn = Xn + b[:, None, :]
        z = rng.standard_normal(X.shape[:2] + (G.shape[1],))
        return Xn + _mat(z, G.T)

    def _root(self, k):
        return psd_sqrt(self.system.process_cov(k))

    # readings ---------------------------------------------------------------
    def limits(self, k):
        if self.censoring is None:
            return np.full(self.m, -np.inf), np.full(self.m, np.inf)
        lo, hi = self.censoring.limits(k)
        return np.broadcast_to(lo, (self.m,)), np.broadcast_to(hi, (self.m,))

    def modes(self, rng, k, X, dy):
        """[(log pi (m,) or scalar, mean (N, Np, m), std broadcastable)]: the latent reading's law."""
        raise NotImplementedError

    def log_likelihood(self, rng, k, X, y, dy):
        """log p(y_k | xi_k) for every particle, (N, Np)."""
        lo, hi = self.limits(k)
        cls = _classify(y, lo, hi)
        modes = self.modes(rng, k, X, dy)
        N, Np = X.shape[:2]
        out = np.zeros((N, Np))
        for l in range(self.m):
            c = cls[:, l]
            for kind in (_INTERIOR, _LOWER, _UPPER):
                rows = np.flatnonzero(c == kind)
                if rows.size == 0:
                    continue
                terms = []
                for logp, mu, sd in modes:
                    lp = logp if np.ndim(logp) == 0 else logp[l]
                    if lp == -np.inf:
                        continue
                    mu_l = mu[rows, :, l]
                    sd_l = _pick(sd, rows, l)
                    if kind == _INTERIOR:
                        z = (y[rows, l][:, None] - mu_l) / sd_l
                        t = -0.5 * z * z - np.log(sd_l) - _LOG_SQRT_2PI
                    elif kind == _LOWER:
                        t = log_ndtr((lo[l] - mu_l) / sd_l)
                    else:
                        t = log_ndtr((mu_l - hi[l]) / sd_l)
                    terms.append(t + lp)
                out[rows] += terms[0] if len(terms) == 1 else logsumexp(np.stack(terms), axis=0)
        return out

    def check_record(self, y2: np.ndarray, start: int) -> None:
        if self.censoring is not None:
            self.censoring.check(self.m, start - 1 + y2.shape[1])
            self.censoring.check_measurements(y2, start=start)


def _pick(sd: Any, rows: np.ndarray, l: int):
    if np.ndim(sd) == 0:
        return sd
    if sd.ndim == 1:
        return sd[l]
    return sd[rows, :, l]


def _diag_sigma(system: LinearSystem, k: int, what: str) -> np.ndarray:
    R = system.measurement_cov(k)
    off = R - np.diag(np.diagonal(R))
    if np.abs(off).max(initial=0.0) > 1e-12 * max(1.0, np.abs(R).max()):
        raise ValidationError(f"R: the particle filter needs a diagonal R (independent channel noises) for {what}")
    d = np.diagonal(R)
    if np.any(d <= 0):
        raise ValidationError(f"R: the particle filter needs positive measurement variances, got {d}")
    return np.sqrt(d)


class _Linear(_Model):
    """y* = C x + D u + v, optionally censored; closed-form locally optimal proposal."""

    optimal = True

    def __init__(self, system, censoring):
        super().__init__(system)
        self.censoring = censoring
        self.nx, self.m = system.n, system.m
        if censoring is not None:
            censoring.check(system.m)

    def modes(self, rng, k, X, dy):
        C = self.system.measurement(k)
        mu = _mat(X, C.T)
        if not (np.isscalar(dy) and dy == 0.0):
            mu = mu + dy[:, None, :]
        return [(0.0, mu, _diag_sigma(self.system, k, "censored readings"))]

    def propose(self, rng, k, X, y, b, dy, xp=None, Pp=None):
        r"""Draw from p(x_k | x_{k-1}, y_k) channel by channel; returns (X_new, log p(y_k | x_{k-1}))."""
        sys_ = self.system
        mu = _shifted(_mat(X, sys_.transition(k - 1).T), b)
        lo, hi = self.limits(k)
        r = _diag_sigma(sys_, k, "censored readings") ** 2
        return _gaussian_proposal(rng, mu, sys_.process_cov(k - 1), sys_.measurement(k), dy, r[None, :], y, lo, hi)


def _exact_reading(yv: np.ndarray, p: np.ndarray, sd: Any) -> tuple[np.ndarray, np.ndarray]:
    r"""An exact reading ``yv`` (rows, 1) in the sequential proposals: the latent value drawn is the reading itself
    (broadcast to the particles' ``p`` (rows, Np)) and its weight the normal log-density
    :math:`\log N(y; p, sd^2)`."""
    z = (yv - p) / sd
    return np.broadcast_to(yv, p.shape), -0.5 * z * z - np.log(sd) - _LOG_SQRT_2PI


def _gaussian_proposal(rng, mu, Qd, H, offset, r, y, lo, hi):
    r"""Sample :math:`(x_k, y^*_{cens})` from the Gaussian model :math:`x_k \sim N(\mu, Q_d)`,
    :math:`y^*_l = H_lx_k + o_l + v_l`, :math:`v_l \sim N(0, r_l)`, given the readings, channel by channel
    (the GHK simulator for censored channels), batched over runs and particles.

    Parameters
    ----------
    mu : (N, Np, n) prior means ; Qd : (n, n) ; H : (m, n) ; offset : (N, Np, m), (N, m) or 0
    r : (N or 1, m) latent noise variances (> 0) ; y : (N, m) ; lo, hi : (m,)

    Returns
    -------
    X : (N, Np, n) the draws ; logw : (N, Np) the log marginal likelihood of the readings under the
    model (:math:`\prod_l` of the sequential densities or masses)
    """
    N, Np, n = mu.shape
    m = H.shape[0]
    cls = _classify(y, lo, hi)
    U = rng.random((N, Np, m))
    eps = rng.standard_normal((N, Np, n))

    def reading(l, kind, rows, p, sd):
        if kind == _INTERIOR:
            return _exact_reading(y[rows, l][:, None], p, sd)
        if kind == _LOWER:
            lm = log_ndtr((lo[l] - p) / sd)
            return _truncated_draw(p, sd, lm, U[rows, :, l], -1), lm
        lm = log_ndtr((p - hi[l]) / sd)
        return _truncated_draw(p, sd, lm, U[rows, :, l], +1), lm

    return _condition_in_sequence(mu, Qd, H, offset, r, cls, reading, eps)


def _condition_in_sequence(mu, Qd, H, offset, r, cls, reading, eps):
    r"""The channel-by-channel Gaussian conditioning shared by the closed-form proposals.

    :math:`x_k \sim N(\mu, \Sigma)`, :math:`\Sigma = Q_d` at the start; for each channel l with a reading
    (``cls[:, l]`` not missing) the latent value :math:`y^*_l = H_lx_k + o_l + v_l`,
    :math:`v_l \sim N(0, r_l)`, has the law :math:`N(p, s^2)`, :math:`p = H_l\mu + o_l`,
    :math:`s^2 = H_l\Sigma H_l^T + r_l`; ``reading(l, kind, rows, p, sd)`` returns a draw of
    :math:`y^*_l` given the reading (for the runs ``rows`` of class ``kind``) and its log weight, and
    the Gaussian is conditioned on it: :math:`\mu \leftarrow \mu + g(y^*_l - p)`,
    :math:`\Sigma \leftarrow \Sigma - s^2gg^T`, :math:`g = \Sigma H_l^T/s^2` (:math:`g = 0` where
    :math:`s^2 = 0`: the value is then :math:`p` itself). Finally :math:`x_k = \mu + \Sigma^{1/2}\varepsilon`.
    With one H per particle (a linearisation about each particle's prediction) :math:`\Sigma` is carried per
    particle.

    Parameters
    ----------
    mu : (N, Np, n) ; Qd : (n, n) ; H : (m, n), or (N, Np, m, n) one per particle ;
    offset : (N, Np, m), (N, m) or 0 ; r : (N or 1, m) (>= 0) ;
    cls : (N, m) reading classes ; reading : callable ; eps : (N, Np, n) standard normal draws

    Returns
    -------
    X : (N, Np, n) ; logw : (N, Np) the sum of the channels' log weights
    """
    N, Np, n = mu.shape
    m = H.shape[-2]
    per_particle = H.ndim == 4
    logw = np.zeros((N, Np))
    per_run = bool((cls == _MISSING).any()) or r.shape[0] != 1
    Sig = np.broadcast_to(Qd, (N, Np, n, n) if per_particle else (N if per_run else 1, n, n)).copy()
    off = offset if np.ndim(offset) != 2 else offset[:, None, :]
    for l in range(m):
        valid = cls[:, l] != _MISSING
        if not valid.any():
            continue
        if per_particle:
            c = H[:, :, l, :]  # (N, Np, n)
            Sc = np.einsum("rpij,rpj->rpi", Sig, c)
            s2 = np.einsum("rpi,rpi->rp", Sc, c) + r[:, l][:, None]  # (N, Np)
            g = Sc / np.where(s2 > 0, s2, 1.0)[..., None]
            pred = np.einsum("rpi,rpi->rp", mu, c)
            sr = np.sqrt(s2)
        else:
            c = H[l]
            Sc = Sig @ c  # (Ns, n)
            s2 = Sc @ c + r[:, l]  # (Ns,)
            g = Sc / np.where(s2 > 0, s2, 1.0)[:, None]
            pred = _mat(mu, c[:, None])[..., 0]
            sr = np.broadcast_to(np.sqrt(s2), (N,))[:, None]
        if not (np.isscalar(off) and off == 0.0):
            pred = pred + off[..., l]
        val = np.zeros((N, Np))
        for kind in (_INTERIOR, _LOWER, _UPPER):
            rows = np.flatnonzero(cls[:, l] == kind)
            if rows.size == 0:
                continue
            v, lw = reading(l, kind, rows, pred[rows], sr[rows])
            val[rows] = v
            logw[rows] += lw
        innov = np.where(valid[:, None], val - pred, 0.0)
        if per_particle:
            mu = mu + innov[..., None] * g
            upd = s2[..., None, None] * g[..., :, None] * g[..., None, :]
            Sig = symmetrize(Sig - np.where(valid[:, None, None, None], upd, 0.0))
            continue
        gr = np.broadcast_to(g, (N, n)) if g.shape[0] == 1 else g
        mu = mu + innov[..., None] * gr[:, None, :]
        upd = s2[:, None, None] * g[:, :, None] * g[:, None, :]
        if per_run:
            upd = np.where(valid[:, None, None], upd, 0.0)
        Sig = symmetrize(Sig - upd)
    L = psd_sqrt(Sig)
    if per_particle:
        X = mu + np.einsum("rpij,rpj->rpi", L, eps)
    elif L.shape[0] == 1:
        X = mu + _mat(eps, L[0].T)
    else:
        X = mu + np.einsum("rij,rpj->rpi", L, eps)
    return X, logw


class _Augmented(_Model):
    """A model whose state stacks the current state on the last ones, :math:`[x_k; x_{k-1}; \\dots]` (the fading
    and protocol channels' windows): the top block moves as the plain model's state, the others shift down one."""

    def predict_moments(self, k, x, P, b):
        return shift_predict(x, P, self.system.transition(k - 1), self.system.process_cov(k - 1), b)

    def propagate(self, rng, k, X, b):
        n = self.n
        top = super().propagate(rng, k, X[..., :n], b)
        return np.concatenate([top, X[..., : self.nx - n]], axis=-1)


class _Fading(_Augmented):
    """Rice fading of order L (Gaussian coefficients marginalized exactly; other laws drawn)."""

    serves = RiceFading

    def __init__(self, system, fading, censoring):
        super().__init__(system)
        fading.check(system.m)
        self.fading, self.censoring = fading, censoring
        self.L = fading.order
        self.nx, self.m = system.n * (self.L + 1), system.m
        self.gaussian = isinstance(fading.coefficients, Gaussian)
        self.mean_g = fading.mean_gains(system.m)  # (L+1, m)
        self.var_g = fading.var_gains(system.m)
        if censoring is not None:
            censoring.check(system.m)

    def initial(self, rng, N, Np, x0, P0):
        X = np.zeros((N, Np, self.nx))
        X[..., : self.n] = super().initial(rng, N, Np, x0, P0)
        return X

    def modes(self, rng, k, X, dy):
        n = self.n
        S = min(self.L, k)
        cx = np.stack(
            [_mat(X[..., s * n : (s + 1) * n], measurement_matrix_at(self.system, k - s).T) for s in range(S + 1)],
            axis=2,
        )  # (N, Np, S+1, m)
        return self._faded_modes(rng, k, cx, dy)

    def _faded_modes(self, rng, k, cx, dy):
        r"""The latent reading's law given each particle's unfaded terms ``cx`` (N, Np, S+1, m), term s the
        reading :math:`C_{k-s}x_{k-s}` that the gain :math:`\vartheta(s)` multiplies (a NonlinearSystem's order 0:
        :math:`h(x_k, k)`), plus the unfaded feedthrough ``dy`` (N, m) or 0."""
        N, Np, S1, m = cx.shape
        S = S1 - 1
        sigma = _diag_sigma(self.system, k, "fading readings")
        if self.gaussian:
            mu = np.einsum("rpsm,sm->rpm", cx, self.mean_g[: S + 1])
            var = np.einsum("rpsm,sm->rpm", cx * cx, self.var_g[: S + 1]) + sigma**2
            sd = np.sqrt(var)
        else:
            law = self.fading.coefficients
            theta = law.sample(rng, (N, Np, m)) if law.shape == (self.L + 1,) else law.sample(rng, (N, Np))
            if law.shape == (self.L + 1,):
                theta = np.swapaxes(theta, -1, -2)  # (N, Np, L+1, m)
            mu = np.einsum("rpsm,rpsm->rpm", cx, theta[:, :, : S + 1])
            sd = sigma
        if not (np.isscalar(dy) and dy == 0.0):
            mu = mu + dy[:, None, :]
        return [(0.0, mu, sd)]


class _Protocol(_Augmented):
    """Integral window + failure gains + Round-Robin + censoring at tau (the scheduled sensor's reading)."""

    serves = ProtocolChannel
    feedthrough = False

    @classmethod
    def build(cls, system, piece, censoring):
        if censoring is not None:
            raise ValidationError("censoring: the protocol channel carries its own threshold tau; give no Censoring")
        return cls(system, piece)

    def __init__(self, system, channel: ProtocolChannel):
        super().__init__(system)
        channel.check(system)
        self.channel = channel
        self.ell = channel.window
        self.nx, self.m = system.n * (self.ell + 1), 1
        self.censoring = Censoring(lower=channel.threshold)
        self.discrete: list[tuple[np.ndarray, np.ndarray] | None] = []
        for i, law in enumerate(channel.laws):
            if isinstance(law, PMF):
                self.discrete.append((np.asarray(law.values, float), np.asarray(law.probs, float)))
            elif isinstance(law, Gaussian) and float(law.variance) == 0.0:
                self.discrete.append((np.atleast_1d(float(law.mean)), np.ones(1)))
            else:
                self.discrete.append(None)
        self.optimal = all(d is not None for d in self.discrete)

    def sensor(self, k):
        order = self.channel.schedule.order
        return int(order[(k - 1) % order.size]) - 1

    def initial(self, rng, N, Np, x0, P0):
        n, ell = self.n, self.ell
        X = np.empty((N, Np, self.nx))
        X[..., :n] = super().initial(rng, N, Np, x0, P0)
        mode = self.channel.prehistory
        for s in range(1, ell + 1):
            if mode == "prior":
                X[..., s * n : (s + 1) * n] = super().initial(rng, N, Np, x0, P0)
            elif mode == "hold":
                X[..., s * n : (s + 1) * n] = X[..., :n]
            else:
                X[..., s * n : (s + 1) * n] = 0.0
        return X

    def _window_row(self, k):
        h = self.sensor(k)
        c = self.system.measurement(k)[h]
        r = _diag_sigma(self.system, k, "the protocol channel")[h] ** 2
        return h, c, r

    def modes(self, rng, k, X, dy):
        h, c, r = self._window_row(k)
        n = self.n
        win = X[..., :n].copy()
        for s in range(1, self.ell + 1):
            win += X[..., s * n : (s + 1) * n]
        base = (win @ c)[..., None]  # (N, Np, 1)
        sd = np.sqrt(r)
        d = self.discrete[h]
        if d is None:
            lam = np.asarray(self.channel.laws[h].sample(rng, base.shape), dtype=float)
            return [(0.0, lam * base, sd)]
        vals, probs = d
        with np.errstate(divide="ignore"):
            logp = np.log(probs)
        return [(logp[j], vals[j] * base, sd) for j in range(vals.size)]

    def propose(self, rng, k, X, y, b, dy, xp=None, Pp=None):
        r"""Locally optimal proposal for a discrete failure law.

        Per particle: the outcome j from its posterior :math:`\propto \pi_jp(y \mid \xi_{k-1}, \lambda_j)`, the
        latent reading z (the reading, or a truncated-normal draw when censored), then
        :math:`x_k \mid (x_{k-1}, z, \lambda_j)`, drawn by Matheron's rule: a joint prior draw
        :math:`(\tilde x, \tilde z)` moved by :math:`\tilde x + \mathrm{Cov}(x, z)\mathrm{Var}(z)^{-1}(z - \tilde z)`
        (exact, no factorization per particle). Weight: :math:`p(y \mid \xi_{k-1}) = \sum_j\pi_j p(y\mid\xi_{k-1},\lambda_j)`."""
        n, nx = self.n, self.nx
        sys_ = self.system
        A, Qd = sys_.transition(k - 1), sys_.process_cov(k - 1)
        h, c, r = self._window_row(k)
        vals, probs = self.discrete[h]
        J = vals.size
        N, Np = X.shape[:2]
        mux = _mat(X[..., :n], A.T)
        if not (np.isscalar(b) and b == 0.0):
            mux = mux + b[:, None, :]
        past = np.zeros((N, Np))
        for s in range(self.ell):
            past += _mat(X[..., s * n : (s + 1) * n], c[:, None])[..., 0]
        U = rng.random((N, Np, 2))
        eps = rng.standard_normal((N, Np, n))
        vt = rng.standard_normal((N, Np))
        base = _mat(mux, c[:, None])[..., 0] + past  # C_h (mean of x_k + past states)
        tau = self.channel.threshold
        cls = _classify(y[:, 0], np.full(N, tau), np.full(N, np.inf))
        Qc = Qd @ c
        cQc = float(c @ Qc)
        sds = np.sqrt(vals**2 * cQc + r)  # (J,)
        with np.errstate(divide="ignore"):
            logpi = np.log(probs)
        inter, lower = np.flatnonzero(cls == _INTERIOR), np.flatnonzero(cls == _LOWER)
        comps = np.zeros((J, N, Np))
        for j in range(J):
            mean = vals[j] * base
            if inter.size:
                zz = (y[inter, 0][:, None] - mean[inter]) / sds[j]
                comps[j, inter] = -0.5 * zz * zz - np.log(sds[j]) - _LOG_SQRT_2PI
            if lower.size:
                comps[j, lower] = log_ndtr((tau - mean[lower]) / sds[j])
            comps[j] += logpi[j]
        logw = logsumexp(comps, axis=0)  # (N, Np)
        missing = cls == _MISSING
        logw[missing] = 0.0
        cum = np.cumsum(np.exp(comps - logw[None]), axis=0)
        jsel = np.minimum((U[None, ..., 0] >= cum).sum(0), J - 1)  # (N, Np)
        lam, sd = vals[jsel], sds[jsel]
        z = np.broadcast_to(y[:, 0][:, None], (N, Np)).copy()
        if lower.size:
            lm = np.take_along_axis(comps[:, lower], jsel[lower][None], axis=0)[0] - logpi[jsel[lower]]
            z[lower] = _truncated_draw(lam[lower] * base[lower], sd[lower], lm, U[lower, :, 1], -1)
        xt = mux + _mat(eps, psd_sqrt(Qd).T)  # joint prior draw (x~, z~)
        zt = lam * (_mat(xt, c[:, None])[..., 0] + past) + np.sqrt(r) * vt
        gain = np.where(missing[:, None], 0.0, lam / (sd * sd) * (z - zt))
        Xn = np.empty((N, Np, nx))
        Xn[..., :n] = xt + gain[..., None] * Qc
        Xn[..., n:] = X[..., : nx - n]
        return Xn, logw

    # Rao-Blackwellised (mixture Kalman) filter ------------------------------------------------
    def rb_initial(self, N, Np, x0, P0):
        r"""The Gaussian of the window :math:`\xi_0 = (x_0, x_{-1}, \dots, x_{-\ell})` every particle starts
        from: means (N, Np, n_x) and covariances (N, Np, n_x, n_x), by the channel's ``prehistory``
        (``"prior"``: iid blocks :math:`N(\bar x_0, P_0)`; ``"hold"``: every block :math:`x_0`; ``"zero"``)."""
        n, ell, nx = self.n, self.ell, self.nx
        mode = self.channel.prehistory
        m = np.zeros((N, nx))
        P = np.zeros((N, nx, nx))
        for s in range(ell + 1):
            if s == 0 or mode != "zero":
                m[:, s * n : (s + 1) * n] = x0
            for t in range(ell + 1):
                if s == t and (s == 0 or mode != "zero"):
                    P[:, s * n : (s + 1) * n, t * n : (t + 1) * n] = P0
                elif mode == "hold" and s > 0 and t > 0:
                    P[:, s * n : (s + 1) * n, t * n : (t + 1) * n] = P0
            if mode == "hold" and s > 0:
                P[:, :n, s * n : (s + 1) * n] = P0
                P[:, s * n : (s + 1) * n, :n] = P0
        M = np.broadcast_to(m[:, None], (N, Np, nx)).copy()
        C = np.broadcast_to(P[:, None], (N, Np, nx, nx)).copy()
        return M, C

    def rb_step(self, rng, k, M, P, y, b):
        r"""One step of the Rao-Blackwellised filter (see :class:`ParticleFilter`, ``"rao_blackwellised"``).

        ``M`` (N, Np, n_x), ``P`` (N, Np, n_x, n_x): each particle's Gaussian of the window given its
        failure outcomes and latent readings; ``y`` (N, 1). Returns the updated (M, P) and the log
        incremental weights (N, Np) :math:`\log\sum_j\pi_jp(y_k \mid \lambda_j, \text{particle})`."""
        n, nx = self.n, self.nx
        sys_ = self.system
        A, Qd = sys_.transition(k - 1), sys_.process_cov(k - 1)
        N, Np = M.shape[:2]
        bb: Any = 0.0
        if not (np.isscalar(b) and b == 0.0):
            bb = np.broadcast_to(np.asarray(b)[:, None, :], (N, Np, n)).reshape(-1, n)
        Mf, Pf = shift_predict(M.reshape(-1, nx), P.reshape(-1, nx, nx), A, Qd, bb)
        Mf, Pf = Mf.reshape(N, Np, nx), Pf.reshape(N, Np, nx, nx)
        h, c, r = self._window_row(k)
        d = self.discrete[h]
        assert d is not None  # checked when the filter is built
        vals, probs = d
        J = vals.size
        H = np.tile(c, self.ell + 1)  # (n_x,): C_h applied to the window sum
        u = Pf @ H  # (N, Np, n_x)  P^- H^T
        s0 = np.maximum(u @ H, 0.0)  # (N, Np)  H P^- H^T
        base = Mf @ H  # (N, Np)
        U = rng.random((N, Np, 2))
        tau = self.channel.threshold
        cls = _classify(y[:, 0], np.full(N, tau), np.full(N, np.inf))
        inter, lower = np.flatnonzero(cls == _INTERIOR), np.flatnonzero(cls == _LOWER)
        with np.errstate(divide="ignore"):
            logpi = np.log(probs)
        sds = np.sqrt(vals[:, None, None] ** 2 * s0[None] + r)  # (J, N, Np)
        comps = np.zeros((J, N, Np))
        for j in range(J):
            mean = vals[j] * base
            if inter.size:
                zz = (y[inter, 0][:, None] - mean[inter]) / sds[j, inter]
                comps[j, inter] = -0.5 * zz * zz - np.log(sds[j, inter]) - _LOG_SQRT_2PI
            if lower.size:
                comps[j, lower] = log_ndtr((tau - mean[lower]) / sds[j, lower])
            comps[j] += logpi[j]
        logw = logsumexp(comps, axis=0)
        missing = cls == _MISSING
        logw[missing] = 0.0
        with np.errstate(invalid="ignore"):
            cum = np.cumsum(np.exp(comps - logw[None]), axis=0)
        jsel = np.minimum((U[None, ..., 0] >= cum).sum(0), J - 1)  # (N, Np)
        lam = vals[jsel]
        sd = np.take_along_axis(sds, jsel[None], axis=0)[0]
        z = np.broadcast_to(y[:, 0][:, None], (N, Np)).copy()
        if lower.size:
            lm = np.take_along_axis(comps[:, lower], jsel[lower][None], axis=0)[0] - logpi[jsel[lower]]
            z[lower] = _truncated_draw(lam[lower] * base[lower], sd[lower], lm, U[lower, :, 1], -1)
        S = sd * sd
        g = np.where(missing[:, None], 0.0, lam / S)  # (N, Np); 0 where lambda_j = 0 or missing
        innov = np.where(missing[:, None], 0.0, z - lam * base)
        Mn = Mf + (g * innov)[..., None] * u
        Pn = Pf - (g * lam)[..., None, None] * (u[..., :, None] * u[..., None, :])
        return Mn, Pn, logw

    def check_record(self, y2, start):
        with np.errstate(invalid="ignore"):
            bad = y2 < self.channel.threshold - _RTOL_LIMIT * max(1.0, abs(self.channel.threshold))
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValidationError(
                f"y: reading {y2[idx]:.6g} at index {idx} lies below the protocol threshold "
                f"tau = {self.channel.threshold:.6g}"
            )


class _Saturation(_Model):
    """Randomly occurring saturation with missing readings: a three-mode mixture per sensor."""

    optimal = True
    serves = RandomSaturation
    feedthrough = False

    def __init__(self, system, channel: RandomSaturation, censoring):
        super().__init__(system)
        channel.check(system)
        self.channel, self.censoring = channel, censoring
        self.nx, self.m = system.n, system.m
        with np.errstate(divide="ignore"):
            mu, nu = channel.mu, channel.nu
            self.logp = (np.log(mu), np.log((1 - mu) * nu), np.log((1 - mu) * (1 - nu)))
        if censoring is not None:
            censoring.check(system.m)

    def modes(self, rng, k, X, dy):
        return self._saturated_modes(k, _mat(X, self.system.measurement(k).T))

    def _saturated_modes(self, k, cx):
        """The three modes given each particle's unsaturated reading ``cx`` (N, Np, m) (:math:`C_kx_k`; a
        NonlinearSystem's :math:`h(x_k, k)`)."""
        sd = _diag_sigma(self.system, k, "saturated readings")
        return [
            (self.logp[0], saturate(cx, self.channel.level), sd),
            (self.logp[1], cx, sd),
            (self.logp[2], np.zeros_like(cx), sd),
        ]

    def propose(self, rng, k, X, y, b, dy, xp=None, Pp=None):
        r"""Locally optimal proposal :math:`p(x_k \mid x_{k-1}, y_k)` for the three-mode channel.

        Given :math:`x_{k-1}`, :math:`x_k \sim N(\mu, Q_d)`, :math:`\mu = A_{k-1}x_{k-1} + B^u_ku_k`, and
        sensor i reads through :math:`c_i = C_ix_k` only. The sensors are taken in sequence (diagonal R):
        with :math:`c_i \mid x_{k-1}, c_{<i} \sim N(m, s^2)` (the running Gaussian of
        :func:`_condition_in_sequence`, here with no latent noise), :math:`c_i` is drawn from its posterior
        given :math:`y_i`, a finite mixture whose pieces have closed-form masses :math:`M_j` and draws
        (:math:`S = s^2 + r`, :math:`m' = m + \tfrac{s^2}{S}(y - m)`, :math:`v' = s^2r/S`, u the level,
        :math:`\pi_{sat} = \mu_i`, :math:`\pi_{lin} = (1-\mu_i)\nu_i`, :math:`\pi_0 = (1-\mu_i)(1-\nu_i)`;
        an uncensored reading y):

        .. math::

            \begin{array}{lll}
            \text{noise only} & M = \pi_0N(y; 0, r) & c \sim N(m, s^2) \\
            \text{linear} & M = \pi_{lin}N(y; m, S) & c \sim N(m', v') \\
            \text{saturated}, c \le -u & M = \pi_{sat}\Phi(\tfrac{-u-m}{s})N(y; -u, r) & c \sim TN(m, s^2; (-\infty, -u]) \\
            \text{saturated}, |c| < u & M = \pi_{sat}N(y; m, S)\,P_{(-u,u)}(m', v') & c \sim TN(m', v'; (-u, u)) \\
            \text{saturated}, c \ge u & M = \pi_{sat}\Phi(\tfrac{m-u}{s})N(y; u, r) & c \sim TN(m, s^2; [u, \infty))
            \end{array}

        (the pieces of :mod:`~tobitkf.filters.adf_saturation`). A piece is chosen with probability
        :math:`M_j/\sum M`, c drawn from it, then :math:`x_k \mid c` (Gaussian); the incremental weight is
        :math:`\sum_jM_j = p(y_i \mid x_{k-1}, c_{<i})`. A reading censored below at l (:math:`y^* \le l`)
        changes the masses to :math:`\pi_0\Phi(l/\sqrt r)`, :math:`\pi_{lin}\Phi((l-m)/\sqrt S)` (c drawn
        through a truncated-normal draw of :math:`y^*`, as :func:`_gaussian_proposal`),
        :math:`\pi_{sat}\Phi(\tfrac{-u-m}{s})\Phi(\tfrac{l+u}{\sqrt r})`,
        :math:`\pi_{sat}\Phi(\tfrac{m-u}{s})\Phi(\tfrac{l-u}{\sqrt r})`; the middle saturated piece (a
        bivariate normal mass) is replaced by its unbiased one-draw estimate
        :math:`\pi_{sat}P_{(-u,u)}(m, s^2)\Phi((l-c)/\sqrt r)`, :math:`c \sim TN(m, s^2; (-u, u))` (a random
        weight: still properly weighted); above, mirrored. A missing (NaN) reading leaves
        :math:`c_i` free, weight 1. For one sensor and an uncensored reading this is exactly
        :math:`p(x_k \mid x_{k-1}, y_k)` with weight :math:`p(y_k \mid x_{k-1})`; for several, the GHK
        sequence (the weight is unbiased for :math:`p(y_k \mid x_{k-1})`).

        Returns (X_new (N, Np, n), log incremental weight (N, Np)).
        """
        sys_ = self.system
        mu = _shifted(_mat(X, sys_.transition(k - 1).T), b)
        N, Np, n = mu.shape
        m = self.m
        lo, hi = self.limits(k)
        cls = _classify(y, lo, hi)
        rv = _diag_sigma(sys_, k, "saturated readings") ** 2
        U = rng.random((N, Np, m, 3))
        Z = rng.standard_normal((N, Np, m))
        eps = rng.standard_normal((N, Np, n))
        level = self.channel.level
        lps, lpl, lp0 = (self.logp[0], self.logp[1], self.logp[2])

        def reading(l, kind, rows, p, sd):
            return _saturation_pieces(
                kind,
                y[rows, l][:, None],
                p,
                sd,
                rv[l],
                level[l],
                lo[l],
                hi[l],
                (lps[l], lpl[l], lp0[l]),
                U[rows, :, l],
                Z[rows, :, l],
            )

        return _condition_in_sequence(
            mu, sys_.process_cov(k - 1), sys_.measurement(k), 0.0, np.zeros((1, m)), cls, reading, eps
        )


def _lognorm(y, mean, var):
    return -0.5 * (y - mean) ** 2 / var - 0.5 * np.log(var) - _LOG_SQRT_2PI


def _log_interval(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    r""":math:`\log(\Phi(b) - \Phi(a))` for :math:`a \le b`, stable in both tails (mirrored to :math:`a \le 0`)."""
    flip = a > 0
    a2, b2 = np.where(flip, -b, a), np.where(flip, -a, b)
    la, lb = log_ndtr(a2), log_ndtr(b2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return lb + np.log1p(-np.exp(la - lb))


def _interval_z(a: np.ndarray, b: np.ndarray, log_mass: np.ndarray, u: np.ndarray) -> np.ndarray:
    r"""A standard normal draw truncated to :math:`[a, b]` by inversion in log space,
    :math:`z = \Phi^{-1}(\Phi(a) + u(\Phi(b) - \Phi(a)))` (mirrored to :math:`a \le 0`; ``log_mass`` from
    :func:`_log_interval`)."""
    flip = a > 0
    a2, b2 = np.where(flip, -b, a), np.where(flip, -a, b)
    with np.errstate(divide="ignore"):
        z = ndtri_exp(np.logaddexp(log_ndtr(a2), np.log(u) + log_mass))
    z = np.clip(z, a2, b2)
    return np.where(flip, -z, z)


def _saturation_pieces(kind, y, m, s, r, u, lo, hi, logpi, U, Z):
    """The five pieces of one saturated sensor's posterior of c (see ``_Saturation.propose``): a draw of c
    and the log of the total mass, for the prior c ~ N(m, s^2) (m (R, Np), s (R, 1)) and readings y (R, 1)."""
    lps, lpl, lp0 = logpi
    s = np.maximum(s, 1e-150)  # s = 0: c is m itself (the limits of the pieces below)
    S = s * s + r
    sS, sr = np.sqrt(S), np.sqrt(r)
    gk = s * s / S
    sv = np.sqrt(s * s * r / S)
    la, lb = log_ndtr((-u - m) / s), log_ndtr((m - u) / s)  # Prob(c <= -u), Prob(c >= u)
    c_low = _truncated_draw(m, s, la, U[..., 1], -1)
    c_high = _truncated_draw(m, s, lb, U[..., 1], +1)
    full = np.broadcast_to
    if kind == _INTERIOR:
        mp = m + gk * (y - m)
        am, bm = (-u - mp) / sv, (u - mp) / sv
        lmid = _log_interval(am, bm)
        lin = _lognorm(y, m, S)
        logs = [
            full(lp0 + _lognorm(y, 0.0, r), m.shape),
            lpl + lin,
            lps + la + _lognorm(y, -u, r),
            lps + lin + lmid,
            lps + lb + _lognorm(y, u, r),
        ]
        draws = [m + s * Z, mp + sv * Z, c_low, mp + sv * _interval_z(am, bm, lmid, U[..., 1]), c_high]
    else:
        side = -1 if kind == _LOWER else +1
        t = lo if side < 0 else hi

        def tail(v):  # log Prob(v + noise beyond the limit t)
            return log_ndtr((t - v) / sr) if side < 0 else log_ndtr((v - t) / sr)

        ll = log_ndtr((t - m) / sS) if side < 0 else log_ndtr((m - t) / sS)
        ystar = _truncated_draw(m, sS, ll, U[..., 1], side)
        am, bm = (-u - m) / s, (u - m) / s
        lmid = _log_interval(am, bm)
        c_mid = m + s * _interval_z(am, bm, lmid, U[..., 2])
        logs = [
            full(lp0 + tail(0.0), m.shape),
            lpl + ll,
            lps + la + tail(-u),
            lps + lmid + tail(c_mid),
            lps + lb + tail(u),
        ]
        draws = [m + s * Z, m + gk * (ystar - m) + sv * Z, c_low, c_mid, c_high]
    L = np.stack(logs)  # (5, R, Np)
    tot = logsumexp(L, axis=0)
    with np.errstate(invalid="ignore"):
        P = np.where(np.isfinite(tot), np.exp(L - tot), 0.0)
    j = np.minimum((U[None, ..., 0] >= np.cumsum(P, axis=0)).sum(0), 4)
    c = np.take_along_axis(np.stack(draws), j[None], axis=0)[0]
    return np.where(np.isfinite(c), c, m), tot  # a non-finite draw only where no piece explains y


def channel_log_likelihood(channel: Channel, k: int, y: np.ndarray, mu: np.ndarray, sd: np.ndarray) -> np.ndarray:
    r"""The log-likelihood of the readings ``y`` (N, m) (NaN: missing, no term) at step ``k`` for each particle,
    :math:`\sum_l \log p(y_l \mid y^*_l \sim N(\mu_l, s_l^2))` by the channel's ``reading_log_likelihood``:
    ``mu`` (N, Np, m) the particles' latent means, ``sd`` (m,) the noise standard deviations. Returns (N, Np)."""
    N, Np, m = mu.shape
    out = np.zeros((N, Np))
    for l in range(m):
        rows = np.flatnonzero(~np.isnan(y[:, l]))
        if rows.size == 0:
            continue
        yy = np.repeat(y[rows, l], Np)
        ll = channel.reading_log_likelihood(yy, mu[rows, :, l].ravel(), np.full(yy.size, sd[l]), k, l)
        out[rows] += np.asarray(ll, dtype=float).reshape(rows.size, Np)
    return out


def _flatten(channel: Any) -> list:
    if channel is None:
        return []
    if isinstance(channel, (list, tuple)):
        out = []
        for c in channel:
            out.extend(_flatten(c))
        return out
    return [channel]


def region_reader(channel: Channel, k: int, y: np.ndarray, U: np.ndarray):
    r"""The reading classes (N, m) and the ``reading`` of :func:`_condition_in_sequence` for a channel with a
    ``region``: an exact reading (``lo == hi``) conditions on its value, an interval one on a draw of :math:`y^*`
    from the normal truncated to it (by the uniforms ``U`` (N, Np, m); weight its mass)."""
    N, m = y.shape
    lo, hi = np.full((N, m), np.nan), np.full((N, m), np.nan)
    cls = np.full((N, m), _MISSING, dtype=np.int8)
    for l in range(m):
        rows = ~np.isnan(y[:, l])
        if rows.any():
            lo[rows, l], hi[rows, l] = channel.region(y[rows, l], k, l)
            cls[rows, l] = np.where(lo[rows, l] == hi[rows, l], _INTERIOR, _LOWER)  # exact / an interval

    def reading(l, kind, rows, p, sd):
        if kind == _INTERIOR:
            return _exact_reading(lo[rows, l][:, None], p, sd)
        a, bb = (lo[rows, l][:, None] - p) / sd, (hi[rows, l][:, None] - p) / sd
        lm = _log_interval(a, bb)
        return p + sd * _interval_z(a, bb, lm, U[rows, :, l]), lm

    return cls, reading


class _Contract(_Model):
    r"""A channel of the measurement contract (:mod:`tobitkf.channels.base`): the reading of channel l is a
    function of :math:`y^*_l = C_lx + D_lu + v_l`; its weight is the channel's ``reading_log_likelihood`` of the
    particle's latent mean and the noise's standard deviation. A channel with a ``region`` (an interval per
    reading) also has the locally optimal proposal: the channels in sequence, an exact reading conditioned on
    its value, an interval one on a draw of :math:`y^*` from the normal truncated to it (weight its mass)."""

    def __init__(self, system: LinearSystem, channel: Channel):
        super().__init__(system)
        channel.check(system)
        self.channel = channel
        self.nx, self.m = system.n, system.m
        self.optimal = type(channel).region is not Channel.region

    @property
    def label(self) -> str:
        return type(self.channel).__name__

    def log_likelihood(self, rng, k, X, y, dy):
        mu = _shifted(_mat(X, self.system.measurement(k).T), dy)
        sd = _diag_sigma(self.system, k, f"{type(self.channel).__name__} readings")
        return channel_log_likelihood(self.channel, k, y, mu, sd)

    def propose(self, rng, k, X, y, b, dy, xp=None, Pp=None):
        sys_ = self.system
        mu = _shifted(_mat(X, sys_.transition(k - 1).T), b)
        N, Np, n = mu.shape
        r = _diag_sigma(sys_, k, f"{type(self.channel).__name__} readings") ** 2
        cls, reading = region_reader(self.channel, k, y, rng.random((N, Np, self.m)))
        eps = rng.standard_normal((N, Np, n))
        return _condition_in_sequence(
            mu, sys_.process_cov(k - 1), sys_.measurement(k), dy, r[None, :], cls, reading, eps
        )

    def check_record(self, y2: np.ndarray, start: int) -> None:
        self.channel.check(self.system, start - 1 + y2.shape[1])
        self.channel.check_readings(y2, start=start)


def _build_model(system: LinearSystem, channel: Any, censoring: Any) -> _Model:
    pieces = _flatten(channel) + ([] if censoring is None else [censoring])
    for p in pieces:
        if not isinstance(p, Channel):
            raise ValidationError(
                f"channel: expected Censoring, RiceFading, ProtocolChannel, RandomSaturation, Quantizer or "
                f"other tobitkf.Channel pieces, got {type(p).__name__}"
            )
    cens = [p for p in pieces if isinstance(p, Censoring)]
    drawers = [p for p in pieces if not isinstance(p, Censoring)]
    if len(cens) > 1:
        raise ValidationError(
            "censoring: expected at most one Censoring piece (stack several regions as channels, tobitkf.multi_region)"
        )
    if len(drawers) > 1:
        raise ValidationError(
            f"channel: expected at most one reading model, got {', '.join(type(d).__name__ for d in drawers)}"
        )
    c = cens[0] if cens else None
    if not drawers:
        return _Linear(system, c)
    d = drawers[0]
    model = next((_Model._served[t] for t in type(d).__mro__ if t in _Model._served), None)
    if model is not None:
        return model.build(system, d, c)
    if c is not None:
        raise ValidationError(
            f"censoring: {type(d).__name__} is a reading model of its own; give no Censoring with it (a channel "
            "of your own includes its limits in its region)"
        )
    if not d.supports("likelihood"):
        raise ValidationError(
            f"channel: {type(d).__name__} supplies neither region() nor reading_moments() (tobitkf.channels.base), "
            "which the particle filter needs"
        )
    return _Contract(system, d)


#: model class other than LinearSystem -> ``builder(system, channel, censoring)`` of its particle-filter model;
#: filled by the module that serves it (tobitkf.filters.particle_nonlinear for NonlinearSystem)
SYSTEM_MODELS: dict[type, Any] = {}
