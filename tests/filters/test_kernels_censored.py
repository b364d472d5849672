"""The compiled censored-normal statistics (``_compiled_censored``: the vectorised one-sided block routes and
``censored_stats``, which every compiled caller uses).

Checked against three independent things: the high-precision numpy reference ``tobitkf.censored_moments``
(itself tested against 60-digit values), Laplace's continued fraction run to 3000 terms (a converged oracle
for the truncated moments beyond the erfcx route, where the reference's direct formulas cancel), and the
60-digit vectors of ``shared/vectors``. The two-sided and interval routes against the reference are in
``tests/filters/test_kernels.py`` (``test_stats_*``).
"""

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("numba")
from tobitkf.censored import censored_moments  # noqa: E402
from tobitkf.filters import _compiled_censored as kc  # noqa: E402

VECTORS = Path("/work/shared/vectors/censoring_stats.json")


def reference(mu, sd, lim, upper):
    """The reference statistics (8, K) of ``censored_moments`` for a lower (or upper) limit ``lim``."""
    mu = np.ascontiguousarray(mu, dtype=float)
    return np.array(censored_moments(mu, sd, -np.inf if upper else lim, lim if upper else np.inf))


def assert_close(got, want, rtol, atol, where):
    """|got - want| <= rtol |want| + atol elementwise (``atol`` may be an array); names the first misses."""
    bad = ~(np.abs(got - want) <= rtol * np.abs(want) + atol)
    assert not bad.any(), (where[bad][:5], got[bad][:5], want[bad][:5])


def noise_of(stats, mu, code):
    """The noise term of ``code`` (NOISE_CODES) from the reference statistics, as tobit_update_block forms it."""
    if code == 0:
        return stats[5]
    if code == 1:
        return stats[7]
    return stats[2] * (stats[5] + (stats[4] - mu) ** 2)


def standardized_grid():
    """The standardized lower limit a: dense in the central routes, the route switches (-4, 0, 2 and 4,
    where the reference switches), the tails out to 1e5 sigma, and where e^{-a^2/2} becomes subnormal
    and underflows (a ~ 37.7 to 38.6)."""
    rng = np.random.default_rng(0)
    edges = np.array([-4.0, 0.0, 2.0, 4.0])
    return np.concatenate(
        [
            rng.uniform(-8.0, 8.0, 20000),
            -np.geomspace(4.0, 60.0, 500),
            np.geomspace(1e-6, 1e5, 2000),
            edges,
            edges + 1e-12,
            edges - 1e-12,
            np.linspace(37.5, 39.0, 301),
        ]
    )


@pytest.mark.parametrize("upper", [False, True])
@pytest.mark.parametrize("code", [0, 1, 2])
def test_block_equals_the_reference_statistics(upper, code):
    """gamma and E(y) to 1e-13 of the reference (relative, or absolute on the means' scale); the noise
    term to 1e-13 wherever the reference itself is that accurate (below a = 2), and beyond a = 2, where
    the reference's direct formula 1 + a lambda - lambda^2 cancels (up to a = 4), within the sum of both
    errors against the converged continued fraction (next test) plus 1e-14."""
    a = standardized_grid()
    sd, lim = 0.7, 0.3
    mu = lim + a * sd if upper else lim - a * sd
    gam, noise, cmean = kc.one_sided_array(np.ascontiguousarray(mu), sd, lim, upper, code)
    ref = reference(mu, sd, lim, upper)
    scale = np.abs(mu) + sd + abs(lim)
    assert_close(gam, ref[2], 1e-13, 1e-300, a)
    assert_close(cmean, ref[6], 1e-13, 1e-14 * scale, a)
    rn = noise_of(ref, mu, code)
    c = a <= 2.0
    assert_close(noise[c], rn[c], 1e-13, 1e-14 * sd * scale[c], a[c])
    assert_close(noise, rn, 1.5e-12, 1e-14 * sd * scale, a)
    for v in (gam, noise, cmean):
        assert np.isfinite(v).all()


def converged_tail(a):
    """``(lambda, Var[Z | Z > a])`` by Laplace's continued fraction with 3000 terms (converged for a >= 2)."""
    s = np.zeros_like(a)
    for k in range(3000, 1, -1):
        s = k / (a + s)
    t = 1.0 / (a + s)
    return a + t, t * (s - t)


