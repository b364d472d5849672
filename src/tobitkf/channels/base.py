r"""The interface every channel implements: what happens between the sensor and the estimator.

A channel is one small public class that knows how it is **drawn** (the simulator), what a reading
says about the **latent reading** :math:`y^*` (the filters: its Gaussian moments and its likelihood),
and its **options** (the registry of estimators and the sweep files). A class that names its
``section`` registers itself when it is defined, so a channel written outside the package (the
tutorial "Write your own channel") gets the
assumed-density filter :class:`~tobitkf.AssumedDensityFilter`, the Tobit-type filter
:class:`~tobitkf.TobitFilter`, the particle filter, the simulator, the registry and the sweep files
without an edit to any of them.

Simulation
----------
A channel takes part in a simulation at up to three stages, in this order, and every stage has a
do-nothing default so that a channel implements only what it does:

==============================================  ==========================================================
``draw(rng, x, system, noise, inputs)``          the sensor reading that replaces :math:`C_kx_k + D_ku_k + v_k`
                                                 (Rice fading, integral measurements with failures, random
                                                 saturation); returns ``(y_latent, extras)`` or ``None`` for
                                                 the plain linear reading
``censor(y_latent)``                             what a limited sensor reports (Tobit censoring, a
                                                 quantizer, a threshold)
``apply(rng, y, extras)``                        what the network does with the censored reading afterwards
                                                 (scheduling, packet loss)
==============================================  ==========================================================

``check(system, steps)`` is called once, before anything is drawn or filtered, and raises a
:class:`~tobitkf.ShapeError` or :class:`~tobitkf.ValidationError` when the channel does not fit the
system. Arrays: ``x`` is ``(N, T+1, n)`` (x_0..x_T), ``noise`` the ``(N, T, m)`` draw of :math:`v_k`,
``y`` and ``y_latent`` ``(N, T, m)`` (y_1..y_T at indices 0..T-1), ``extras`` a dict of the channel's
own random variables, kept in :attr:`SimulationData.extras <tobitkf.SimulationData.extras>`.

The measurement contract (the filters)
--------------------------------------
For a channel whose reading is a function of the linear latent reading
:math:`y^*_k(l) = C_k(l)x_k + D_k(l)u_k + v_k(l)`, :math:`v_k(l) \sim N(0, R_{ll})` (R diagonal: the
channels are independent given the state), one reading :math:`y` of channel l at step k says
something about :math:`y^*`. Given a Gaussian :math:`y^* \sim N(\mu, s^2)` (the filter's prediction of
the latent reading, noise included), a channel supplies one of

``region(y, k, l)`` → ``(lo, hi)``
    the interval the reading says :math:`y^*` lies in: ``lo == hi`` for an exact reading
    (:math:`y^* = y`), ``lo < hi`` for an interval, infinite ends allowed. This is all most channels
    need (censoring, a quantizer, a dead band, a threshold detector): the two hooks below follow from it.
``reading_moments(y, mean, std, k, l)`` → ``(observed, retained, log_likelihood)``
    the posterior moments :math:`E[y^* \mid y]`, :math:`\mathrm{Var}[y^* \mid y]` and
    :math:`\log p(y)` under :math:`y^* \sim N(\mu, s^2)`. Default from ``region``: an exact reading
    gives :math:`(y, 0, \log N(y; \mu, s^2))`, an interval :math:`[a, b]` the truncated-normal moments
    and :math:`\log(\Phi(\beta) - \Phi(\alpha))`, :math:`\alpha = (a-\mu)/s`, :math:`\beta = (b-\mu)/s`
    (:func:`interval_moments`, stable 40 σ into either tail).
``reading_log_likelihood(y, mean, std, k, l)`` → ``log p(y | y* ~ N(mean, std²))``
    the particle filter's weight of a particle whose latent mean is ``mean`` (``std`` the noise's);
    default from ``region`` (or the third output of ``reading_moments``).

Every array argument is ``(N,)`` (only the rows with a reading: a missing reading, NaN, never reaches
a hook), ``std > 0``, ``k >= 1`` the time index and ``l`` the channel index. From the moments one
generic assumed-density update follows (the projection formula, Maybeck 1982 §12.7): with
:math:`K = \bar Pc^T/s^2`,

.. math::

    \hat x = \bar x + K\,(E[y^* \mid y] - \mu), \qquad P = \bar P - K\,(s^2 - \mathrm{Var}[y^* \mid y])\,K^T

(:class:`~tobitkf.AssumedDensityFilter`). Optional hooks:

``reading_statistics(mean, std, k, l)`` → ``(expected, slope, variance)``
    :math:`E[y]`, :math:`\partial E[y]/\partial\mu` and :math:`\mathrm{Var}[y]` of the *reading* under
    :math:`y^* \sim N(\mu, s^2)`: the statistically linearised (Tobit-type) update of
    :class:`~tobitkf.TobitFilter`, all statistics at the prior mean as the Tobit Kalman filter takes them.
``fisher_information(mean, std, k, l)`` → :math:`I_{\mu\mu}`
    the Fisher information of one reading about :math:`\mu` (the posterior Cramér–Rao bound,
    :func:`~tobitkf.posterior_crlb`).
``check_readings(y, start=1, name="y")``
    raise :class:`~tobitkf.ValidationError` for a reading the channel cannot give (off a quantizer's
    levels, outside censoring limits); ``y`` is ``(..., T, m)`` and row 0 is time ``start``.
``at_limit(y, start=1)``
    the ``(..., T, m)`` mask of readings at a limit of the sensor (reported by the sweeps).

``compiled_block`` (class attribute, default None): the channel's moments compiled, for the compiled loop of
the assumed-density filters. A ``numba.njit`` function (or ``"module:name"`` of one, imported when first needed,
so that importing the channel does not import numba) of the block signature

.. code-block:: python

    block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf)

that updates the runs ``b < nb`` of a block of one channel l: ``y[b]`` the reading and ``cls[b]`` its class
(0 missing: no update, no term; else 1), :math:`\mu` = ``hx[b]`` and :math:`s^2` = ``hph[b] + rb[b]`` (the prior
variance of :math:`c\bar x` and the noise's), ``par`` (K,) the channel's parameters at the step; it writes
``alpha[b]`` :math:`= (E[y^* \mid y] - \mu)/s^2`, ``beta[b]`` :math:`= (s^2 - \mathrm{Var}[y^* \mid y])/s^4`,
``pu[b]`` (1 for a channel without censoring) and adds :math:`\log p(y)` to ``ll[b]``; ``lo``, ``hi``, ``comp``
are unused here and ``glx``, ``glw``, ``buf`` go to the helpers. For a reading that is an interval of
:math:`y^*` one call per run does it all:
``alpha[b], beta[b], lp = interval_update(hx[b], hph[b] + rb[b], lo_b, hi_b, glx, glw, buf)``
(:func:`tobitkf.channels.compiled.interval_update`, the exact and the interval case as :meth:`region` says,
stable 40 σ into the tails), then ``ll[b] += lp``. The block's parameters come from
``compiled_parameters(k, steps, m)`` → an array (1 or ``steps``, m, K) for the steps k..k+steps-1 (default:
none, K = 0). With it :class:`~tobitkf.AssumedDensityFilter` runs :meth:`filter` in the compiled loop (and the
nonlinear assumed-density filter its compiled loop), and takes its moments from the same block in the numpy
loop too (``backend`` as for the other filters); a channel without one runs on the numpy path. The loop's
version for a block is compiled once (about a minute of CPU) and cached on disk under a key made of the hash of the
block's code and of the globals it reads (numbers, arrays, the functions it calls): an edit of the block
compiles it afresh, in-package and outside alike. Alternatively ``compiled_moments`` names one of the package's
blocks (``"censored_block"``, ``"saturation_block"``, ``"protocol_block"`` of
:mod:`tobitkf.filters._compiled_moments`); it takes precedence over ``compiled_block``.

Registration
------------
``section`` (class attribute) names the channel in the registry and in sweep files (``[quantizer]``);
``sweep_options`` maps the keywords a sweep file may give to their kind (``float``, ``int``, a tuple of
allowed values, or ``object``); ``from_options(options, system)`` builds the channel from them (default
``cls(**options)``); ``replaces_censoring = True`` says the channel carries its own limits (a sweep file
then has no ``[censoring]`` table). Defining a subclass with a ``section`` registers it
(:func:`registered_channels`, :func:`channel_class`, :func:`section_of`); a class of the same name
defined again (a module reloaded, a notebook cell run twice) replaces the earlier one, another class
for a taken section is refused.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

import numpy as np
from scipy.special import log_ndtr

__all__ = [
    "Channel",
    "refuse_feedthrough",
    "interval_moments",
    "log_interval_mass",
    "registered_channels",
    "channel_class",
    "section_of",
]

_LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)
_CHANNELS: dict[str, type[Channel]] = {}


class Channel:
    """Base class of the channel pieces (censoring, fading, protocol, saturation, quantizer); see the module
    docstring for the contract."""

    section: ClassVar[str | None] = None
    """Name of the channel in the registry and in sweep files; a subclass that sets it registers itself."""
    sweep_options: ClassVar[Mapping[str, Any]] = {}
    """Keywords a sweep file's section may give -> their kind (``float``, ``int``, tuple of values, ``object``)."""
    replaces_censoring: ClassVar[bool] = False
    """True when the channel carries its own limits (no separate :class:`~tobitkf.Censoring` with it)."""
    compiled_block: ClassVar[Any] = None
    """The channel's compiled block: a ``numba.njit`` function or ``"module:name"`` of one (module docstring);
    None: the numpy path only (unless ``compiled_moments``)."""
    compiled_moments: ClassVar[Any] = None
    """Name of one of the package's block functions (module docstring); None: the channel's own ``compiled_block``."""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        section = cls.__dict__.get("section")
        if section is not None:
            _register(cls, section)

    @classmethod
    def from_options(cls, options: Mapping[str, Any], system: Any = None) -> Channel:
        """The channel from the ``options`` of a sweep file's section (default ``cls(**options)``).

        Raises
        ------
        ValidationError
            An option the class does not take (its constructor's own errors for bad values).
        """
        from .._validation import ValidationError

        unknown = set(options) - set(cls.sweep_options)
        if unknown:
            raise ValidationError(
                f"{sorted(unknown)[0]}: not an option of [{cls.section}]; expected one of "
                f"{', '.join(sorted(cls.sweep_options)) or 'none'}"
            )
        return cls(**options)

    # --- simulation ---------------------------------------------------------------------------------
    def check(self, system: Any, steps: int | None = None) -> None:
        """Raise unless the channel fits ``system`` (and a horizon of ``steps``); default: always fits."""

    def draw(
        self, rng: np.random.Generator, x: np.ndarray, system: Any, noise: np.ndarray, inputs: np.ndarray | None = None
    ) -> tuple[np.ndarray, dict[str, np.ndarray]] | None:
        """The latent readings ``(N, T, m)`` and the channel's draws; ``None``: the plain linear reading."""
        return None

    def censor(self, y_latent: np.ndarray) -> np.ndarray:
        """What the sensor reports for the latent readings ``(..., T, m)``; default: unchanged."""
        return y_latent

    def apply(self, rng: np.random.Generator, y: np.ndarray, extras: dict[str, Any]) -> np.ndarray:
        """What reaches the estimator after censoring; default: unchanged."""
        return y

    @property
    def measures(self) -> bool:
        """True when the channel replaces the linear reading (overrides :meth:`draw`)."""
        return type(self).draw is not Channel.draw

    # --- the measurement contract -------------------------------------------------------------------
    def region(self, y: np.ndarray, k: int, l: int) -> tuple[np.ndarray, np.ndarray]:
        """The interval ``(lo, hi)`` (each ``(N,)``) the readings ``y`` (N,) of channel ``l`` at step ``k`` say
        the latent reading lies in; ``lo == hi``: the exact value. Not implemented by default."""
        raise NotImplementedError(f"{type(self).__name__} does not say what a reading tells of the latent reading")

    def reading_moments(
        self, y: np.ndarray, mean: np.ndarray, std: np.ndarray, k: int, l: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r""":math:`E[y^* \mid y]`, :math:`\mathrm{Var}[y^* \mid y]` and :math:`\log p(y)` under
        :math:`y^* \sim N(\text{mean}, \text{std}^2)`, each (N,); default from :meth:`region`."""
        lo, hi = self.region(y, k, l)
        return interval_moments(mean, std, lo, hi)

    def reading_log_likelihood(self, y: np.ndarray, mean: np.ndarray, std: np.ndarray, k: int, l: int) -> np.ndarray:
        r""":math:`\log p(y \mid y^* \sim N(\text{mean}, \text{std}^2))`, (N,); default from :meth:`region`
        (else the third output of :meth:`reading_moments`)."""
        if _overrides(self, "region"):
            lo, hi = self.region(y, k, l)
            return interval_log_likelihood(mean, std, lo, hi)
        return self.reading_moments(y, mean, std, k, l)[2]

    def reading_statistics(
        self, mean: np.ndarray, std: np.ndarray, k: int, l: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r""":math:`E[y]`, :math:`\partial E[y]/\partial\mu` and :math:`\mathrm{Var}[y]` of the reading of channel
        ``l`` under :math:`y^* \sim N(\text{mean}, \text{std}^2)`, each (N,). Not implemented by default."""
        raise NotImplementedError(f"{type(self).__name__} gives no statistics of its reading (reading_statistics)")

    def fisher_information(self, mean: np.ndarray, std: np.ndarray, k: int, l: int) -> np.ndarray:
        r"""Fisher information :math:`I_{\mu\mu}` of one reading of channel ``l`` about the latent mean, (N,).
        Not implemented by default."""
        raise NotImplementedError(f"{type(self).__name__} gives no Fisher information (fisher_information)")

    def compiled_parameters(self, k: int, steps: int, m: int) -> np.ndarray:
        """The ``par`` of the channel's compiled block (module docstring) for the steps k..k+steps-1, an array
        (1 or ``steps``, m, K); default: none, (1, m, 0)."""
        return np.zeros((1, m, 0))

    def check_readings(self, y: np.ndarray, start: int = 1, name: str = "y") -> None:
        """Raise :class:`~tobitkf.ValidationError` for a reading of ``y`` (..., T, m) the channel cannot give
        (row 0 is time ``start``); default: every reading possible."""

    def reading_width(self, system: Any) -> int:
        """Channels of the readings the estimators receive from ``system`` (default its m outputs)."""
        return int(system.m)

    def at_limit(self, y: np.ndarray, start: int = 1) -> np.ndarray:
        """Mask (..., T, m) of the readings at a limit of the sensor; default: none."""
        return np.zeros(np.shape(y), dtype=bool)

    def supports(self, hook: str) -> bool:
        """True when this channel supplies the contract's ``hook`` (``"moments"``: :meth:`region` or
        :meth:`reading_moments`; ``"likelihood"``; ``"statistics"``; ``"fisher"``)."""
        if hook in ("moments", "likelihood"):
            return _overrides(self, "region") or _overrides(self, "reading_moments")
        name = {"statistics": "reading_statistics", "fisher": "fisher_information"}.get(hook, hook)
        return _overrides(self, name)


def _overrides(obj: Any, name: str) -> bool:
    return getattr(type(obj), name, None) is not getattr(Channel, name, None)


def _register(cls: type[Channel], section: str) -> None:
    from .._validation import ValidationError

    if not isinstance(section, str) or not section.isidentifier():
        raise ValidationError(f"section: expected a plain name for the channel {cls.__name__}, got {section!r}")
    old = _CHANNELS.get(section)
    if old is not None and old.__name__ != cls.__name__:
        raise ValidationError(
            f"section: {section!r} is already the channel {old.__module__}.{old.__name__}; "
            f"give {cls.__name__} another section name"
        )
    _CHANNELS[section] = cls


def registered_channels() -> dict[str, type[Channel]]:
    """Every registered channel class, by section name (a copy)."""
    return dict(_CHANNELS)


def channel_class(section: str) -> type[Channel]:
    """The channel class registered as ``section``; :class:`~tobitkf.ValidationError` listing them otherwise."""
    from .._validation import ValidationError

    if not isinstance(section, str) or section not in _CHANNELS:
        raise ValidationError(f"channel: unknown section {section!r}; expected one of {', '.join(sorted(_CHANNELS))}")
    return _CHANNELS[section]


def section_of(piece: Any) -> str | None:
    """The section name of a channel piece (the first registered class in its method resolution order), or
    None for an object that is not a registered channel."""
    for klass in type(piece).__mro__:
        sec = klass.__dict__.get("section")
        if sec is not None and _CHANNELS.get(sec) is klass:
            return sec
    return None


# --------------------------------------------------------------------------- interval moments
def log_interval_mass(a: Any, b: Any) -> np.ndarray:
    r""":math:`\log(\Phi(b) - \Phi(a))` for :math:`a \le b` (infinite ends allowed), elementwise.

    Computed as a difference of ``log_ndtr`` values on the side of the lower tail (the window is mirrored,
    :math:`[a, b] \to [-b, -a]`, when :math:`a + b > 0`), :math:`\log\Phi(b') + \log(1 - e^{\log\Phi(a') -
    \log\Phi(b')})`: finite and accurate 40 σ and more into either tail, and for narrow windows.

    >>> round(float(log_interval_mass(40.0, np.inf)), 2), round(float(log_interval_mass(-np.inf, -40.0)), 2)
    (-804.61, -804.61)
    """
    a, b = np.broadcast_arrays(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    with np.errstate(invalid="ignore"):
        flip = (a + b) > 0
    a2, b2 = np.where(flip, -b, a), np.where(flip, -a, b)
    la, lb = log_ndtr(a2), log_ndtr(b2)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = lb + np.log1p(-np.exp(la - lb))
    return np.where(np.isneginf(la), lb, out)


def interval_log_likelihood(mean: Any, std: Any, lo: Any, hi: Any) -> np.ndarray:
    r""":math:`\log p(y^* \in [lo, hi])` for :math:`y^* \sim N(\mu, s^2)`, or the log-density at ``lo``
    where ``lo == hi`` (an exact reading), elementwise."""
    mu, sd, lo, hi = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (mean, std, lo, hi)))
    exact = lo == hi
    with np.errstate(invalid="ignore", over="ignore"):
        z = (lo - mu) / sd
        dens = -0.5 * z * z - np.log(sd) - _LOG_SQRT_2PI
        a = np.where(np.isneginf(lo), -np.inf, (lo - mu) / sd)
        b = np.where(np.isposinf(hi), np.inf, (hi - mu) / sd)
    return np.where(exact, dens, log_interval_mass(np.where(exact, 0.0, a), np.where(exact, 1.0, b)))


def interval_moments(mean: Any, std: Any, lo: Any, hi: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Posterior moments of :math:`y^* \sim N(\mu, s^2)` told that :math:`y^* \in [lo, hi]` (or
    :math:`y^* = lo` where ``lo == hi``), elementwise.

    .. math::

        E[y^* \mid \cdot] = \mu + s\,\frac{\phi(\alpha) - \phi(\beta)}{\Phi(\beta) - \Phi(\alpha)}, \qquad
        \mathrm{Var}[y^* \mid \cdot] = s^2\Big[1 + \frac{\alpha\phi(\alpha) - \beta\phi(\beta)}{\Phi(\beta) -
        \Phi(\alpha)} - \Big(\frac{\phi(\alpha) - \phi(\beta)}{\Phi(\beta) - \Phi(\alpha)}\Big)^2\Big],

    :math:`\alpha = (lo - \mu)/s`, :math:`\beta = (hi - \mu)/s`, through the package's tail-safe
    truncated-normal moments (:func:`tobitkf.censored_moments`: continued fractions and quadrature where
    the closed form cancels: far tails, narrow windows), and the log-mass :func:`log_interval_mass`.

    Returns
    -------
    observed, retained, log_likelihood : ndarrays of the broadcast shape
        :math:`E[y^* \mid \cdot]`, :math:`\mathrm{Var}[y^* \mid \cdot]` (0 for an exact reading) and the
        log-mass (the log-density for an exact reading).

    Examples
    --------
    Told only that :math:`y^* \ge 0`, a standard normal has the half-normal's mean :math:`\sqrt{2/\pi}`:

    >>> obs, var, ll = interval_moments(0.0, 1.0, 0.0, np.inf)
    >>> round(float(obs), 6), round(float(var), 6), round(float(np.exp(ll)), 6)
    (0.797885, 0.36338, 0.5)
    """
    from ..censored import unchecked_moments

    mu, sd, lo, hi = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (mean, std, lo, hi)))
    exact = lo == hi
    obs = np.where(exact, lo, np.nan)
    var = np.zeros(mu.shape)
    win = ~exact
    if win.any():
        st = unchecked_moments(mu[win], sd[win], lo[win], hi[win])
        obs[win] = st.truncated_mean
        var[win] = st.truncated_var
    return obs, var, interval_log_likelihood(mu, sd, lo, hi)


def refuse_feedthrough(system: Any, inputs: Any, reading: str) -> None:
    """Raise :class:`~tobitkf.ValidationError` for control ``inputs`` on a ``system`` with a feedthrough D when
    the channel's ``reading`` replaces :math:`Cx + Du + v` by a model without a :math:`Du` term (the
    protocol channel's integral reading, the randomly saturated one): drawing it would drop D u silently,
    as its filters would (they refuse it the same way)."""
    if inputs is not None and getattr(system, "D", None) is not None:
        from .._validation import ValidationError

        raise ValidationError(
            f"u: {reading} has no feedthrough D u; give the system no D (a control input enters through Bu only)"
        )
