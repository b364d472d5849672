"""Sigma-point rules integrate every monomial of their degree exactly, mixed ones included.

The oracle is Stein's identity for :math:`x \\sim N(m, P)`, :math:`E[x_i g(x)] = m_i E[g(x)] + \\sum_j P_{ij}
E[\\partial_j g(x)]`, which gives the moment of every monomial :math:`x^\\alpha` by recursion on its degree: no
quadrature and none of the rules' code. ``tests/filters/test_nonlinear.py`` checks powers of a few linear forms;
here every monomial up to the degree is checked, in a correlated 3-D Gaussian.
"""

from __future__ import annotations

import itertools
from functools import lru_cache

import numpy as np
import pytest

import tobitkf as tk

N = 3
RNG = np.random.default_rng(31)
M = RNG.normal(size=N)
_G = RNG.normal(size=(N, N))
P = _G @ _G.T + 0.5 * np.eye(N)


@lru_cache(maxsize=None)
def gaussian_moment(alpha: tuple[int, ...]) -> float:
    """E[prod_i x_i^alpha_i], x ~ N(M, P), by Stein's identity (recursion on the degree)."""
    if sum(alpha) == 0:
        return 1.0
    i = next(j for j, a in enumerate(alpha) if a > 0)
    rest = list(alpha)
    rest[i] -= 1
    out = M[i] * gaussian_moment(tuple(rest))
    for j in range(N):
        if rest[j] > 0:
            lower = list(rest)
            lower[j] -= 1
            out += P[i, j] * rest[j] * gaussian_moment(tuple(lower))
    return out


def monomials(degree: int):
    return [a for a in itertools.product(range(degree + 1), repeat=N) if sum(a) == degree]


RULES = [
    ({"rule": "unscented"}, 3),
    ({"rule": "unscented", "alpha": 0.3, "beta": 2.0, "kappa": 1.0}, 3),
    ({"rule": "unscented", "alpha": 1.0, "beta": 0.0, "kappa": 0.0}, 3),
    ({"rule": "cubature"}, 3),
    ({"rule": "gauss_hermite", "order": 1}, 1),
    ({"rule": "gauss_hermite", "order": 2}, 3),
    ({"rule": "gauss_hermite", "order": 3}, 5),
    ({"rule": "gauss_hermite", "order": 4}, 7),
]


def _rule_mean(rule, alpha):
    X = rule.points(M[None], P[None])[0]  # (L, n)
    _, wm, _ = rule.unit(N)
    return float(wm @ np.prod(X ** np.array(alpha), axis=-1))


@pytest.mark.parametrize(
    "opts,degree", RULES, ids=lambda v: "-".join(map(str, v.values())) if isinstance(v, dict) else v
)
def test_every_monomial_up_to_the_degree_is_exact_and_one_beyond_is_not(opts, degree):
    rule = tk.SigmaPoints(**opts)
    for d in range(degree + 1):
        for alpha in monomials(d):
            want = gaussian_moment(alpha)
            assert _rule_mean(rule, alpha) == pytest.approx(want, rel=1e-10, abs=1e-10), (alpha, want)
    # the degree is sharp: some monomial of the next degree is not integrated
    assert any(
        abs(_rule_mean(rule, alpha) - gaussian_moment(alpha)) > 1e-6 * max(1.0, abs(gaussian_moment(alpha)))
        for alpha in monomials(degree + 1)
    )


@pytest.mark.parametrize(
    "opts,degree",
    [r for r in RULES if r[1] >= 2],
    ids=lambda v: "-".join(map(str, v.values())) if isinstance(v, dict) else v,
)
def test_the_covariance_weights_give_back_the_covariance(opts, degree):
    # sum_l w^c_l (X_l - m)(X_l - m)^T = P for every rule of degree 2 or more (the unscented beta term sits on the centre point, whose
    # deviation is zero), and the mean weights sum to 1
    rule = tk.SigmaPoints(**opts)
    X = rule.points(M[None], P[None])[0]
    _, wm, wc = rule.unit(N)
    D = X - M
    np.testing.assert_allclose((D * wc[:, None]).T @ D, P, rtol=0, atol=1e-12)
    assert wm.sum() == pytest.approx(1.0, abs=1e-13)