def test_tail_route_is_at_least_as_accurate_as_the_reference():
    """Beyond a = 2 the block computes lambda and the variance from fits of the continued fraction (no
    cancellation): within 2e-14 of the converged fraction everywhere, and at least as close to it as the
    reference (whose direct formula loses up to ~1e-12 just below a = 4)."""
    a = np.concatenate([np.linspace(2.0 + 1e-9, 4.0, 4001), np.geomspace(4.0, 1e4, 2001)])
    lam_true, var_true = converged_tail(a)
    mu = -a  # sd 1, lower limit 0
    _, tvar, _ = kc.one_sided_array(np.ascontiguousarray(mu), 1.0, 0.0, False, 0)
    ref = reference(mu, 1.0, 0.0, False)
    err_block = np.abs(tvar / var_true - 1.0)
    err_ref = np.abs(ref[5] / var_true - 1.0)
    assert err_block.max() < 2e-14, (a[np.argmax(err_block)], err_block.max())
    assert np.all(err_block <= err_ref + 2e-14)
    # gamma = phi(a) / lambda against the same lambda
    gam, _, cmean = kc.one_sided_array(np.ascontiguousarray(mu), 1.0, 0.0, False, 0)
    phi = np.exp(-0.5 * a * a) / np.sqrt(2.0 * np.pi)
    fine = phi > 1e-300  # not subnormal
    np.testing.assert_allclose(gam[fine], phi[fine] / lam_true[fine], rtol=2e-13)


def test_against_60_digit_vectors():
    """Every one-sided case of the shared 60-digit vectors: gamma, E(y) and the three noise terms no less
    accurate than the reference (plus 1e-12 of their scale)."""
    if not VECTORS.exists():
        pytest.skip("shared vectors not available")
    cases = [
        c
        for c in json.loads(VECTORS.read_text())["cases"]
        if (float(c["lower"]) == -np.inf) != (float(c["upper"]) == np.inf)
    ]
    assert len(cases) >= 50
    for c in cases:
        mu, sd, lo, hi = (float(c[k]) for k in ("mu", "sigma", "lower", "upper"))
        upper = lo == -np.inf
        lim = hi if upper else lo
        ref = reference(np.array([mu]), sd, lim, upper)[:, 0]
        exact = {k: float(c[k]) for k in ("p_uncensored", "truncated_variance", "censored_mean", "censored_variance")}
        for code, key in ((0, "truncated_variance"), (1, "censored_variance")):
            gam, noise, cmean = (v[0] for v in kc.one_sided_array(np.array([mu]), sd, lim, upper, code))
            rn = ref[5] if code == 0 else ref[7]
            scale = abs(mu) + sd + abs(lim)
            for got, want, mine in ((gam, exact["p_uncensored"], ref[2]), (cmean, exact["censored_mean"], ref[6])):
                assert abs(got - want) <= abs(mine - want) + 1e-12 * max(abs(want), 1e-300) + 1e-15 * scale, (c, got)
            assert abs(noise - exact[key]) <= abs(rn - exact[key]) + 1e-12 * abs(exact[key]) + 1e-300, (c, noise)


@settings(max_examples=80, deadline=None)
@given(
    mu=st.floats(-1e3, 1e3),
    sd=st.floats(1e-3, 1e2),
    a=st.floats(-60.0, 1e4),
    upper=st.booleans(),
    code=st.sampled_from([0, 1, 2]),
)
def test_block_property(mu, sd, a, upper, code):
    """Any mean, scale and limit: finite, gamma in [0, 1], and the reference's numbers (the looser
    noise tolerance of the first test)."""
    lim = mu - a * sd if upper else mu + a * sd
    gam, noise, cmean = (v[0] for v in kc.one_sided_array(np.array([mu]), sd, lim, upper, code))
    ref = reference(np.array([mu]), sd, lim, upper)[:, 0]
    scale = abs(mu) + sd + abs(lim)
    assert 0.0 <= gam <= 1.0 and np.isfinite(noise) and np.isfinite(cmean)
    assert abs(gam - ref[2]) <= 1e-13 * ref[2] + 1e-300
    assert abs(cmean - ref[6]) <= 1e-13 * abs(ref[6]) + 1e-14 * scale
    rn = float(noise_of(ref, mu, code))
    assert abs(noise - rn) <= 1.5e-12 * abs(rn) + 1e-14 * sd * scale


def test_exp_without_libm():
    """The polynomial exponential: to 2 ulp on [-745, 0], 0 below the subnormals, subnormals kept."""
    z = np.concatenate([-np.geomspace(1e-12, 745.0, 20000), [0.0, -708.0, -740.0, -744.4, -745.3, -1e6]])

    from numba import njit

    @njit
    def run(z):
        out = np.empty_like(z)
        for i in range(z.shape[0]):
            out[i] = kc._exp_neg(z[i])
        return out

    got, want = run(z), np.exp(z)
    normal = want > 2.3e-308
    np.testing.assert_allclose(got[normal], want[normal], rtol=4.5e-16)
    np.testing.assert_allclose(got[~normal], want[~normal], rtol=0, atol=1e-322)
    assert got[-1] == 0.0 and got[-2] == 0.0


