"""Independent tests of the censored-normal statistics (``tobitkf.censored``).

Oracles, in order of strength:

1. ``shared/vectors/censoring_stats.json``: 273 cases computed with 60-digit
   arithmetic (mpmath), limits up to 1000 standard deviations away;
2. ``scipy.stats.truncnorm`` / ``scipy.stats.norm`` in the central region;
3. the printed test-vector tables of spec 001b §2.6 and 001a §6 item 6;
4. Monte Carlo with 10^6 seeded draws (tolerances from the sample size);
5. hypothesis properties (probability axioms, bounds, symmetry, continuity).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats

from tobitkf import ValidationError, censored_moments

VECTORS = Path("/work/shared/vectors/censoring_stats.json")
EPS = np.finfo(float).eps
TINY = np.finfo(float).tiny  # smallest normal double, 2.2e-308

FIELDS = [  # (name in the vector file, attribute of CensoredMoments)
    ("p_lower", "p_lower"),
    ("p_upper", "p_upper"),
    ("p_uncensored", "p_uncensored"),
    ("inverse_mills", "inverse_mills"),
    ("truncated_mean", "truncated_mean"),
    ("truncated_variance", "truncated_var"),
    ("censored_mean", "censored_mean"),
    ("censored_variance", "censored_var"),
]


def _load_cases():
    if not VECTORS.exists():  # pragma: no cover - the shared folder is part of the project setup
        return []
    return json.loads(VECTORS.read_text())["cases"]


CASES = _load_cases()


def _case_id(c):
    return f"mu={c['mu']},s={c['sigma']},[{c['lower']},{c['upper']}]"


# ---------------------------------------------------------------------------------------------
# 1. 60-digit reference vectors
# ---------------------------------------------------------------------------------------------
def test_vector_file_is_complete():
    # guard against silently testing nothing
    assert len(CASES) >= 200


@pytest.mark.parametrize("case", CASES, ids=[_case_id(c) for c in CASES])
def test_matches_60_digit_vectors(case):
    """Every statistic of every reference case.

    Tolerances. The reference is exact to far more than double precision, so any
    difference is the implementation's. The relative tolerance 1e-9 (about ten
    significant digits) is tight enough to catch any formula slip (a wrong sign, a
    missing term, a pdf for a cdf all give errors of order 1) and leaves room for
    the 64-node tail quadrature, whose accuracy is ~1e-11. Absolute floors, each for
    a reason float64 itself imposes:

    * probabilities: below the smallest *normal* double (2.2e-308) numbers are
      subnormal and carry only a few significant bits; the reference lists such
      values (e.g. Phi(-38) = 2.9e-316) while a double-precision ``ndtr`` may return 0.
      So probabilities get ``atol = tiny``.
    * truncated and censored means are formed as mu + sigma*lambda; when the
      result is small compared with |mu| (a window 1000 sigma away from mu) float64
      cannot represent it better than a few eps*|mu|: ``atol = 8 eps max(|mu|, |limits|)``.
    * censored variance: one reference value is -1.9e-62, i.e. negative, which is a
      cancellation inside the 60-digit reference itself (a variance cannot be
      negative); the true values there are ~1e-61 on a latent variance sigma^2 = 9.
      Such values are zero to any precision a variance of scale sigma^2 can carry in
      float64, so the censored variance is compared with ``atol = 1e-12 sigma^2``.
    """
    mu, sigma = float(case["mu"]), float(case["sigma"])
    lower, upper = float(case["lower"]), float(case["upper"])
    got = censored_moments(mu, sigma, lower, upper)
    finite_lims = [abs(v) for v in (lower, upper) if math.isfinite(v)]
    mean_scale = max([abs(mu)] + finite_lims)
    for ref_name, attr in FIELDS:
        ref = float(case[ref_name])
        val = float(getattr(got, attr))
        assert math.isfinite(val), f"{attr} is not finite"
        atol = 0.0
        if ref_name.startswith("p_"):
            atol = TINY
        elif ref_name in ("truncated_mean", "censored_mean"):
            atol = 8 * EPS * mean_scale
        elif ref_name == "censored_variance":
            atol = 1e-12 * sigma**2
        elif ref_name == "inverse_mills":
            # lambda = (tmean - mu)/sigma inherits the same cancellation, divided by sigma
            atol = 8 * EPS * mean_scale / sigma
        assert val == pytest.approx(ref, rel=1e-9, abs=atol), f"{attr}: got {val!r}, reference {ref!r}"


def test_vectors_in_one_batched_call():
    """Broadcasting over all cases at once gives the same numbers as one case at a time.

    To a few units in the last place, not bitwise: numpy's vectorised loops (SIMD exp/log/erfc
    paths for arrays) and its scalar loops may round the last bit differently, and which loop
    runs depends on the CPU and the array's alignment (a 1-ulp difference in p_uncensored was
    seen on one CI machine and not on another).
    """
    mu = np.array([float(c["mu"]) for c in CASES])
    sd = np.array([float(c["sigma"]) for c in CASES])
    lo = np.array([float(c["lower"]) for c in CASES])
    hi = np.array([float(c["upper"]) for c in CASES])
    batch = censored_moments(mu, sd, lo, hi)
    for i in range(0, len(CASES), 17):
        one = censored_moments(mu[i], sd[i], lo[i], hi[i])
        for _, attr in FIELDS:
            b, o = float(getattr(batch, attr)[i]), float(getattr(one, attr))
            assert b == pytest.approx(o, rel=8 * EPS, abs=0.0), f"{attr}[{i}]: {b!r} vs {o!r}"


# ---------------------------------------------------------------------------------------------
# 2. scipy.stats in the central region
# ---------------------------------------------------------------------------------------------
CENTRAL = [
    (0.0, 1.0, -1.0, 1.0),
    (0.3, 0.5, -1.0, 1.0),
    (0.0, 1.0, 0.0, np.inf),
    (0.0, 1.0, -np.inf, 0.0),
    (1.2, 2.0, -0.5, 3.0),
    (-0.1, 0.1, 0.0, np.inf),
    (0.1, 0.1, 0.0, np.inf),
    (2.0, 0.5, -np.inf, 1.5),
    (-1.0, 0.7, -2.5, -0.2),
    (0.0, 3.0, -2.0, 9.0),
]


@pytest.mark.parametrize("mu,sigma,lo,hi", CENTRAL)
def test_agrees_with_scipy_truncnorm(mu, sigma, lo, hi):
    a, b = (lo - mu) / sigma, (hi - mu) / sigma
    tn = stats.truncnorm(a, b, loc=mu, scale=sigma)
    got = censored_moments(mu, sigma, lo, hi)
    p_lo = stats.norm.cdf(a)
    p_hi = stats.norm.sf(b)
    assert got.p_lower == pytest.approx(p_lo, rel=1e-12, abs=1e-300)
    assert got.p_upper == pytest.approx(p_hi, rel=1e-12, abs=1e-300)
    assert got.p_uncensored == pytest.approx(stats.norm.cdf(b) - stats.norm.cdf(a), rel=1e-12)
    assert got.truncated_mean == pytest.approx(tn.mean(), rel=1e-10, abs=1e-12 * sigma)
    assert got.truncated_var == pytest.approx(tn.var(), rel=1e-10)
    assert got.inverse_mills == pytest.approx((tn.mean() - mu) / sigma, rel=1e-10, abs=1e-12)
    # E[y] and Var[y] of the clipped variable from the mixture (independent formula)
    lo_v = lo if np.isfinite(lo) else 0.0
    hi_v = hi if np.isfinite(hi) else 0.0
    gam = stats.norm.cdf(b) - stats.norm.cdf(a)
    ey = p_lo * lo_v + gam * tn.mean() + p_hi * hi_v
    ey2 = p_lo * lo_v**2 + gam * (tn.var() + tn.mean() ** 2) + p_hi * hi_v**2
    assert got.censored_mean == pytest.approx(ey, rel=1e-10, abs=1e-12 * sigma)
    assert got.censored_var == pytest.approx(ey2 - ey**2, rel=1e-8, abs=1e-12 * sigma**2)


# ---------------------------------------------------------------------------------------------
# 3. printed test-vector tables
# ---------------------------------------------------------------------------------------------
# spec 001b §2.6. The table's lambda uses the dissertation's sign, (phi(b) - phi(a))/gamma,
# so that m = mu - sigma*lambda; the library's inverse_mills is (phi(a) - phi(b))/gamma = -lambda.
INF = np.inf
TABLE_2_6 = [
    # mu, sigma, lo, hi, gamma, lambda, m, V, E[y]
    (0.3, 0.5, -1.0, 1.0, 0.914582, 0.148860, 0.225570, 0.177508, 0.282398),
    (0.0, 1.0, -INF, 0.0, 0.5, 0.797885, -0.797885, 0.363380, -0.398942),
    (0.0, 1.0, 0.0, INF, 0.5, -0.797885, 0.797885, 0.363380, 0.398942),
    (2.0, 0.5, -INF, 1.5, 0.158655, 1.525135, 1.237432, 0.049774, 1.458342),
    (-0.2, 0.1, 0.0, INF, 0.022750, -2.373216, 0.037322, 0.001143, 0.000849),
    (5.0, 1.0, -1.0, 1.0, 3.17e-5, 4.225547, 0.774453, 0.046557, 0.999993),
]


def _half_ulp_printed(value: float) -> float:
    """Half a unit in the last printed digit (6 decimals, or 3 significant digits for 3.17e-5)."""
    if value != 0 and abs(value) < 1e-4:
        return 0.5 * 10 ** (math.floor(math.log10(abs(value))) - 2)
    return 0.5e-6


@pytest.mark.parametrize("row", TABLE_2_6, ids=[f"row{i}" for i in range(len(TABLE_2_6))])
def test_spec_001b_table_2_6(row):
    mu, sigma, lo, hi, gamma, lam, m, V, Ey = row
    got = censored_moments(mu, sigma, lo, hi)
    # tolerance: the table is printed to 6 decimals; allow half a unit plus float noise
    for val, ref in (
        (got.p_uncensored, gamma),
        (-got.inverse_mills, lam),
        (got.truncated_mean, m),
        (got.truncated_var, V),
        (got.censored_mean, Ey),
    ):
        assert abs(float(val) - ref) <= _half_ulp_printed(ref) * 1.0001 + 1e-12, (val, ref)


@pytest.mark.parametrize(
    "mu,p_u,ey,m_tr,v_tr,epv2",
    [
        # spec 001a §6 item 6 (Miller Example 1 channel: sigma = 0.1, left-censored at T = 0)
        (-0.1, 0.15866, 0.00833, 0.05251, 0.001991, 0.004006),
        (0.1, 0.84134, 0.10833, 0.12876, 0.006297, 0.005994),
    ],
)
def test_spec_001a_item6_values(mu, p_u, ey, m_tr, v_tr, epv2):
    got = censored_moments(mu, 0.1, 0.0, np.inf)
    assert abs(got.p_uncensored - p_u) <= 0.5e-5
    assert abs(got.censored_mean - ey) <= 0.5e-5
    assert abs(got.truncated_mean - m_tr) <= 0.5e-5
    assert abs(got.truncated_var - v_tr) <= 0.5e-6
    # E[p v^2] = gamma (V_tr + (m_tr - mu)^2)  (exact alternative (i) of)
    pv2 = got.p_uncensored * (got.truncated_var + (got.truncated_mean - mu) ** 2)
    assert abs(pv2 - epv2) <= 0.5e-6
    # and the closed form sigma^2 [p_u + a phi(a)] of A-3.2 (i)
    a = (0.0 - mu) / 0.1
    assert pv2 == pytest.approx(0.01 * (stats.norm.sf(a) + a * stats.norm.pdf(a)), rel=1e-12)


def test_sign_convention_of_inverse_mills():
    """Left censoring: lambda = phi(a)/(1-Phi(a)) (3.7); right: minus phi(b)/Phi(b) (module docstring)."""
    a = -0.4
    left = censored_moments(0.0, 1.0, a, np.inf)
    assert left.inverse_mills == pytest.approx(stats.norm.pdf(a) / stats.norm.sf(a), rel=1e-13)
    b = 0.7
    right = censored_moments(0.0, 1.0, -np.inf, b)
    assert right.inverse_mills == pytest.approx(-stats.norm.pdf(b) / stats.norm.cdf(b), rel=1e-13)


# ---------------------------------------------------------------------------------------------
# 4. Monte Carlo, 10^6 seeded draws
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "mu,sigma,lo,hi",
    [
        (-0.1, 0.1, 0.0, np.inf),
        (0.1, 0.1, 0.0, np.inf),
        (0.3, 0.5, -1.0, 1.0),
        (2.0, 0.5, -np.inf, 1.5),
        (0.0, 2.0, -0.5, 0.25),
    ],
)
def test_monte_carlo_mean_and_variance(mu, sigma, lo, hi):
    n = 1_000_000
    rng = np.random.default_rng(20240611)
    y = np.clip(mu + sigma * rng.standard_normal(n), lo, hi)
    got = censored_moments(mu, sigma, lo, hi)
    mean, var = y.mean(), y.var()
    # standard errors from the sample: SE(mean) = sd/sqrt(n); SE(var) = sqrt((m4 - var^2)/n)
    se_mean = math.sqrt(var / n)
    m4 = np.mean((y - mean) ** 4)
    se_var = math.sqrt((m4 - var**2) / n)
    assert abs(got.censored_mean - mean) < 5 * se_mean
    assert abs(got.censored_var - var) < 5 * se_var
    # the probabilities of the three outcomes: binomial standard errors
    for p, frac in ((got.p_lower, np.mean(y <= lo)), (got.p_upper, np.mean(y >= hi))):
        assert abs(p - frac) < 5 * math.sqrt(max(p * (1 - p), 1e-12) / n) + 1e-12
    inside = y[(y > lo) & (y < hi)]
    assert abs(got.truncated_mean - inside.mean()) < 5 * math.sqrt(inside.var() / inside.size)


# ---------------------------------------------------------------------------------------------
# 5. properties (hypothesis)
# ---------------------------------------------------------------------------------------------
mus = st.floats(-100, 100)
sigmas = st.floats(1e-3, 1e2)
z = st.floats(-1000, 1000)  # limit positions in standard deviations from the mean


@st.composite
def windows(draw):
    """(mu, sigma, lower, upper) with limits within 1000 sigma, possibly infinite."""
    mu, sigma = draw(mus), draw(sigmas)
    kind = draw(st.sampled_from(["two", "left", "right", "none"]))
    za = draw(z)
    width = draw(st.one_of(st.floats(1e-3, 2000), st.floats(0.05, 4)))
    lo = mu + sigma * za if kind in ("two", "left") else -np.inf
    hi = mu + sigma * (za + width) if kind in ("two", "right") else np.inf
    if kind == "right":
        hi = mu + sigma * za
    if not lo < hi:
        hi = np.nextafter(lo, np.inf) if np.isfinite(lo) else hi
    if not lo < hi:  # pragma: no cover
        lo = -np.inf
    return mu, sigma, lo, hi


PROPS = settings(
    max_examples=int(__import__("os").environ.get("TOBITKF_HYPOTHESIS_EXAMPLES", 150)),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)


@PROPS
@given(windows())
def test_probabilities_are_probabilities(w):
    mu, sigma, lo, hi = w
    got = censored_moments(mu, sigma, lo, hi)
    for p in (got.p_lower, got.p_upper, got.p_uncensored):
        assert 0.0 <= p <= 1.0
    assert got.p_lower + got.p_upper + got.p_uncensored == pytest.approx(1.0, abs=1e-12)


@PROPS
@given(windows())
def test_truncated_variance_positive_and_at_most_sigma2(w):
    mu, sigma, lo, hi = w
    got = censored_moments(mu, sigma, lo, hi)
    # Truncating a log-concave density can only shrink the variance; it stays > 0 for a window
    # of positive width (unless the width underflows relative to sigma).
    width = hi - lo
    assert got.truncated_var <= sigma**2 * (1 + 1e-12)
    if width > 1e-6 * sigma:
        assert got.truncated_var > 0.0
    assert np.isfinite(got.censored_var) and got.censored_var >= 0.0
    assert got.censored_var <= sigma**2 * (1 + 1e-12)  # clipping is a contraction


@PROPS
@given(windows())
def test_means_lie_inside_the_limits(w):
    mu, sigma, lo, hi = w
    got = censored_moments(mu, sigma, lo, hi)
    slack = 8 * EPS * max(abs(mu), abs(lo) if np.isfinite(lo) else 0.0, abs(hi) if np.isfinite(hi) else 0.0)
    for val in (got.censored_mean, got.truncated_mean):
        assert np.isfinite(val)
        assert lo - slack <= val <= hi + slack


@PROPS
@given(windows())
def test_mirror_symmetry(w):
    """y = clip(y*, l, h) mirrored: -y = clip(-y*, -h, -l) with -y* ~ N(-mu, sigma^2)."""
    mu, sigma, lo, hi = w
    a = censored_moments(mu, sigma, lo, hi)
    b = censored_moments(-mu, sigma, -hi, -lo)
    scale = max(abs(mu), abs(lo) if np.isfinite(lo) else 0.0, abs(hi) if np.isfinite(hi) else 0.0, sigma)
    assert b.p_lower == pytest.approx(a.p_upper, rel=1e-12, abs=TINY)
    assert b.p_upper == pytest.approx(a.p_lower, rel=1e-12, abs=TINY)
    assert b.p_uncensored == pytest.approx(a.p_uncensored, rel=1e-12, abs=TINY)
    assert b.inverse_mills == pytest.approx(-a.inverse_mills, rel=1e-10, abs=16 * EPS * scale / sigma)
    assert b.truncated_mean == pytest.approx(-a.truncated_mean, rel=1e-10, abs=16 * EPS * scale)
    assert b.censored_mean == pytest.approx(-a.censored_mean, rel=1e-10, abs=16 * EPS * scale)
    assert b.truncated_var == pytest.approx(a.truncated_var, rel=1e-9, abs=1e-14 * sigma**2)
    assert b.censored_var == pytest.approx(a.censored_var, rel=1e-9, abs=1e-12 * sigma**2)


@PROPS
@given(mus, sigmas, st.floats(-8, 8), st.sampled_from([40.0, 60.0, 1e3, 1e6, 1e100]))
def test_far_limit_equals_one_sided(mu, sigma, za, far):
    """Continuity: a second limit far away (40 sigma or more) gives the one-sided statistics."""
    lo = mu + za * sigma
    one = censored_moments(mu, sigma, lo, np.inf)
    two = censored_moments(mu, sigma, lo, mu + far * sigma)
    hi = mu - za * sigma
    one_r = censored_moments(mu, sigma, -np.inf, hi)
    two_r = censored_moments(mu, sigma, mu - far * sigma, hi)
    for x, y in ((one, two), (one_r, two_r)):
        for _, attr in FIELDS:
            assert getattr(y, attr) == pytest.approx(getattr(x, attr), rel=1e-12, abs=1e-14 * max(1.0, abs(mu))), attr


@PROPS
@given(mus, sigmas, st.floats(40, 1000))
def test_limits_40_sigma_away_are_finite(mu, sigma, k):
    # all mass on the uncensored side: statistics of the plain normal
    for lo, hi in ((mu - k * sigma, np.inf), (-np.inf, mu + k * sigma), (mu - k * sigma, mu + k * sigma)):
        got = censored_moments(mu, sigma, lo, hi)
        assert got.p_uncensored == 1.0
        assert got.censored_mean == pytest.approx(mu, rel=1e-13, abs=1e-13 * sigma)
        assert got.censored_var == pytest.approx(sigma**2, rel=1e-12)
        assert got.truncated_var == pytest.approx(sigma**2, rel=1e-12)
    # all mass censored: E[y] is the limit, the truncated moments stay finite and sit next to it
    for lo, hi in (
        (mu + k * sigma, np.inf),
        (mu + k * sigma, mu + (k + 1) * sigma),
        (-np.inf, mu - k * sigma),
        (mu - (k + 1) * sigma, mu - k * sigma),
    ):
        got = censored_moments(mu, sigma, lo, hi)
        vals = np.array([getattr(got, attr) for _, attr in FIELDS], dtype=float)
        assert np.isfinite(vals).all()
        assert got.p_uncensored < 1e-300
        edge = lo if np.isfinite(lo) and lo > mu else hi
        assert got.censored_mean == pytest.approx(edge, rel=1e-12, abs=1e-12 * sigma)
        # beyond a z-score k the truncated normal is nearly exponential: mean offset
        # sigma (1/k - 2/k^3 + ...), variance sigma^2 (1/k^2 - 6/k^4 + ...); the offset is a
        # difference of two numbers of size |edge|, so it also carries a few eps*|edge| of rounding
        slack = 16 * EPS * max(abs(mu), abs(edge))
        assert abs(got.truncated_mean - edge) == pytest.approx(sigma / k, rel=3.0 / k**2, abs=slack)
        assert got.truncated_var == pytest.approx((sigma / k) ** 2, rel=8.0 / k**2)


FP_STRICT = dict(over="raise", invalid="raise", divide="raise", under="ignore")  # underflow to 0 is expected


@pytest.mark.parametrize("far", [1e3, 1e6, 1e10, 1e100, 1e200])
def test_extreme_limits_are_exact_and_quiet(far):
    """Limits arbitrarily far away: no overflow/invalid warnings, never NaN.

    On the uncensored side a limit `far` sigma away is the one-sided formula; on the
    censored side E[y] is exactly the limit and the truncated moments follow the
    exponential tail (mean offset sigma/z, variance (sigma/z)^2). "Never return silent
    garbage" (DESIGN.md): a NaN here would turn a TKF state into NaN.
    """
    mu, sigma = 0.5, 0.1
    with np.errstate(**FP_STRICT):
        one = censored_moments(mu, sigma, 0.0, np.inf)
        two = censored_moments(mu, sigma, 0.0, mu + far * sigma)
        both = censored_moments(mu, sigma, mu - far * sigma, mu + far * sigma)
        up = censored_moments(mu, sigma, mu + far * sigma, np.inf)  # all censored at the lower limit
        down = censored_moments(mu, sigma, -np.inf, mu - far * sigma)  # all censored at the upper limit
        narrow = censored_moments(mu, sigma, mu + far * sigma, mu + 2 * far * sigma)
    for _, attr in FIELDS:
        assert getattr(two, attr) == pytest.approx(getattr(one, attr), rel=1e-14), attr
    assert both.p_uncensored == 1.0 and both.censored_var == pytest.approx(sigma**2, rel=1e-14)
    for got, edge in ((up, mu + far * sigma), (down, mu - far * sigma), (narrow, mu + far * sigma)):
        vals = np.array([getattr(got, attr) for _, attr in FIELDS], dtype=float)
        assert np.isfinite(vals).all(), vals
        assert got.p_uncensored == 0.0
        assert got.censored_mean == edge
        assert got.censored_var == 0.0
        # the window's mass sits within a few sigma/far of the limit
        assert abs(got.truncated_mean - edge) <= 1.01 * sigma / far + 4 * EPS * abs(edge)
        assert 0.0 <= got.truncated_var <= (1.01 * sigma / far) ** 2


def test_broadcasting_shapes():
    mu = np.linspace(-1, 1, 6).reshape(2, 3)
    got = censored_moments(mu, 0.5, np.array([-0.5, 0.0, -np.inf]), np.inf)
    for _, attr in FIELDS:
        assert getattr(got, attr).shape == (2, 3)
    # the -inf channel is an uncensored channel
    assert np.all(got.p_uncensored[:, 2] == 1.0)
    np.testing.assert_array_equal(got.censored_mean[:, 2], mu[:, 2])


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(mean=0.0, std=0.0, lower=0.0, upper=1.0), "std"),
        (dict(mean=0.0, std=-1.0, lower=0.0, upper=1.0), "std"),
        (dict(mean=0.0, std=np.nan, lower=0.0, upper=1.0), "std"),
        (dict(mean=0.0, std=1.0, lower=1.0, upper=1.0), "lower"),
        (dict(mean=0.0, std=1.0, lower=2.0, upper=1.0), "lower"),
        (dict(mean=0.0, std=1.0, lower=np.nan, upper=1.0), "lower"),
    ],
)
def test_invalid_arguments(kwargs, match):
    with pytest.raises(ValidationError, match=match):
        censored_moments(**kwargs)


# ---------------------------------------------------------------------------------------------
# the one-sided tail route (continued fraction) against an independent 40-digit evaluation
# ---------------------------------------------------------------------------------------------
def _tail_reference(x: float):
    """E[Z | Z > x] and Var[Z | Z > x] from 1500 levels of the continued fraction in 40-digit decimals."""
    from decimal import Decimal, getcontext

    getcontext().prec = 40
    xd, s = Decimal(x), Decimal(0)
    for k in range(1500, 1, -1):
        s = Decimal(k) / (xd + s)
    t = 1 / (xd + s)
    return float(xd + t), float(t * (s - t))


@pytest.mark.parametrize("x", [4.0 + 1e-9, 5.0, 5.5, 7.0, 12.0, 26.0, 37.5, 40.0, 41.0, 160.0, 1000.0, 1e5])
@pytest.mark.parametrize("side", ["left", "right"])
def test_one_sided_tail_route_is_accurate(x, side):
    """A limit x sigma into the censored side (the continued-fraction route): the inverse Mills ratio
    and the truncated variance to a few ulp of a 40-digit reference, the uncensored probability to
    scipy's ndtr where that does not underflow, out to 10^5 sigma."""
    lam, zvar = _tail_reference(x)
    sigma, mu = 0.3, 1.0
    lo, hi = (mu + x * sigma, np.inf) if side == "left" else (-np.inf, mu - x * sigma)
    got = censored_moments(mu, sigma, lo, hi)
    sign = 1.0 if side == "left" else -1.0
    assert float(got.inverse_mills) == pytest.approx(sign * lam, rel=4 * EPS)
    assert float(got.truncated_var) == pytest.approx(sigma**2 * zvar, rel=8 * EPS)
    from scipy.special import ndtr

    ref_gamma = float(ndtr(-x))
    if ref_gamma > TINY:
        assert float(got.p_uncensored) == pytest.approx(ref_gamma, rel=1e-13)
    else:
        assert 0.0 <= float(got.p_uncensored) <= 1.01 * TINY or ref_gamma == 0.0


