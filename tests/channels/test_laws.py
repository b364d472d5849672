"""Tests of the coefficient laws (tobitkf.channels.laws)."""

import numpy as np
import pytest

from tobitkf._validation import ShapeError, ValidationError
from tobitkf.channels.laws import PMF, Constant, Gaussian, Uniform, as_law


def test_gaussian_moments_and_shapes():
    law = Gaussian([0.95, 0.75, 0.85], [0.0081, 0.0064, 0.0049])
    np.testing.assert_array_equal(law.mean, [0.95, 0.75, 0.85])
    np.testing.assert_array_equal(law.variance, [0.0081, 0.0064, 0.0049])
    np.testing.assert_allclose(law.second_moment, law.variance + law.mean**2)
    assert law.sample(np.random.default_rng(0), (5, 2)).shape == (5, 2, 3)
    assert law[1:].shape == (2,)


def test_uniform_closed_form_moments():
    law = Uniform([0.0, 0.2], [1.0, 0.8])
    np.testing.assert_allclose(law.mean, [0.5, 0.5])
    np.testing.assert_allclose(law.variance, [1 / 12, 0.36 / 12])


def test_pmf_closed_form_moments():
    # spec 002 §5 base pmf: values {0.95, 0.98, 1}, probs {0.05, 0.15, 0.8}
    law = PMF([0.95, 0.98, 1.0], [0.05, 0.15, 0.8])
    mean = 0.05 * 0.95 + 0.15 * 0.98 + 0.8
    np.testing.assert_allclose(law.mean, mean, rtol=1e-15)
    np.testing.assert_allclose(law.second_moment, 0.05 * 0.95**2 + 0.15 * 0.98**2 + 0.8, rtol=1e-14)
    # Bernoulli special case: variance p(1-p)
    b = PMF([0.0, 1.0], [0.3, 0.7])
    np.testing.assert_allclose(b.variance, 0.21, rtol=1e-14)


def test_pmf_batched_laws_and_indexing():
    law = PMF([[0.0, 1.0], [2.0, 3.0]], [[0.5, 0.5], [0.25, 0.75]])
    assert law.shape == (2,)
    np.testing.assert_allclose(law.mean, [0.5, 2.75])
    assert law[1].shape == ()
    np.testing.assert_allclose(law[1].mean, 2.75)


@pytest.mark.parametrize(
    "law",
    [
        Gaussian([1.0, -2.0], [0.25, 4.0]),
        Uniform([0.0, 0.5], [1.0, 0.9]),
        PMF([[0.1, 0.5, 0.9], [0.0, 1.0, 2.0]], [[0.2, 0.3, 0.5], [0.6, 0.3, 0.1]]),
    ],
)
def test_sample_moments_match_within_monte_carlo_error(law):
    n = 200_000
    draws = law.sample(np.random.default_rng(42), n)
    assert draws.shape == (n,) + law.shape
    se_mean = np.sqrt(law.variance / n)
    assert np.all(np.abs(draws.mean(0) - law.mean) <= 6 * se_mean + 1e-12)
    # variance of the sample variance <= E[(x-mu)^4]/n; bound fourth moment crudely by 9 sigma^4
    se_var = np.sqrt(9 * law.variance**2 / n)
    assert np.all(np.abs(draws.var(0) - law.variance) <= 6 * se_var + 1e-12)


def test_pmf_samples_only_support_points():
    law = PMF([0.95, 0.98, 1.0], [0.05, 0.15, 0.8])
    draws = law.sample(np.random.default_rng(1), 1000)
    assert set(np.unique(draws)) <= {0.95, 0.98, 1.0}


def test_same_generator_seed_same_draws():
    law = Gaussian([0.5, 0.7], [0.01, 0.02])
    a = law.sample(np.random.default_rng(7), 3)
    b = law.sample(np.random.default_rng(7), 3)
    np.testing.assert_array_equal(a, b)


def test_constant_and_as_law():
    c = Constant([1.0, 2.0])
    np.testing.assert_array_equal(c.sample(np.random.default_rng(0), 2), [[1.0, 2.0], [1.0, 2.0]])
    assert as_law(c) is c
    np.testing.assert_array_equal(as_law([0.3]).mean, [0.3])


def test_bad_input_names_the_argument():
    with pytest.raises(ValidationError, match="variance"):
        Gaussian([1.0], [-0.1])
    with pytest.raises(ShapeError, match="mean/variance"):
        Gaussian([1.0, 2.0], [0.1, 0.2, 0.3])
    with pytest.raises(ValidationError, match="low/high"):
        Uniform(1.0, 0.5)
    with pytest.raises(ValidationError, match="probs"):
        PMF([0.0, 1.0], [0.5, 0.6])
    with pytest.raises(ValidationError, match="probs"):
        PMF([0.0, 1.0], [-0.5, 1.5])
    with pytest.raises(ShapeError, match="probs"):
        PMF([0.0, 1.0, 2.0], [0.5, 0.5])
    with pytest.raises(ShapeError, match="values"):
        PMF(1.0, [1.0])
    with pytest.raises(ValidationError, match="mean"):
        Gaussian([np.nan], [0.1])
    with pytest.raises(ValidationError, match="rng"):
        Gaussian(1.0).sample(0, 3)
    with pytest.raises(ValidationError, match="law"):
        as_law("gauss")