def test_lower_stats_block_gives_every_statistic_of_the_reference():
    """The form the fading and protocol kernels read: gamma, lambda, the truncated variance, the censored mean
    and variance, against the reference (lambda to 1e-13; the variances as in the first test)."""
    a = standardized_grid()
    sd, lo = 0.4, -0.2
    mu = lo - a * sd
    got = kc.lower_stats_array(np.ascontiguousarray(mu), sd, lo)
    ref = reference(mu, sd, lo, False)
    scale = np.abs(mu) + sd + abs(lo)
    assert_close(got[0], ref[2], 1e-13, 1e-300, a)
    assert_close(got[1], ref[3], 1e-13, 1e-300, a)
    assert_close(got[3], ref[6], 1e-13, 1e-14 * scale, a)
    for i, j in ((2, 5), (4, 7)):
        c = a <= 2.0
        assert_close(got[i][c], ref[j][c], 1e-13, 1e-14 * sd * scale[c], a[c])
        assert_close(got[i], ref[j], 1.5e-12, 1e-14 * sd * scale, a)


def test_censored_stats_against_the_reference_on_a_grid():
    """``censored_stats`` (the statistics every compiled caller uses) against ``censored_moments`` on a grid of
    standardized lower limits a in [-40, 40] and windows [a, a + w] (w from 1e-3 sigma, the quadrature
    route, to one-sided), lower and mirrored upper, and no limit. Bounds: the probabilities 3e-13 relative
    (the reference's ndtr loses ~a^2 eps far in a tail, 1.8e-13 at 37 sigma; subnormal ones to 1e-300
    absolute); the inverse Mills ratio and the means 1e-13 relative plus 1e-14 of the limits' scale; the
    variances 2e-12 relative (the reference's direct two-sided formula cancels near 4 sigma, 1.1e-12 from
    60-digit values: next test)."""
    a = np.concatenate([np.linspace(-40.0, 40.0, 801), [-40.0 - 1e-9, 40.0 + 1e-9, -4.0, 4.0, -2.0, 2.0]])
    w = np.array([1e-3, 0.01, 0.3, 1.0 - 1e-12, 1.0, 2.0, 5.0, 12.0, np.inf])
    A, W = (v.ravel() for v in np.meshgrid(a, w))
    mu, sd = 0.3, 0.7
    lo = mu + sd * A
    hi = np.where(np.isinf(W), np.inf, mu + sd * (A + W))
    for lo_, hi_ in ((lo, hi), (-hi, -lo), (np.full(2, -np.inf), np.full(2, np.inf))):
        m, s = np.full(lo_.size, mu), np.full(lo_.size, sd)
        ref = np.array(censored_moments(m, s, lo_, hi_))
        got = kc.censored_moments_array(m, s, np.ascontiguousarray(lo_), np.ascontiguousarray(hi_), kc.GL_X, kc.GL_W)
        assert np.isfinite(got).all()
        scale = mu + sd + np.abs(np.where(np.isfinite(lo_), lo_, 0.0)) + np.abs(np.where(np.isfinite(hi_), hi_, 0.0))
        where = np.stack([lo_, hi_], 1)
        for i in (0, 1, 2):
            assert_close(got[i], ref[i], 3e-13, 1e-300, where)
        for i in (3, 4, 6):
            assert_close(got[i], ref[i], 1e-13, 1e-14 * scale, where)
        for i in (5, 7):
            assert_close(got[i], ref[i], 2e-12, 1e-300, where)


def test_two_sided_variance_against_60_digit_values():
    """Windows [a, a + w] in the lower tail near the route switch at 4 sigma, where the direct formula
    1 + (a phi(a) - b phi(b)) / gamma - lambda^2 cancels: the compiled truncated variance within 4e-13 of
    60-digit values (Decimal arithmetic; Q(x) by Laplace's continued fraction, 20000 terms)."""
    from decimal import Decimal, getcontext

    getcontext().prec = 60
    pi = Decimal("3.14159265358979323846264338327950288419716939937510582097494")

    def phi(x):
        return (-(x * x) / 2).exp() / (2 * pi).sqrt()

    def q(x):
        s = Decimal(0)
        for k in range(20000, 0, -1):
            s = Decimal(k) / (x + s)
        return phi(x) / (x + s)

    mu, sd = 0.3, 0.7
    for a, w in ((-5.0, 1.0), (-4.9, 1.0), (-6.0, 2.0), (-3.6, 1.5), (-7.0, 3.0)):
        lo, hi = mu + sd * a, mu + sd * (a + w)
        a2, b2 = (Decimal(mu) - Decimal(hi)) / Decimal(sd), (Decimal(mu) - Decimal(lo)) / Decimal(sd)  # mirrored
        g = q(a2) - q(b2)
        lam = (phi(a2) - phi(b2)) / g
        exact = (1 + (a2 * phi(a2) - b2 * phi(b2)) / g - lam * lam) * Decimal(sd) ** 2
        got = kc.censored_moments_array(
            np.array([mu]), np.array([sd]), np.array([lo]), np.array([hi]), kc.GL_X, kc.GL_W
        )
        assert abs(float((Decimal(got[5, 0]) - exact) / exact)) < 4e-13, (a, w)