def test_one_sided_route_is_continuous_at_its_switches():
    """Across a' = 4 (direct formulas -> continued fraction) and across the far-limit threshold
    b'^2 - a'^2 = 100 (quadrature -> continued fraction) the statistics do not jump."""
    eps = 1e-9
    for lo_a, hi_a in ((4.0 - eps, 4.0 + eps),):
        a = censored_moments(0.0, 1.0, lo_a, np.inf)
        b = censored_moments(0.0, 1.0, hi_a, np.inf)
        for _, attr in FIELDS:
            assert float(getattr(a, attr)) == pytest.approx(float(getattr(b, attr)), rel=1e-7, abs=1e-300)
    x = 6.0
    far = np.sqrt(100.0 + x * x)
    a = censored_moments(0.0, 1.0, x, far - eps)  # two-sided in the tail: quadrature
    b = censored_moments(0.0, 1.0, x, far + eps)  # far limit negligible: continued fraction
    for _, attr in FIELDS:  # (p_upper = Phi(-b) itself moves by b * eps relative)
        rel = 1e-7 if attr == "p_upper" else 1e-11
        assert float(getattr(a, attr)) == pytest.approx(float(getattr(b, attr)), rel=rel, abs=1e-300)


def test_small_path_equals_the_array_path():
    """Up to 4 entries take the per-entry route on Python floats (the online step of one run); more take the
    array code. Both evaluate the same routes, so they agree to a few ulp on every route: direct, continued
    fraction (one-sided far tail), quadrature (narrow or two-sided in a tail), mirrored windows, infinite
    limits. A NaN mean (a diverged run) falls back to the array code and propagates NaN."""
    from tobitkf.censored import unchecked_moments

    rng = np.random.default_rng(11)
    n = 4000
    mu = rng.normal(size=n) * rng.choice([0.1, 1.0, 5.0, 30.0, 1000.0], size=n)
    sd = np.exp(rng.normal(size=n))
    lo = np.where(rng.random(n) < 0.3, -np.inf, 3.0 * rng.normal(size=n))
    hi = np.where(rng.random(n) < 0.4, np.inf, lo + np.exp(2.0 * rng.normal(size=n)))
    hi = np.where(np.isinf(lo) & np.isinf(hi), 1.0, hi)
    whole = unchecked_moments(mu, sd, lo, hi)  # n > 4: the array code
    a, b = (lo - mu) / sd, (hi - mu) / sd
    aa = np.minimum(np.abs(a), np.abs(b))
    assert (aa > 4).sum() > 100 and ((b - a) < 1).sum() > 100  # the tail routes are exercised
    for i in range(0, n, 2):  # pairs: the small path on (2,) inputs
        part = unchecked_moments(mu[i : i + 2], sd[i : i + 2], lo[i : i + 2], hi[i : i + 2])
        for got, ref in zip(part, whole):
            np.testing.assert_allclose(got, ref[i : i + 2], rtol=1e-13, atol=1e-300)
    nan = unchecked_moments(np.array([np.nan, 0.0]), 1.0, 0.0, np.inf)
    assert np.isnan(nan.censored_mean[0]) and nan.censored_mean[1] == pytest.approx(
        1.0 / math.sqrt(2.0 * math.pi)
    )  # E[max(Z, 0)] = phi(0)
