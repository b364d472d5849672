r"""The measurement moments of the assumed-density families, compiled, for a block of runs and one channel.

An assumed-density update of one scalar channel with row :math:`h` conditions the Gaussian prior
:math:`N(\bar x, \bar P)` on what was observed about the latent reading and projects the result back
onto a Gaussian. For every family here the posterior moments (a single Gaussian or a moment-matched
mixture of them) are a rank-one change along :math:`\bar Ph^T`:

.. math::

    \hat x = \bar x + \alpha\,\bar Ph^T, \qquad P = \bar P - \beta\,\bar Ph^T h\bar P,

with two scalars per run. A component j of the update with scale :math:`\lambda_j` (the reading is
:math:`\lambda_j h x + d + v`, :math:`s_j^2 = \lambda_j^2h\bar Ph^T + r`), posterior latent mean
:math:`E_j` and retained variance :math:`V_j` contributes
:math:`c_j = \lambda_j(E_j - \mu_j)/s_j^2` and :math:`d_j = \lambda_j^2(s_j^2 - V_j)/s_j^4`
(:mod:`tobitkf.filters.assumed_density`: :math:`K_j = \lambda_j\bar Ph^T/s_j^2`,
:math:`P_j = \bar P - K_j(s_j^2 - V_j)K_j^T`); the mixture with posterior weights :math:`w_j` merges to
(:func:`~tobitkf.filters.assumed_density.merge_gaussians`)

.. math::

    \alpha = \sum_j w_jc_j, \qquad \beta = \sum_j w_jd_j - \sum_j w_j(c_j - \alpha)^2.

A family supplies :math:`(\alpha, \beta)`, the log-likelihood of the reading under the Gaussian prior,
the probability of an uncensored reading and its components' posterior weights, for the runs of a
block (runs on the last axis, as in every kernel), by one function of the common signature
``(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp)``:

* :func:`censored_block` (class code :data:`CENSORED`): censoring one- or two-sided, several regions
  (stacked channels), the Rice-fading channel (its fading variance is in ``rb``);
* :func:`saturation_block` (:data:`SATURATION`): random saturation, three modes;
* :func:`protocol_block` (:data:`PROTOCOL`): the protocol channel's failure outcomes, censored at τ;
* a channel's own block (:data:`BLOCK`): the function its ``compiled_block`` names (:func:`block_kind`; the
  quantized sensor's is :func:`tobitkf.channels._compiled_quantizer.quantizer_block`).

The protocol Tobit Kalman filter (not an assumed-density update: a Kalman-type update with the censored
moments of (21)–(24)) supplies its moments by :func:`protocol_tkf_block`.

A channel of the measurement contract (:mod:`tobitkf.channels.base`) reaches the loop with a block function of
its own, its ``compiled_block`` (:func:`channel_kind`), or by naming one of the blocks here in its
``compiled_moments`` (a key of :data:`FAMILIES`), and gives the block's ``par`` through ``compiled_parameters``.
A block of its own travels as a kind too, :func:`block_kind`: the tuple of :data:`BLOCK` handles of a numba type
named by the hash of the block's code (:class:`BlockType`), which :func:`family_block` calls. The type is the same
in every process for the same code, so the loop's version for that block is cached on disk like the package's own
families' (an ``njit`` function as the argument, typed by numba as that object, is not: its type does not survive
the process, and the loop was compiled again in every one). No edit to this module, the loop or its callers adds a
channel.

The event "the latent reading lies in [ea, eb]" (:func:`interval_event`: beyond a limit on one side, or
between two finite bounds) is the piece a quantized sensor's interval update reuses. Every statistic comes
from :mod:`tobitkf.filters._compiled_censored`, the one compiled implementation of the censored-normal
statistics (:func:`~tobitkf.filters._compiled_censored.beyond` for one finite bound,
:func:`~tobitkf.filters._compiled_censored.censored_stats` for a window, quadrature for narrow ones);
log-probabilities stay finite 40σ (and more) into the tails: :math:`\log Q(a) = -a^2/2 - \log\sqrt{2\pi}
- \log\lambda(a)` beyond the centre.
:mod:`tobitkf.censored` remains the high-precision reference (tested against it).
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import math
import sys
from types import CodeType
from typing import Any

import numpy as np
from numba import njit, types
from numba.core.registry import CPUDispatcher
from numba.extending import NativeValue, models, overload, register_model, typeof_impl, unbox

from ._compiled_censored import GL_W, GL_X, _exp_neg, _log_pos, beyond, censored_stats, lower_stats_block

__all__ = [
    "CENSORED",
    "SATURATION",
    "PROTOCOL",
    "MISSING",
    "INTERIOR",
    "LOWER",
    "UPPER",
    "INTERVAL",
    "beyond",
    "interval_event",
    "censored_block",
    "saturation_block",
    "protocol_block",
    "BLOCK",
    "FAMILIES",
    "BlockType",
    "block_kind",
    "channel_kind",
    "call_block",
    "interval_update",
    "BLOCK_PARAMETERS",
    "family_block",
    "family_array",
    "kind",
    "PROTOCOL_TKF_EXTRAS",
    "protocol_tkf_block",
]

CENSORED, SATURATION, PROTOCOL = 0, 1, 2  #: family codes of the compiled loop
BLOCK = 3  #: the family code of a channel's own block (:func:`block_kind`)
#: the block functions a channel may name in its ``compiled_moments`` -> their family codes
FAMILIES = {
    "censored_block": CENSORED,
    "saturation_block": SATURATION,
    "protocol_block": PROTOCOL,
}
#: the parameters of every block function, in order (a channel's own ``compiled_block`` takes the same)
BLOCK_PARAMETERS = (
    "nb", "y", "cls", "hx", "hph", "rb", "lo", "hi", "par", "alpha", "beta", "ll", "pu", "comp", "glx", "glw", "buf",
)  # fmt: skip
MISSING, INTERIOR, LOWER, UPPER, INTERVAL = 0, 1, 2, 3, 4  #: reading classes (as tobitkf.filters._readings)
_TINY = float(np.finfo(np.float64).tiny)
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_RTOL_LIMIT = 1e-12  # the limit rule of classify_readings
_LOG_SMALL = -600.0  # below this log-mass a window's probability is taken in log space (e^-600 ~ 1e-261)
_INF = math.inf


@njit(cache=True, error_model="numpy")
def _two_sided(mu, sd, ea, eb, glx, glw, buf):
    st = censored_stats(mu, sd, ea, eb, glx, glw, buf)
    g = st[2]
    return math.log(g) if g > 0.0 else -_INF, st[4], st[5]


@njit(cache=True, error_model="numpy")
def _log_window(mu, sd, ea, eb):
    r""":math:`\log P(ea \le y^* \le eb)` for finite ea < eb from the two one-sided log-probabilities on the
    side of the nearer tail (mirrored when the window lies above the mean): :math:`\log P_b +
    \log(1 - e^{\log P_a - \log P_b})`, finite where :math:`\Phi(\beta) - \Phi(\alpha)` underflows (a cell
    40σ away), as :func:`tobitkf.channels.base.log_interval_mass`."""
    if (ea - mu) + (eb - mu) > 0.0:
        _p, la, _m, _v = beyond(mu, sd, eb, 1.0)
        _p, lb, _m, _v = beyond(mu, sd, ea, 1.0)
    else:
        _p, la, _m, _v = beyond(mu, sd, ea, -1.0)
        _p, lb, _m, _v = beyond(mu, sd, eb, -1.0)
    return lb + math.log1p(-math.exp(la - lb))


@njit(cache=True, error_model="numpy", inline="always")
def interval_event(mu, sd, ea, eb, glx, glw, buf):
    r"""``(log_p, mean, var)`` of :math:`y^* \sim N(\mu, sd^2)` given :math:`ea \le y^* \le eb` (one side
    may be infinite): the log-probability of the event and the truncated moments. One finite bound: the
    vectorised one-sided routes (:func:`beyond`); two: :func:`~tobitkf.filters._compiled_censored.censored_stats`
    (direct formulas, quadrature for a narrow window or one in a tail). The update of a quantized sensor
    (a reading at level l: the window [l - w/2, l + w/2)) and of a censored one (beyond its limit)."""
    if ea == -_INF:
        _p, lp, tm, tv = beyond(mu, sd, eb, -1.0)
        return lp, tm, tv
    if eb == _INF:
        _p, lp, tm, tv = beyond(mu, sd, ea, 1.0)
        return lp, tm, tv
    lp, tm, tv = _two_sided(mu, sd, ea, eb, glx, glw, buf)
    if lp < _LOG_SMALL:  # the mass is (nearly) subnormal: its logarithm from the tails' log-probabilities
        lp = _log_window(mu, sd, ea, eb)
    return lp, tm, tv


@njit(cache=True, error_model="numpy", inline="always")
def classify(y, lo, hi):
    """The class of one reading by the limit rule of :func:`~tobitkf.filters._readings.classify_readings`."""
    if math.isnan(y):
        return MISSING
    if lo != -_INF and y <= lo + _RTOL_LIMIT * max(1.0, abs(lo)):
        return LOWER
    if hi != _INF and y >= hi - _RTOL_LIMIT * max(1.0, abs(hi)):
        return UPPER
    return INTERIOR


@njit(cache=True, error_model="numpy", inline="always")
def _censored_one(y, c, mu, s2, lo, hi):
    r"""One run of :func:`censored_block`: ``(alpha, beta, ll, pu)`` of the reading ``y`` of class ``c``
    with latent :math:`N(\mu, s2)` and limits lo < hi (either infinite), as
    :func:`~tobitkf.filters.assumed_density.censored_channel_update`."""
    ok = s2 > _TINY
    s = math.sqrt(s2) if ok else 1.0
    # p_uncensored = P(y* > lo) - P(y* > hi), and the piece beyond the limit of a censored reading
    lo_fin = lo != -_INF
    hi_fin = hi != _INF
    # a side without a limit is not evaluated (the branch is the channel's, the same for every run)
    p_above_lo, lp_lo, m_lo, v_lo = beyond(mu, s, lo, -1.0) if lo_fin else (1.0, 0.0, 0.0, 0.0)  # y* <= lo
    p_below_hi, lp_hi, m_hi, v_hi = beyond(mu, s, hi, 1.0) if hi_fin else (1.0, 0.0, 0.0, 0.0)  # y* >= hi
    if lo_fin and hi_fin:
        pu = p_above_lo - _exp_neg(lp_hi)  # (lp_hi <= 0) no libm call: the loop over runs stays vectorisable
    elif lo_fin:
        pu = p_above_lo
    elif hi_fin:
        pu = p_below_hi
    else:
        pu = 1.0
    # selects rather than branches per run (the loop over a block's runs stays vectorisable)
    is_lo = c == LOWER
    is_hi = c == UPPER
    z = (y - mu) / s
    ll_in = -0.5 * z * z - _log_pos(s) - _LOG_SQRT_2PI
    obs = m_lo if is_lo else (m_hi if is_hi else y)
    v = v_lo if is_lo else (v_hi if is_hi else 0.0)
    ll = lp_lo if is_lo else (lp_hi if is_hi else ll_in)
    take = ok and c != MISSING
    alpha = (obs - mu) / s2 if take else 0.0
    beta = (s2 - v) / (s2 * s2) if take else 0.0
    if not take:
        # missing: 0; a degenerate latent: the indicator of the reading (mu agrees with it), no update
        agrees = (mu <= lo) if is_lo else ((mu >= hi) if is_hi else (y == mu))
        ll = 0.0 if (c == MISSING or agrees) else -_INF
    return alpha, beta, ll, pu


@njit(cache=True, error_model="numpy")
def censored_block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
    r"""The assumed-density update of a censored channel for the runs ``b < nb`` of a block: the reading
    ``y[b]`` of class ``cls[b]``, latent mean ``hx[b]`` (:math:`h\bar x + d`) and variance
    ``hph[b] + rb[b]``, the channel's limits ``lo[b]`` < ``hi[b]``; writes ``alpha``, ``beta``, ``pu``
    and adds the log-likelihood to ``ll`` (``par``, ``comp`` unused). The equations of
    :mod:`tobitkf.filters.assumed_density`: :math:`\alpha = (E[y^*\mid\text{obs}] - \mu)/s^2`,
    :math:`\beta = (s^2 - V)/s^4`. A reading of class :data:`INTERVAL` (flagged censored inside its limits)
    is told :math:`lo \le y^* \le hi` (:func:`interval_event`)."""
    for b in range(nb):
        a, be, lb, p = _censored_one(y[b], cls[b], hx[b], hph[b] + rb[b], lo[b], hi[b])
        if cls[b] == INTERVAL:  # y* in [lo, hi]: the interval's mass and truncated moments (interval_event)
            mu, s2 = hx[b], hph[b] + rb[b]
            if s2 > _TINY:
                lb, tm, tv = interval_event(mu, math.sqrt(s2), lo[b], hi[b], glx, glw, buf)
                a, be = (tm - mu) / s2, (s2 - tv) / (s2 * s2)
            else:
                a, be = 0.0, 0.0
                lb = 0.0 if (lo[b] <= mu and mu <= hi[b]) else -_INF
        alpha[b] = a
        beta[b] = be
        ll[b] += lb
        pu[b] = p


@njit(cache=True, error_model="numpy", inline="always")
def _lognorm(y, m, var):
    d = y - m
    return -0.5 * d * d / var - 0.5 * math.log(var) - _LOG_SQRT_2PI


@njit(cache=True, error_model="numpy", inline="always")
def interval_update(mu, s2, ea, eb, glx, glw, buf):
    r"""``(alpha, beta, log_p)`` of one run whose reading says :math:`ea \le y^* \le eb` under
    :math:`y^* \sim N(\mu, s2)`: ``ea == eb`` the exact value, :math:`(y - \mu)/s^2`, :math:`1/s^2` and
    :math:`\log N(y; \mu, s^2)`; an interval (either end may be infinite) the truncated moments :math:`(E, V)` and
    the log-probability of :func:`interval_event`, :math:`\alpha = (E - \mu)/s^2`, :math:`\beta = (s^2 - V)/s^4`
    (finite 40σ into either tail). A degenerate latent (``s2`` not above the smallest normal number): no update,
    the term 0 when :math:`\mu` lies in :math:`[ea, eb]`, else :math:`-\infty`. The update of every channel whose
    reading is an interval of the latent reading (the contract's ``region``: a quantizer, a dead band); ``glx``,
    ``glw``, ``buf`` are the block function's own arguments, passed on."""
    if not s2 > _TINY:
        return 0.0, 0.0, (0.0 if (ea <= mu and mu <= eb) else -_INF)
    if ea == eb:
        return (ea - mu) / s2, 1.0 / s2, _lognorm(ea, mu, s2)
    lp, tm, tv = interval_event(mu, math.sqrt(s2), ea, eb, glx, glw, buf)
    return (tm - mu) / s2, (s2 - tv) / (s2 * s2), lp


@njit(cache=True, error_model="numpy")
def saturation_block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
    r"""The assumed-density update of a randomly saturating sensor (:mod:`tobitkf.filters.adf_saturation`)
    for the runs ``b < nb``: ``hx`` = :math:`\mu_c = C_i\bar x`, ``hph`` = :math:`s^2 = C_i\bar PC_i^T`,
    ``rb`` = :math:`R_{ii}`, ``par`` = ``(u, log P(saturated), log P(linear), log P(noise only))``. Three
    modes: saturated (the three pieces of :math:`\sigma(c)`, merged), linear (the Kalman update), noise
    only (no change); their posterior probabilities go to ``comp`` (3, B); ``pu`` is 1 (no censoring)."""
    u = par[0]
    for b in range(nb):
        pu[b] = 1.0
        c = cls[b]
        if c == MISSING:
            alpha[b] = 0.0
            beta[b] = 0.0
            for j in range(3):
                comp[j, b] = math.exp(par[1 + j])
            continue
        yb = y[b]
        mu = hx[b]
        var = hph[b]
        r = rb[b]
        ok = var > _TINY
        vs = var if ok else 1.0
        s = math.sqrt(vs)
        # the saturated mode: c <= -u, |c| < u given the reading, c >= u
        _p1, lp_low, m_low, v_low = beyond(mu, s, -u, -1.0)
        _p3, lp_high, m_high, v_high = beyond(mu, s, u, 1.0)
        g = vs / (vs + r)
        mid_m = mu + g * (yb - mu)
        mid_v = vs * r / (vs + r)
        st = censored_stats(mid_m, math.sqrt(mid_v), -u, u, glx, glw, buf)
        l1p = lp_low + _lognorm(yb, -u, r)
        l2p = _lognorm(yb, mu, vs + r) + (math.log(st[2]) if st[2] > 0.0 else -_INF)
        l3p = lp_high + _lognorm(yb, u, r)
        top = max(l1p, max(l2p, l3p))
        w1, w2, w3 = math.exp(l1p - top), math.exp(l2p - top), math.exp(l3p - top)
        tot = w1 + w2 + w3
        w1, w2, w3 = w1 / tot, w2 / tot, w3 / tot
        pm = w1 * m_low + w2 * st[4] + w3 * m_high
        pv = w1 * (v_low + (m_low - pm) ** 2) + w2 * (st[5] + (st[4] - pm) ** 2) + w3 * (v_high + (m_high - pm) ** 2)
        pv = max(pv, 0.0)
        l_sat = math.log(tot) + top
        if ok:
            c1 = (pm - mu) / var
            d1 = (var - pv) / (var * var)
        else:  # the saturated mode leaves the prior (its reading is masked)
            l_sat = _lognorm(yb, min(max(mu, -u), u), r)
            c1 = 0.0
            d1 = 0.0
        # the linear mode: the Kalman update
        sl = var + r
        c2 = (yb - mu) / sl
        d2 = 1.0 / sl
        q1 = par[1] + l_sat
        q2 = par[2] + _lognorm(yb, mu, sl)
        q3 = par[3] + _lognorm(yb, 0.0, r)
        top = max(q1, max(q2, q3))
        e1, e2, e3 = math.exp(q1 - top), math.exp(q2 - top), math.exp(q3 - top)
        tot = e1 + e2 + e3
        e1, e2, e3 = e1 / tot, e2 / tot, e3 / tot
        a = e1 * c1 + e2 * c2
        alpha[b] = a
        beta[b] = e1 * d1 + e2 * d2 - (e1 * (c1 - a) ** 2 + e2 * (c2 - a) ** 2 + e3 * a * a)
        ll[b] += math.log(tot) + top
        comp[0, b] = e1
        comp[1, b] = e2
        comp[2, b] = e3


@njit(cache=True, error_model="numpy")
def protocol_block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
    r"""The assumed-density update of the protocol channel (:mod:`tobitkf.filters.adf_protocol`) for the runs
    ``b < nb``: ``hx`` = :math:`\mathcal C_h\bar\xi`, ``hph`` = :math:`\mathcal C_h\bar P\mathcal C_h^T`, ``rb``
    = :math:`R_{hh}`, ``lo`` the threshold τ, ``par`` = ``(λ_1..λ_J, log π_1..log π_J)`` (J = ``comp.shape[0]``).
    Each failure outcome j is a censored reading (:func:`_censored_one`) of scale :math:`\lambda_j`; the
    outcomes' posterior probabilities go to ``comp``, :math:`\sum_j\pi_jP_j(y^* > \tau)` to ``pu``."""
    J = comp.shape[0]
    cj = np.empty(J)
    dj = np.empty(J)
    for b in range(nb):
        c = cls[b]
        mu0 = hx[b]
        v0 = hph[b]
        r = rb[b]
        top = -_INF
        pub = 0.0
        for j in range(J):
            lam = par[j]
            aj, bj, lj, pj = _censored_one(y[b], c, lam * mu0, lam * lam * v0 + r, lo[b], hi[b])
            cj[j] = lam * aj
            dj[j] = lam * lam * bj
            pub += math.exp(par[J + j]) * pj
            q = par[J + j] + lj  # the log weight, normalised below
            comp[j, b] = q
            top = max(top, q)
        pu[b] = pub
        tot = 0.0
        for j in range(J):
            w = math.exp(comp[j, b] - top)
            comp[j, b] = w
            tot += w
        a = 0.0
        for j in range(J):
            comp[j, b] /= tot
            a += comp[j, b] * cj[j]
        bsum = 0.0
        for j in range(J):
            d = cj[j] - a
            bsum += comp[j, b] * (dj[j] - d * d)
        alpha[b] = a
        beta[b] = bsum
        if c != MISSING:
            ll[b] += math.log(tot) + top


def kind(code: int) -> tuple[None, ...]:
    """The family ``code`` as a type: the tuple of ``code`` Nones (its length read as a constant while compiled code
    given it is typed; Nones, not integers, so that the tuple has one numba type from Python and as a constant of
    compiled code, and costs nothing to pass). Compiled code given it (:func:`family_block`, the compiled loop)
    holds only that family's branch, found by the ordinary dispatch on the argument types: each family compiles
    its own version, not the code of every other family."""
    return (None,) * code


class BlockType(types.Dummy):
    """The numba type of a handle of a channel's own block (:func:`block_kind`), named by the block's key: its
    qualified name and the hash of its code (:func:`_block_key`). Equal for equal code in every process (a handle
    carries no data), so that the cached versions of the compiled functions specialised on it load from disk; the
    block function itself is looked up by the key when numba compiles a call of it (:func:`call_block`)."""

    def __init__(self, key: str):
        self.block_key = key
        super().__init__(f"CompiledBlock({key})")


class BlockHandle:
    """What compiled code is given for a channel's own block (typed :class:`BlockType`; :func:`block_kind`)."""

    __slots__ = ("key",)

    def __init__(self, key: str):
        self.key = key

    def __repr__(self) -> str:
        return f"BlockHandle({self.key!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, BlockHandle) and other.key == self.key

    def __hash__(self) -> int:
        return hash(self.key)


_BLOCKS: dict[str, Any] = {}  # key -> the block's njit function (this process)
_HANDLES: dict[int, tuple[Any, BlockHandle]] = {}  # id(block) -> (block, handle); the block held, so the id stays


@typeof_impl.register(BlockHandle)
def _typeof_handle(val, c):
    return BlockType(val.key)


register_model(BlockType)(models.OpaqueModel)


@unbox(BlockType)
def _unbox_handle(typ, obj, c):
    return NativeValue(c.context.get_dummy_value())


def call_block(handle, nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
    """Call the block a handle names (``handle`` of :class:`BlockType`) with the block arguments; compiled code only
    (:func:`family_block`)."""
    raise NotImplementedError("call_block: runs in compiled code only (tobitkf.filters._compiled_moments)")


@overload(call_block, jit_options={"error_model": "numpy"})
def _call_block_impl(handle, nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
    if not isinstance(handle, BlockType):
        return None
    fn = _BLOCKS[handle.block_key]

    def impl(handle, nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
        fn(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf)

    return impl


def _hash_code(code: CodeType, h: Any, names: set[str]) -> None:
    """Feed the bytecode, names and constants of ``code`` (and of the code nested in it) to ``h``, without its file
    name or line numbers (the same function has the same hash wherever its file lies); collect its names."""
    h.update(code.co_code)
    h.update(repr(code.co_names).encode())
    names.update(code.co_names)
    for c in code.co_consts:
        if isinstance(c, CodeType):
            _hash_code(c, h, names)
        elif isinstance(c, frozenset):
            h.update(repr(sorted(map(repr, c))).encode())
        else:
            h.update(repr(c).encode())


def _hash_function(fn: Any, h: Any, seen: set[int]) -> None:
    """Feed what numba compiles into ``fn`` to ``h``: its code and the values of the globals and closure variables it
    names (numba freezes them into the machine code): a number, string or array by value, a module by name, a
    compiled function of this package by name (the package's cache key holds its code, :mod:`tobitkf._compiled_cache`),
    any other compiled or plain function by its own hash."""
    if id(fn) in seen:
        return
    seen.add(id(fn))
    names: set[str] = set()
    h.update(fn.__qualname__.encode())
    _hash_code(fn.__code__, h, names)
    scope = dict(fn.__globals__)
    if fn.__closure__:
        scope.update(zip(fn.__code__.co_freevars, (cell.cell_contents for cell in fn.__closure__)))
    for name in sorted(names):
        if name not in scope:
            continue
        v = scope[name]
        h.update(name.encode())
        if isinstance(v, (bool, int, float, complex, str, bytes, type(None))) or (
            isinstance(v, tuple) and all(isinstance(e, (bool, int, float, str, type(None))) for e in v)
        ):
            h.update(repr(v).encode())
        elif isinstance(v, np.ndarray):
            h.update(repr((v.dtype.str, v.shape)).encode() + np.ascontiguousarray(v).tobytes())
        elif inspect.ismodule(v):
            h.update(v.__name__.encode())
        else:
            py = getattr(v, "py_func", v)
            mod = getattr(py, "__module__", None) or ""
            if inspect.isfunction(py) and not (mod == "tobitkf" or mod.startswith("tobitkf.")):
                _hash_function(py, h, seen)
            else:
                h.update(f"{mod}.{getattr(py, '__qualname__', type(py).__qualname__)}".encode())


def _block_key(block: Any) -> str:
    """The key of a block function: its qualified name and a hash of what numba compiles into it
    (:func:`_hash_function`)."""
    h = hashlib.sha256()
    _hash_function(block.py_func, h, set())
    return f"{block.py_func.__qualname__}-{h.hexdigest()[:24]}"


def _importable_dynamic_module() -> None:
    """Make numba's stand-in module of functions whose module cannot be imported (``"<dynamic>"``: a block defined
    in a file loaded by path, or in code run by ``exec``) importable, so that a cached loop compiled with such a
    block loads in another process: numba rebuilds the block's environment (its globals, unused by compiled code
    that handles no Python objects) by importing the module it names."""
    from numba.core.utils import _dynamic_modname, _dynamic_module

    sys.modules.setdefault(_dynamic_modname, _dynamic_module)


def block_kind(block: Any, who: str = "the channel") -> tuple[BlockHandle, ...]:
    """The kind (:func:`kind`) of a channel's own block: the tuple of :data:`BLOCK` handles of the block function
    ``block`` (a ``numba.njit`` function of the parameters :data:`BLOCK_PARAMETERS`, or ``"module:name"`` naming
    one, imported here), which the compiled functions given it call (:func:`family_block`). One handle per block
    function and process.

    Raises
    ------
    ValidationError
        A ``block`` that is not such a function (or names none).
    """
    from .._validation import ValidationError

    if isinstance(block, str):
        module, _, name = block.partition(":")
        try:
            block = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError, ValueError):
            raise ValidationError(
                f"compiled_block: expected 'module:name' of a numba.njit block function for {who}, got {block!r}"
            ) from None
    known = _HANDLES.get(id(block))
    if known is not None and known[0] is block:
        return (known[1],) * BLOCK
    if not isinstance(block, CPUDispatcher):
        raise ValidationError(
            f"compiled_block: expected a numba.njit function (or 'module:name' of one) for {who}, got {block!r}"
        )
    params = tuple(inspect.signature(block.py_func).parameters)
    if len(params) != len(BLOCK_PARAMETERS):
        raise ValidationError(
            f"compiled_block: expected a block function of the {len(BLOCK_PARAMETERS)} parameters "
            f"({', '.join(BLOCK_PARAMETERS)}) for {who}, got {block.py_func.__qualname__}({', '.join(params)})"
        )
    if sys.modules.get(block.py_func.__module__) is None:
        _importable_dynamic_module()
    key = _block_key(block)
    _BLOCKS.setdefault(key, block)  # the same key: the same code, whichever function compiles it
    handle = BlockHandle(key)
    _HANDLES[id(block)] = (block, handle)
    return (handle,) * BLOCK


def channel_kind(channel: Any) -> tuple[Any, ...] | None:
    """The kind of a channel's compiled moments: of the package's block its ``compiled_moments`` names (a key of
    :data:`FAMILIES`), else of its own ``compiled_block`` (:func:`block_kind`); None when it has neither.

    Raises
    ------
    ValidationError
        A ``compiled_moments`` that names no block of the compiled loop, a ``compiled_block`` that is none.
    """
    from .._validation import ValidationError

    who = type(channel).__name__
    name = getattr(channel, "compiled_moments", None)
    if name is not None:
        if not (isinstance(name, str) and name in FAMILIES):
            raise ValidationError(
                f"compiled_moments: expected the name of a block of the compiled loop ({', '.join(FAMILIES)}) "
                f"for {who}, got {name!r}"
            )
        return kind(FAMILIES[name])
    block = getattr(channel, "compiled_block", None)
    if inspect.ismethod(block):  # an njit function set on the class binds to the instance like a method
        block = block.__func__
    return None if block is None else block_kind(block, who)


@njit(cache=True, error_model="numpy")
def family_block(family, nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf):
    """The block function of the family ``family`` (:data:`CENSORED`, :data:`SATURATION`, :data:`PROTOCOL`, or a
    channel's own, :data:`BLOCK`) as a kind (:func:`kind`, :func:`block_kind`): numba reads the tuple's length as a
    constant and prunes the other families' branches before typing, so that each family's version holds its own
    block function alone (chosen by the ordinary dispatch on the argument types). A kind of no family raises
    ValueError. (A channel's own block travels as a handle of :class:`BlockType`, not as the ``njit`` function:
    numba types a function argument by the object, a type that does not survive the process, and the loop would
    be compiled again in every process.)"""
    code = len(family)  # a constant: numba rewrites the length of a tuple argument before typing
    if code == CENSORED:
        censored_block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf)
    elif code == SATURATION:
        saturation_block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf)
    elif code == PROTOCOL:
        protocol_block(nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf)
    elif code == BLOCK:  # a channel's own block (block_kind): the handle's type names it
        call_block(family[0], nb, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, glx, glw, buf)
    else:
        raise ValueError("family_block: family: expected the kind of an assumed-density family")


@njit(cache=True, error_model="numpy")
def family_array(family, y, cls, hx, hph, rb, lo, hi, par, J):
    """:func:`family_block` over 1-d arrays (a testing aid, and the form the numpy side may call): returns
    ``(alpha, beta, ll, pu, comp)`` with ``comp`` (J, N). ``family`` a kind (:func:`kind`: this family's block
    alone is compiled). The quadrature nodes are the module's (read-only constants in compiled code, as the
    compiled loops pass them: the block functions are compiled once for both callers)."""
    n = y.shape[0]
    alpha, beta, ll, pu = np.empty(n), np.empty(n), np.zeros(n), np.empty(n)
    comp = np.zeros((J, n))
    buf = np.empty((2, GL_X.shape[0]))
    family_block(family, n, y, cls, hx, hph, rb, lo, hi, par, alpha, beta, ll, pu, comp, GL_X, GL_W, buf)
    return alpha, beta, ll, pu, comp


#: the per-step scalars of the protocol TKF (:func:`protocol_tkf_block`), in the order of its rows 4..10
PROTOCOL_TKF_EXTRAS = (
    "theta_bar",
    "inverse_mills",
    "trunc_var_factor",
    "expected_y",
    "innovation",
    "p_uncensored",
    "innovation_var",
)
_FLOOR = 1e-12  # R (1 - phi) floored at 1e-12 R


@njit(cache=True, error_model="numpy")
def protocol_tkf_block(nb, mom, ok, sd, r, tau, lm, lv, fixed, mode, glx, glw, buf):
    r"""The measurement moments of the protocol Tobit Kalman filter (Geng et al. (13)–(16), (21), (23)–(24);
    also :func:`tobitkf.filters.protocol_model.protocol_measurement`, the numpy path's moments) for the runs ``b < nb`` of a
    block, the scheduled sensor h with noise variance ``r`` (``sd`` = :math:`\sqrt r`), threshold τ = ``tau``,
    failure mean and variance ``lm`` = :math:`\bar\Lambda_h`, ``lv`` = :math:`\check\Lambda_h`:

    .. math::

        \bar\vartheta = (\tau - \zeta)/\sqrt{\mathcal R}, \quad \lambda, \;\mathcal R(1 - \varphi)
        \text{ (the censored statistics at } \zeta\text{, floored at } 10^{-12}\mathcal R), \quad
        \hat y = \zeta + \sqrt{\mathcal R}\lambda, \quad
        R_{ee} = \mathbf HP^-\mathbf H^T + F + \mathcal R(1 - \varphi),

    the failure term F by ``mode``: 0 ``"variance"`` :math:`\check\Lambda_h\mathcal C_hP^-\mathcal C_h^T`,
    1 ``"literal"`` :math:`(\bar\Lambda_h^2 + \check\Lambda_h)\mathcal C_hP^-\mathcal C_h^T`, 2
    ``"second_moment"`` :math:`\check\Lambda_h(\mathcal C_hP^-\mathcal C_h^T + (\mathcal C_h\hat\xi^-)^2)`, 3
    ``"lmmse_unconditional"`` ``fixed`` (the same for every run).

    ``mom`` (20, B): in, the rows 0 :math:`\zeta = \mathbf H\hat\xi^-`, 1 :math:`\mathbf HP^-\mathbf H^T`,
    2 :math:`\mathcal C_hP^-\mathcal C_h^T`, 3 :math:`\mathcal C_h\hat\xi^-`, 14 the reading; out, the rows
    4..10 the step's scalars of :data:`PROTOCOL_TKF_EXTRAS` (for a censored reading, γ = 0: ``expected_y`` τ,
    ``innovation`` 0, ``innovation_var`` the noise alone), 11 the noise :math:`F + \mathcal R(1 - \varphi)`,
    12 :math:`R_{ee}`, 13 the innovation of the update; rows 15..19 scratch. ``ok`` (B,) bool: in, γ; out,
    whether the run takes part in the update (γ = 1 and :math:`R_{ee}` above the smallest normal number; a
    run that does not has innovation 0 and keeps its prediction)."""
    zeta, hph, cpc, xc, yv = mom[0], mom[1], mom[2], mom[3], mom[14]
    st_g, st_lam, st_tv = mom[15], mom[16], mom[17]
    lower = tau != -_INF  # the upper limit is infinite
    if lower:  # the statistics of the block at once, vectorised
        lower_stats_block(zeta, sd, tau, nb, st_g, st_lam, st_tv, mom[18], mom[19])
    for b in range(nb):
        z = zeta[b]
        if lower:  # (13)-(16)
            pg, lam, tv = st_g[b], st_lam[b], st_tv[b]
        else:
            st = censored_stats(z, sd, tau, _INF, glx, glw, buf)
            pg, lam, tv = st[2], st[3], st[5]
        nz = max(tv, _FLOOR * r)  # R (1 - phi), floored
        if mode == 0:
            F = lv * cpc[b]
        elif mode == 1:
            F = (lm * lm + lv) * cpc[b]
        elif mode == 2:
            F = lv * (cpc[b] + xc[b] * xc[b])
        else:
            F = fixed
        ntot = F + nz
        yhat = z + sd * lam  # (21), gamma = 1
        ree = hph[b] + ntot  # (24)
        g = ok[b]
        good = g and ree > _TINY
        mom[4, b] = (tau - z) / sd
        mom[5, b] = lam
        mom[6, b] = 1.0 - nz / r
        mom[7, b] = yhat if g else tau
        mom[8, b] = yv[b] - yhat if g else 0.0
        mom[9, b] = pg
        mom[10, b] = ree if g else nz
        mom[11, b] = ntot
        mom[12, b] = ree
        mom[13, b] = yv[b] - yhat if good else 0.0
        ok[b] = good
