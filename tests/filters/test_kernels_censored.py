"""The vectorised one-sided censored statistics of the kernels (``_kernels_censored.one_sided_block``).

Checked against three independent things: the scalar kernel statistics (``censored_stats``, the same numbers
as ``censored_moments``, itself tested against 60-digit values), Laplace's continued fraction run to 3000
terms (a converged oracle for the truncated moments beyond the erfcx route, where both the block and the
scalar route have to fight cancellation), and the 60-digit vectors of ``shared/vectors``.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("numba")
from tobitkf.filters import _kernels  # noqa: E402
from tobitkf.filters import _kernels_censored as kc  # noqa: E402

VECTORS = Path("/work/shared/vectors/censoring_stats.json")


def scalar(mu, sd, lim, upper):
    """The scalar kernel's statistics (8, K) for a lower (or upper) limit ``lim``."""
    mu = np.ascontiguousarray(mu, dtype=float)
    lo = np.full_like(mu, -np.inf if upper else lim)
    hi = np.full_like(mu, lim if upper else np.inf)
    return _kernels.censored_moments_array(mu, np.full_like(mu, sd), lo, hi, _kernels.GL_X, _kernels.GL_W)


def assert_close(got, want, rtol, atol, where):
    """|got - want| <= rtol |want| + atol elementwise (``atol`` may be an array); names the first misses."""
    bad = ~(np.abs(got - want) <= rtol * np.abs(want) + atol)
    assert not bad.any(), (where[bad][:5], got[bad][:5], want[bad][:5])


def noise_of(stats, mu, code):
    """The noise term of ``code`` (NOISE_CODES) from the scalar statistics, as tobit_update_block forms it."""
    if code == 0:
        return stats[5]
    if code == 1:
        return stats[7]
    return stats[2] * (stats[5] + (stats[4] - mu) ** 2)


def standardized_grid():
    """The standardized lower limit a: dense in the central routes, the route switches (-4, 0, 2 and 4,
    where the scalar kernel switches), the tails out to 1e5 sigma, and where e^{-a^2/2} becomes subnormal
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
def test_block_equals_the_scalar_statistics(upper, code):
    """gamma and E(y) to 1e-13 of the scalar kernel (relative, or absolute on the means' scale); the noise
    term to 1e-13 wherever the scalar kernel itself is that accurate (below a = 2), and beyond a = 2, where
    the scalar kernel's direct formula 1 + a lambda - lambda^2 cancels (up to a = 4), within the sum of both
    errors against the converged continued fraction (next test) plus 1e-14."""
    a = standardized_grid()
    sd, lim = 0.7, 0.3
    mu = lim + a * sd if upper else lim - a * sd
    gam, noise, cmean = kc.one_sided_array(np.ascontiguousarray(mu), sd, lim, upper, code)
    ref = scalar(mu, sd, lim, upper)
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


def test_tail_route_is_at_least_as_accurate_as_the_scalar_route():
    """Beyond a = 2 the block computes lambda and the variance from fits of the continued fraction (no
    cancellation): within 2e-14 of the converged fraction everywhere, and at least as close to it as the
    scalar kernel (whose direct formula loses up to ~1e-12 just below a = 4)."""
    a = np.concatenate([np.linspace(2.0 + 1e-9, 4.0, 4001), np.geomspace(4.0, 1e4, 2001)])
    lam_true, var_true = converged_tail(a)
    mu = -a  # sd 1, lower limit 0
    _, tvar, _ = kc.one_sided_array(np.ascontiguousarray(mu), 1.0, 0.0, False, 0)
    ref = scalar(mu, 1.0, 0.0, False)
    err_block = np.abs(tvar / var_true - 1.0)
    err_scalar = np.abs(ref[5] / var_true - 1.0)
    assert err_block.max() < 2e-14, (a[np.argmax(err_block)], err_block.max())
    assert np.all(err_block <= err_scalar + 2e-14)
    # gamma = phi(a) / lambda against the same lambda
    gam, _, cmean = kc.one_sided_array(np.ascontiguousarray(mu), 1.0, 0.0, False, 0)
    phi = np.exp(-0.5 * a * a) / np.sqrt(2.0 * np.pi)
    fine = phi > 1e-300  # not subnormal
    np.testing.assert_allclose(gam[fine], phi[fine] / lam_true[fine], rtol=2e-13)


def test_against_60_digit_vectors():
    """Every one-sided case of the shared 60-digit vectors: gamma, E(y) and the three noise terms no less
    accurate than the scalar kernel (plus 1e-12 of their scale)."""
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
        ref = scalar(np.array([mu]), sd, lim, upper)[:, 0]
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
    """Any mean, scale and limit: finite, gamma in [0, 1], and the scalar kernel's numbers (the looser
    noise tolerance of the first test)."""
    lim = mu - a * sd if upper else mu + a * sd
    gam, noise, cmean = (v[0] for v in kc.one_sided_array(np.array([mu]), sd, lim, upper, code))
    ref = scalar(np.array([mu]), sd, lim, upper)[:, 0]
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


def test_lower_stats_block_gives_every_statistic_of_the_scalar_route():
    """The form the fading and protocol kernels read: gamma, lambda, the truncated variance, the censored mean
    and variance, against the scalar kernel (lambda to 1e-13; the variances as in the first test)."""
    a = standardized_grid()
    sd, lo = 0.4, -0.2
    mu = lo - a * sd
    got = kc.lower_stats_array(np.ascontiguousarray(mu), sd, lo)
    ref = scalar(mu, sd, lo, False)
    scale = np.abs(mu) + sd + abs(lo)
    assert_close(got[0], ref[2], 1e-13, 1e-300, a)
    assert_close(got[1], ref[3], 1e-13, 1e-300, a)
    assert_close(got[3], ref[6], 1e-13, 1e-14 * scale, a)
    for i, j in ((2, 5), (4, 7)):
        c = a <= 2.0
        assert_close(got[i][c], ref[j][c], 1e-13, 1e-14 * sd * scale[c], a[c])
        assert_close(got[i], ref[j], 1.5e-12, 1e-14 * sd * scale, a)
