r"""The filters of any channel that supplies the measurement contract (:mod:`tobitkf.channels.base`).

Not in the sources. Two estimators are written once here for every channel whose reading is a function of
the linear latent reading :math:`y^*_k = C_kx_k + D_ku_k + v_k` (R diagonal, channels in sequence):

* :class:`AssumedDensityFilter` (the assumed-density filter, Maybeck 1982 §12.7; Minka 2001): for one
  channel l with prior :math:`x \sim N(\bar x, \bar P)`, :math:`c = C_k(l)`, the latent reading is
  :math:`y^* \sim N(\mu, s^2)`, :math:`\mu = c\bar x + d`, :math:`s^2 = c\bar Pc^T + r`, jointly Gaussian
  with x; the channel says what its reading tells of :math:`y^*` (``reading_moments``: the posterior
  mean :math:`E[y^* \mid y]` and variance :math:`V = \mathrm{Var}[y^* \mid y]`, from the interval of its
  ``region`` by default), and the laws of total expectation and variance give the exact posterior
  moments of x (the projection formula)

  .. math::

      \hat x = \bar x + K\,(E[y^* \mid y] - \mu), \qquad P = \bar P - K\,(s^2 - V)\,K^T, \qquad
      K = \bar Pc^T/s^2,

  the shared Gaussian update (:func:`~tobitkf.filters.core.measurement_update`) with :math:`H_0 = c`,
  noise r, the observed value :math:`E[y^* \mid y]` and the retained variance V, in each covariance form.
  For a channel that has a named form (censoring: :class:`~tobitkf.AssumedDensityTobitFilter`; Rice
  fading: :class:`~tobitkf.FadingAssumedDensityFilter`; the protocol channel:
  :class:`~tobitkf.ProtocolAssumedDensityFilter`; random saturation:
  :class:`~tobitkf.SaturationAssumedDensityFilter`) ``AssumedDensityFilter(system, channel)`` builds that
  class; a subclass of :class:`AssumedDensityFilter` always runs the generic update (for censoring it
  equals the named form to rounding, tested).
* :class:`TobitFilter` (the Tobit Kalman filter's update for any channel): every statistic at the
  *prior mean* as the TKF takes them (Miller 2015, Assumption A1, (3.35)); the channel gives the
  reading's mean :math:`E[y]`, its slope :math:`g = \partial E[y]/\partial\mu` and its variance
  :math:`\mathrm{Var}[y]` under :math:`y^* \sim N(\mu, r)`, :math:`\mu = C\bar x + Du`
  (``reading_statistics``), and the update is the Kalman update with :math:`\hat y = E[y]`,
  :math:`H = \mathrm{diag}(g)C` and noise :math:`\mathrm{diag}(\mathrm{Var}[y])`:

  .. math::

      K = \bar PH^T(H\bar PH^T + \mathrm{diag}(\mathrm{Var}[y]))^{-1}, \qquad
      \hat x = \bar x + K(y - E[y]), \qquad P = (I - KH)\bar P.

  For censoring :math:`g = \Phi(\beta) - \Phi(\alpha) = E(\mathbf p)` and :math:`\mathrm{Var}[y]` the
  censored variance: the TKF with ``noise_term="total_variance"`` (tested to 1e-12); for a quantizer
  :math:`g` is the density at the thresholds times the width, the statistically linearised quantizer.
  With ``linearization="predictive"`` (ours) the statistics are taken under the whole predictive law
  :math:`y^* \sim N(\mu, s^2)`, :math:`s^2 = c\bar Pc^T + r`: by Stein's lemma
  :math:`\mathrm{Cov}(x, y) = \bar Pc^Tg`, so with :math:`H = gc` and the noise
  :math:`\mathrm{Var}[y] - g^2c\bar Pc^T \ge g^2r \ge 0` the Kalman update is the linear minimum-MSE
  update of x given the reading under the Gaussian prediction (per channel; channels taken as
  uncorrelated given the prediction).

Time convention (package-wide): :math:`x_0 \sim N(\bar x_0, P_0)` is the prior, :math:`y_1` is at
index 0, result row k-1 holds :math:`\hat x_{k|k}`, :math:`P_{k|k}` and the prediction.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from .._validation import ValidationError, check_instance, diagonal_sigma
from ..channels.base import Channel, section_of
from ..models.linear import LinearSystem
from ._backend import numba_available
from ._outputs import loop_input
from .assumed_density import AssumedDensityFamily
from .core import (
    COVARIANCE_FORMS,
    MeasurementPrediction,
    check_keywords,
    measurement_update,
)
from .kalman import LinearGaussianFamily
from .likelihood import filter_log_likelihood
from .registry import family_entry, register
from .smoothing import SmoothingMethods

__all__ = ["AssumedDensityFilter", "TobitFilter", "channel_update", "register_named_form", "named_forms"]

_OPTIONS = {"covariance_update": COVARIANCE_FORMS}
LINEARIZATIONS = ("prior_mean", "predictive")
_TINY = np.finfo(np.float64).tiny
_WHO, _WHY = "the Tobit-type filter", "independent channels"

# --------------------------------------------------------------------------- named forms
_NAMED: dict[str, Callable[..., Any]] = {}


def register_named_form(section: str, factory: Callable[..., Any]) -> None:
    """Make ``AssumedDensityFilter(system, channel, **options)`` build ``factory(system, parts, **options)``
    when the channel's main piece (its one piece other than a :class:`~tobitkf.Censoring`, else the
    censoring) is of ``section``; ``parts`` maps section name -> piece."""
    _NAMED[section] = factory


def named_forms() -> dict[str, Callable[..., Any]]:
    """The sections whose assumed-density filter is a named class, and their factories (a copy)."""
    return dict(_NAMED)


def _adtf(system, parts, **o):
    from .assumed_density import AssumedDensityTobitFilter

    _only(parts, {"censoring"})
    return AssumedDensityTobitFilter(system, parts["censoring"], **o)


def _fadf(system, parts, **o):
    from .adf_fading import FadingAssumedDensityFilter

    _only(parts, {"fading", "censoring"})
    return FadingAssumedDensityFilter(system, parts["fading"], parts.get("censoring"), **o)


def _padf(system, parts, **o):
    from .adf_protocol import ProtocolAssumedDensityFilter

    _only(parts, {"protocol"})
    return ProtocolAssumedDensityFilter(system, parts["protocol"], **o)


def _sadf(system, parts, **o):
    from .adf_saturation import SaturationAssumedDensityFilter

    _only(parts, {"saturation"})
    return SaturationAssumedDensityFilter(system, parts["saturation"], **o)


for _section, _factory in (("censoring", _adtf), ("fading", _fadf), ("protocol", _padf), ("saturation", _sadf)):
    register_named_form(_section, _factory)


def _only(parts: dict[str, Any], allowed: set[str]) -> None:
    extra = sorted(set(parts) - allowed)
    if extra:
        raise ValidationError(
            f"channel: the {'/'.join(sorted(allowed))} filter takes no {extra[0]} piece; got {', '.join(sorted(parts))}"
        )


def _pieces(channel: Any) -> list[Any]:
    return list(channel) if isinstance(channel, (list, tuple)) else ([] if channel is None else [channel])


def _parts(channel: Any) -> dict[str, Any] | None:
    """Section -> piece of a channel made only of registered pieces (None if any piece is unregistered)."""
    out: dict[str, Any] = {}
    for piece in _pieces(channel):
        sec = section_of(piece)
        if sec is None:
            return None
        if sec in out:
            raise ValidationError(f"channel: two {sec} pieces; expected at most one of each")
        out[sec] = piece
    return out


def _contract_channel(channel: Any, hook: str, what: str) -> Channel:
    pieces = _pieces(channel)
    if len(pieces) != 1:
        raise ValidationError(
            f"channel: {what} takes one channel piece that supplies the measurement contract, got "
            f"{', '.join(type(p).__name__ for p in pieces) or 'none'}"
        )
    (piece,) = pieces
    check_instance(piece, Channel, "channel")
    if not piece.supports(hook):
        need = {"moments": "region() or reading_moments()", "statistics": "reading_statistics()"}[hook]
        raise ValidationError(
            f"channel: {type(piece).__name__} supplies no {need} (see tobitkf.channels.base), which {what} needs"
        )
    return piece


# --------------------------------------------------------------------------- the generic update
def channel_update(
    channel: Channel,
    k: int,
    l: int,
    x: np.ndarray,
    P: np.ndarray,
    S: np.ndarray | None,
    y: np.ndarray,
    c: np.ndarray,
    r: Any,
    *,
    dy: Any = 0.0,
    form: str = "standard",
    compiled: tuple[tuple[Any, ...], np.ndarray] | None = None,
):
    r"""The assumed-density update of channel ``l`` of ``channel`` at step ``k`` (the module docstring), batched.

    Parameters
    ----------
    channel : Channel
        Supplies ``reading_moments`` (or ``region``).
    x : (N, n) ; P : (N or 1, n, n) ; S : (N or 1, n, n) or None (square-root factor)
    y : (N,) the channel's readings (NaN = missing: no update)
    c : (n,) its row of C ; r : its noise variance (>= 0), scalar or (N,) ; dy : (N,) or 0, the feed-through
    form : {"standard", "joseph", "square_root"}
    compiled : (family, par), optional
        Take the moments from the compiled block of the family ``family`` (a kind,
        :func:`~tobitkf.filters._compiled_moments.channel_kind`) with this channel's parameters
        ``par`` (K,) (:func:`~tobitkf.filters._compiled_moments.family_array`, the function the compiled loop
        runs) instead of ``reading_moments``: :math:`E[y^* \mid y] = \mu + \alpha s^2`,
        :math:`V = s^2 - \beta s^4`. Needs numba.

    Returns
    -------
    x, P, S : the posterior (S None unless ``form="square_root"``)
    log_likelihood : (N,) :math:`\log p(y \mid \text{the Gaussian prior})`, 0 for a missing reading. A degenerate
        latent (:math:`s^2` not above the smallest normal number) is not updated; its term is 0 if the point
        :math:`\mu` lies in the reading's region, else ``-inf`` (0 for a channel without a region).
    """
    N = x.shape[0]
    mu = np.broadcast_to(x @ c + dy, (N,))
    rv = np.asarray(r, dtype=float)
    cPc = np.broadcast_to(np.einsum("rij,i,j->r", P, c, c), (N,))
    s2 = cPc + rv
    ok = s2 > _TINY
    s = np.where(ok, np.sqrt(np.where(ok, s2, 1.0)), 1.0)
    has = ~np.isnan(y)
    valid = ok & has
    obs = np.full(N, np.nan)
    V = np.zeros(N)
    ll = np.zeros(N)
    if compiled is not None:
        family, par = compiled
        alpha, beta, ll = _compiled_moments(family, par, y, has, mu, cPc, np.broadcast_to(rv, (N,)))
        obs = np.where(valid, mu + alpha * s2, np.nan)
        V = np.where(valid, s2 - beta * s2 * s2, 0.0)
    elif valid.any():
        o, v, lp = channel.reading_moments(y[valid], mu[valid], s[valid], k, l)
        obs[valid], V[valid], ll[valid] = o, v, lp
    degenerate = ~ok & has
    if compiled is None and degenerate.any() and channel.supports("likelihood") and _has_region(channel):
        lo, hi = channel.region(y[degenerate], k, l)
        md = mu[degenerate]
        ll[degenerate] = np.where((lo <= md) & (md <= hi), 0.0, -np.inf)
    if not valid.any():
        return x, P, S, ll
    noise = np.full((1, 1), float(rv)) if rv.ndim == 0 else np.broadcast_to(rv, (N,))[:, None]
    mp = MeasurementPrediction(
        expected=mu[:, None],
        H0=c[None, :],
        noise=noise,
        observed=obs[:, None],
        valid=valid[:, None],
        retained=V[:, None] if V.any() else None,
    )
    xn, Pn, Sn, _, _ = measurement_update(x, P, S, obs[:, None], mp, form)
    return xn, Pn, Sn, ll


def _compiled_moments(family, par, y, has, mu, cPc, r):
    """``(alpha, beta, log_likelihood)`` of the compiled block ``family`` for the readings ``y`` (N,)."""
    from ._compiled_moments import INTERIOR, MISSING, family_array

    inf = np.full(y.shape, np.inf)
    cls = np.where(has, INTERIOR, MISSING).astype(np.int8)
    f = loop_input  # writable: numba types read-only arrays (broadcast views) apart, one compile more each
    alpha, beta, ll, _, _ = family_array(family, f(y), cls, f(mu), f(cPc), f(r), -inf, inf, f(par), 0)
    return alpha, beta, ll


def _has_region(channel: Channel) -> bool:
    return type(channel).region is not Channel.region


class _ContractChecks:
    """Record and reading checks of a contract channel (shared by the two generic filters)."""

    channel: Channel
    system: LinearSystem
    m: int

    def _check_record(self, y2, u2, k0, name="y"):
        self.system.check_horizon(k0 + y2.shape[1])
        self.channel.check(self.system, k0 + y2.shape[1])
        self.channel.check_readings(y2, start=k0 + 1, name=name)

    def _check_reading(self, k: int, y: np.ndarray, options) -> None:
        self.channel.check_readings(y[:, None], start=k)


class AssumedDensityFilter(_ContractChecks, SmoothingMethods, AssumedDensityFamily, LinearGaussianFamily):
    r"""Assumed-density filter for any channel that supplies the measurement contract (module docstring).

    Parameters
    ----------
    system : LinearSystem
        The model; R diagonal (the channels are updated in sequence), entries >= 0.
    channel : Channel or sequence of Channel
        A channel with a ``region`` or ``reading_moments`` (:class:`~tobitkf.Quantizer`, a channel of your
        own, ...), or one with a named form (:class:`~tobitkf.Censoring`, :class:`~tobitkf.RiceFading`
        with an optional Censoring, :class:`~tobitkf.ProtocolChannel`, :class:`~tobitkf.RandomSaturation`),
        for which this builds the named class with the ``options`` it takes.
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        The covariance form of the shared update: :math:`\bar P - K(s^2 - V)K^T`; Joseph
        :math:`(I - Kc)\bar P(I - Kc)^T + KrK^T + KVK^T`; the square root (QR array form).
    backend : {"auto", "numba", "numpy"}, default "auto"
        ``"auto"`` runs :meth:`filter` through the compiled loop of the assumed-density filters
        (:mod:`tobitkf.filters._compiled_loop`) when numba is installed, the channel names its compiled moments
        (its ``compiled_moments`` and ``compiled_parameters``: the :class:`~tobitkf.Quantizer` does) and the
        case is covered (the standard covariance form, a time-invariant system, R constant), else the numpy
        loop; ``"numba"`` requires the compiled loop (:class:`~tobitkf.ValidationError` for a case it does not
        cover); ``"numpy"`` never uses it. Both give the same numbers to rounding (tested to 1e-12). Where the
        numpy loop runs (:meth:`step`, the Joseph and square-root forms, a time-varying system) a channel's
        compiled moments come from the same compiled function as the loop's unless ``backend="numpy"``.

    Raises
    ------
    ValidationError
        A channel that supplies neither ``region`` nor ``reading_moments``, more than one piece of a channel
        without a named form, a non-diagonal or negative R, an unknown option.

    Notes
    -----
    Readings the channel cannot give are refused (its ``check_readings``) in :meth:`filter`, :meth:`step`
    and :meth:`update`. Extras: ``log_likelihood`` (..., T), the per-step term
    :math:`\ell_k = \sum_l \log p(y_k(l) \mid \text{the Gaussian the channel is updated from})` (the
    channel's third ``reading_moments`` output), whose sum is the assumed-density approximation of
    :math:`\log p(y_{1:T})` (:meth:`log_likelihood`), exact for one step from a Gaussian prior and one
    channel. :meth:`smooth` is the RTS smoother over the filter's moments.

    Examples
    --------
    A quantized reading, checked against the named form's arithmetic: with a quantizer of width 1 and no
    noise, a reading 0 from the prior N(0, 1) says :math:`y^* \in [-1/2, 1/2)`:

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.0]], x0=[0.0], P0=[[1.0]])
    >>> out = tk.AssumedDensityFilter(sys, tk.Quantizer(1.0)).filter([[0.0]])
    >>> from scipy.stats import truncnorm
    >>> bool(np.isclose(out.cov[0, 0, 0], truncnorm(-0.5, 0.5).var(), rtol=1e-10))
    True

    References
    ----------
    .. [1] P. S. Maybeck, *Stochastic Models, Estimation and Control*, vol. 2, Academic Press, 1982, §12.7.
    .. [2] T. P. Minka, *A family of algorithms for approximate Bayesian inference*, PhD thesis, MIT, 2001, §3.1.
    """

    _name = "AssumedDensityFilter"

    def __new__(cls, system: Any = None, channel: Any = None, **options: Any):
        if cls is AssumedDensityFilter:
            parts = _parts(channel)
            if parts:
                main = next((s for s in parts if s != "censoring"), "censoring")
                factory = _NAMED.get(main)
                if factory is not None:
                    return factory(system, parts, **options)
        return super().__new__(cls)

    def __init__(
        self, system: LinearSystem, channel: Any, *, covariance_update: str = "standard", backend: str = "auto"
    ):
        check_instance(system, LinearSystem, "system")
        self.channel = _contract_channel(channel, "moments", "the assumed-density filter")
        self._configure(system, covariance_update, backend)
        self.channel.check(system)

    #: a channel with compiled moments (``compiled_block`` or ``compiled_moments``) runs :meth:`filter` in the
    #: compiled loop
    _compiled_spec = "channel_spec"

    def _compiled_block(self, k: int, m: int) -> tuple[tuple[Any, ...], np.ndarray] | None:
        """``(family, par (m, K))`` of the channel's compiled moments at step ``k`` when the step loop takes them
        (the channel has them, numba is installed, ``backend`` is not ``"numpy"``), else None; ``family`` a kind
        (:func:`~tobitkf.filters._compiled_moments.channel_kind`)."""
        has = getattr(self.channel, "compiled_moments", None) or getattr(self.channel, "compiled_block", None)
        if has is None or self.backend == "numpy" or not numba_available():
            return None
        from ._compiled_moments import channel_kind

        family = channel_kind(self.channel)
        assert family is not None
        par = np.array(self.channel.compiled_parameters(k, 1, m), dtype=np.float64)
        return family, par[0]

    def _project(self, k, xp, Pp, Sp, y, u, **options):
        N, m = y.shape
        C, r = self.system.measurement(k), self._noise_at(k)
        dy = np.broadcast_to(self._feedthrough(k, u), (N, m))
        block = self._compiled_block(k, m)
        x, P, S = xp, Pp, Sp
        ll = np.zeros(N)
        for l in range(m):
            x, P, S, lll = channel_update(
                self.channel,
                k,
                l,
                x,
                P,
                S,
                y[:, l],
                C[l],
                r[l],
                dy=dy[:, l],
                form=self.covariance_update,
                compiled=None if block is None else (block[0], block[1][l]),
            )
            ll += lll
        return x, P, S, {"log_likelihood": ll}

    def _log_likelihood_terms(self, y: Any, *, u: Any, x0: Any, P0: Any, **recorded: Any) -> np.ndarray:
        """The ``log_likelihood`` extras of :meth:`filter` (..., T)."""
        if recorded:
            raise TypeError(f"unexpected keyword argument {next(iter(recorded))!r}")
        return filter_log_likelihood(self, y, u=u, x0=x0, P0=P0)

    def __repr__(self) -> str:
        backend = "" if self.backend == "auto" else f", backend={self.backend!r}"
        return f"AssumedDensityFilter({self.channel!r}, covariance_update={self.covariance_update!r}{backend})"


class TobitFilter(_ContractChecks, SmoothingMethods, LinearGaussianFamily):
    r"""The Tobit Kalman filter's update for any channel that gives its reading's statistics (module docstring).

    Parameters
    ----------
    system : LinearSystem
        The model; R diagonal with positive entries.
    channel : Channel
        A channel with ``reading_statistics`` (:class:`~tobitkf.Censoring`, :class:`~tobitkf.Quantizer`, a
        channel of your own).
    covariance_update : {"standard", "joseph", "square_root"}, default "standard"
        The covariance form of the shared Kalman update with :math:`H = \mathrm{diag}(g)C`.
    linearization : {"prior_mean", "predictive"}, default "prior_mean"
        ``"prior_mean"``: the statistics at the prior mean with the noise's variance r, as the TKF (Miller
        Assumption A1). Like the TKF's ``"total_variance"`` noise term its gain grows like :math:`1/g` when the
        prior mean sits where the reading hardly moves (a coarse quantizer's cell centre: small :math:`g`,
        small :math:`\mathrm{Var}[y]`), and a reading in the next cell then throws the estimate far off
        (a scalar AR(1) state of standard deviation 1 read with noise 0.3 through quantizers of width 2 and 3:
        MSE 78x and 445x the particle filter's, where the assumed-density filter is at 1.00x). ``"predictive"`` (ours): the statistics under the predictive law
        of :math:`y^*` (the module docstring), the linear minimum-MSE update; it does not have this failure.

    Raises
    ------
    ValidationError
        A channel without ``reading_statistics``, a non-diagonal or non-positive R, an unknown option.

    Notes
    -----
    Extras: ``expected_y`` (..., T, m), the reading's mean :math:`E[y]` at the prior, and ``slope``
    (..., T, m), :math:`g = \partial E[y]/\partial\mu` (for censoring the TKF's :math:`E(\mathbf p)`).
    :meth:`log_likelihood` gives the assumed-density likelihood of the same model (system and channel),
    as the TKF does; :meth:`smooth` the RTS smoother over this filter's linearisation.

    For a quantizer the statistics are sums over its cells, as in the multi-region TKF (Miller §6.6), but
    :func:`~tobitkf.multi_region` with the cells as windows is another model: there each window is a sensor of
    its own noise that passes :math:`y^*` through inside its window, while a quantized reading gives the cell
    alone (no exact value in any cell) and one noise decides every threshold; so
    ``TobitKalmanFilter(*multi_region(...))`` cannot express a quantizer and this filter is its Tobit-type update.

    Examples
    --------
    With censoring it is the TKF with the exact (total) variance of the censored reading as its noise term:

    >>> import numpy as np, tobitkf as tk
    >>> sys = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    >>> y = np.array([[0.3], [0.0], [0.8]])
    >>> a = tk.TobitFilter(sys, tk.Censoring(lower=0.0)).filter(y).mean
    >>> b = tk.TobitKalmanFilter(sys, tk.Censoring(lower=0.0), noise_term="total_variance").filter(y).mean
    >>> bool(np.allclose(a, b, rtol=0, atol=1e-12))
    True

    References
    ----------
    .. [1] C. I. Miller, *Estimation and Control with Censored Data*, PhD thesis, University of Delaware,
       2015, §3.3.4 (the update it generalises).
    """

    _name = "TobitFilter"
    _filter_doc = """Filter the readings ``y`` (..., T, m) with the Tobit Kalman filter's update for this channel: the
    shared Kalman update with the channel's reading statistics (mean, slope g, variance) as its moments."""
    _filter_raises = "a reading the channel cannot give (refused by its own checks)"

    def __init__(
        self,
        system: LinearSystem,
        channel: Any,
        *,
        covariance_update: str = "standard",
        linearization: str = "prior_mean",
    ):
        check_instance(system, LinearSystem, "system")
        self.channel = _contract_channel(channel, "statistics", "the Tobit-type filter")
        check_keywords(
            {"covariance_update": covariance_update, "linearization": linearization},
            {**_OPTIONS, "linearization": LINEARIZATIONS},
        )
        self.linearization = linearization
        self.channel.check(system)
        self._sigma = None if system.R.varying else diagonal_sigma(system.measurement_cov(1), who=_WHO, why=_WHY)
        self._setup_system(system)
        self.covariance_update = covariance_update

    def _measurement(self, k, xp, Pp, y, u, carry, **options):
        sigma = (
            self._sigma
            if self._sigma is not None
            else diagonal_sigma(self.system.measurement_cov(k), f"R({k})", who=_WHO, why=_WHY)
        )
        C = self.system.measurement(k)
        mu = xp @ C.T + self._feedthrough(k, u)
        N, m = mu.shape
        E, g, V = np.empty((N, m)), np.empty((N, m)), np.empty((N, m))
        if self.linearization == "predictive":
            cPc = np.broadcast_to(np.einsum("li,rij,lj->rl", C, Pp, C), (N, m))
            std = np.sqrt(cPc + sigma**2)
        else:
            std = np.broadcast_to(sigma, (N, m))
        for l in range(m):
            E[:, l], g[:, l], V[:, l] = self.channel.reading_statistics(mu[:, l], np.ascontiguousarray(std[:, l]), k, l)
        noise = np.maximum(V - g * g * cPc, 0.0) if self.linearization == "predictive" else V
        mp = MeasurementPrediction(
            expected=E, H0=C, scale=g, noise=noise, valid=~np.isnan(y), extras={"expected_y": E, "slope": g}
        )
        return mp, carry

    def _log_likelihood_terms(self, y: Any, *, u: Any, x0: Any, P0: Any, **recorded: Any) -> np.ndarray:
        """The assumed-density terms (..., T) of this filter's model (system and channel)."""
        if not self.channel.supports("moments"):
            raise ValidationError(
                f"channel: {type(self.channel).__name__} supplies no region() or reading_moments(), "
                "which the likelihood needs"
            )
        adf = _GenericADF(self.system, self.channel)
        return adf._log_likelihood_terms(y, u=u, x0=x0, P0=P0, **recorded)

    def __repr__(self) -> str:
        lin = "" if self.linearization == "prior_mean" else f", linearization={self.linearization!r}"
        return f"TobitFilter({self.channel!r}, covariance_update={self.covariance_update!r}{lin})"


class _GenericADF(AssumedDensityFilter):
    """The generic update whatever the channel (no named form)."""


register(
    family_entry(
        AssumedDensityFilter,
        "assumed-density filter of any channel: a named form where one exists, else the channel's moments",
        ("channel",),
        options={"covariance_update": COVARIANCE_FORMS},
    ),
    family_entry(
        TobitFilter,
        "the Tobit Kalman filter's update for any channel with reading statistics (beyond the sources)",
        ("channel",),
        options={"covariance_update": COVARIANCE_FORMS, "linearization": ("prior_mean", "predictive")},
    ),
)
