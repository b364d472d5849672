"""Numerical extremes for every estimator family beyond the core (issue 9 item 3).

Cases: P0 huge (1e8), tiny (1e-12) and zero; R and Q near singular (1e-12) and Q = 0;
an ill-conditioned A (cond ~ 1e8); censoring limits 40 sigma inside and outside the
predicted mean. Every output must be finite, exactly symmetric and PSD (smallest
eigenvalue >= -1e-9 x the largest entry of that covariance or of its prediction),
in both covariance forms where the estimator offers them.

Measured limit (see docs/reliability.md): a huge prior together with a near-singular R
(P0/R >= 1e20) and a direction the first measurement does not see loses PSD in *both*
the plain and the Joseph form (rounding at the level of P0 survives the update, whose
result is 20 orders smaller); the square-root form (``covariance_update="square_root"``)
holds there. The old forms are recorded below as xfails, the square-root form as a passing
case and against a 60-digit reference.
"""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.channels.fading import RiceFading
from tobitkf.channels.protocol import ProtocolChannel
from tobitkf.design.hinf import WANG2010_PAPER
from tobitkf.filters._backend import numba_available
from tobitkf.filters.delay_augmented import augmented_lmmse
from tobitkf.filters.delay_chain import chain_lmmse
from tobitkf.filters.delay_reorganized import reorganized_lmmse
from tobitkf.filters.fading import FadingKalmanFilter, FadingTobitKalmanFilter
from tobitkf.filters.hinf import RegionalHinfFilter
from tobitkf.filters.protocol import ProtocolTobitKalmanFilter
from tobitkf.filters.steady_state import SteadyStateTobitKalmanFilter, tobit_kalman_filter_controlled
from tobitkf.models.delay import DelayFadingSystem, FadingPMF, HistoryPrior
from tobitkf.models.ross import wang2010_model
from tobitkf.simulate.delay import simulate_delay
from tobitkf.simulate.ross import simulate_ross, wang2010_disturbances


def assert_healthy(mean, cov, pred_cov=None, tol=1e-9):
    mean, cov = np.asarray(mean), np.asarray(cov)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))
    np.testing.assert_array_equal(cov, np.swapaxes(cov, -1, -2))
    scale = np.abs(cov).max(axis=(-1, -2))
    if pred_cov is not None:
        scale = np.maximum(scale, np.abs(np.asarray(pred_cov)).max(axis=(-1, -2)))
    eig = np.linalg.eigvalsh(cov)
    worst = (eig.min(axis=-1) / np.maximum(scale, 1e-300)).min()
    assert worst >= -tol, worst


W = 0.05
BASE = dict(
    A=[[np.cos(W), -np.sin(W)], [np.sin(W), np.cos(W)]],
    C=[[1.0, 0.0]],
    Q=0.01 * np.eye(2),
    R=[[0.1]],
    x0=[0.0, 0.0],
    P0=0.05 * np.eye(2),
)
CASES = {
    "P0 huge (1e8)": dict(P0=1e8 * np.eye(2)),
    "P0 tiny (1e-12)": dict(P0=1e-12 * np.eye(2)),
    "P0 zero": dict(P0=np.zeros((2, 2))),
    "R near singular (1e-12)": dict(R=[[1e-12]]),
    "Q near singular (1e-12)": dict(Q=1e-12 * np.eye(2)),
    "Q zero": dict(Q=np.zeros((2, 2))),
    "ill-conditioned A": dict(A=[[1.0, 1e4], [0.0, 1.0]], Q=np.diag([1e-6, 1e-10])),
}
NOMINAL = tk.LinearSystem(**BASE)
CENS = tk.Censoring(lower=0.0)
DATA = tk.simulate(NOMINAL, 150, 4, censoring=CENS, seed=3)  # data from the nominal model


def system(case):
    return tk.LinearSystem(**{**BASE, **CASES[case]})


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("form", ["standard", "joseph"])
def test_fading_filters_extremes(case, form):
    s = system(case)
    out = FadingTobitKalmanFilter(s, RiceFading(2, [0.95, 0.75, 0.85]), CENS, covariance_update=form).filter(
        DATA.y, keep_smoothed=False
    )
    assert_healthy(out.mean, out.cov, out.pred_cov)
    out = FadingKalmanFilter(s, RiceFading(1, [0.9, 0.5]), covariance_update=form).filter(DATA.y, keep_smoothed=False)
    assert_healthy(out.mean, out.cov, out.pred_cov)


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("form", ["standard", "joseph"])
def test_protocol_filter_extremes(case, form):
    s = system(case)
    ch = ProtocolChannel(1, window=1, threshold=0.0)
    out = ProtocolTobitKalmanFilter(s, ch, covariance_update=form).filter(DATA.y)
    assert_healthy(out.mean, out.cov, out.pred_cov)


@pytest.mark.parametrize("case", list(CASES))
def test_steady_state_filters_extremes(case):
    s = system(case)
    out = SteadyStateTobitKalmanFilter(s, 0.5).filter_controlled(DATA.y_latent)
    assert_healthy(out.mean, out.cov)
    out = tobit_kalman_filter_controlled(s, 0.5, DATA.y_latent)
    assert_healthy(out.mean, out.cov, out.pred_cov)


@pytest.mark.parametrize("shift", [-40.0, 40.0])
def test_limits_40_sigma_from_the_prediction_all_families(shift):
    """Limit 40 sigma below (never censored) or above (always censored) the prediction."""
    s = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], x0=[0.0], P0=[[1.0]])
    T = 30
    cens = tk.Censoring(lower=shift)
    y = np.full((3, T, 1), shift if shift > 0 else 0.5)
    fad = FadingTobitKalmanFilter(s, RiceFading(0, [1.0]), cens).filter(y)
    prot = ProtocolTobitKalmanFilter(s, ProtocolChannel(1, threshold=shift)).filter(y)
    kf = tk.KalmanFilter(s).filter(y)
    for out in (fad, prot):
        assert_healthy(out.mean, out.cov, out.pred_cov)
        if shift > 0:  # every reading censored 40 sigma above the prediction: nothing learnt
            np.testing.assert_allclose(out.mean, 0.0, atol=1e-12)
            np.testing.assert_allclose(out.cov[0, :, 0, 0], 1.0 + 0.01 * np.arange(1, T + 1), rtol=1e-12)
        else:  # limit 40 sigma below: the Kalman filter
            np.testing.assert_allclose(out.mean, kf.mean, atol=1e-10)


DELAY_CASES = {
    "nominal": {},
    "Qw near singular": dict(Qw=1e-12, S=np.sqrt(1e-12 * 0.3)),
    "Qv near singular": dict(Qv=1e-12, S=0.0),
    "S at the singular bound": dict(S=np.sqrt(0.3 * 0.3)),
    "ill-conditioned A": dict(A=[[1.0, 1e4], [0.0, 1.0]]),
}


@pytest.mark.parametrize("case", list(DELAY_CASES))
@pytest.mark.parametrize("prior_var", [1e8, 1e-12])
def test_delay_filters_extremes(case, prior_var):
    kw = dict(
        A=[[0.4, 0.7], [0.2, 0.6]],
        H=[[0.5, 1.0]],
        Gamma=[[1.0], [1.0]],
        Qw=0.3,
        Qv=0.3,
        S=0.3,
        d=2,
        fading=FadingPMF([0.95, 0.98, 1.0], [0.05, 0.15, 0.8]),
    )
    kw.update(DELAY_CASES[case])
    sys_ = DelayFadingSystem(**kw)
    truth_sys = DelayFadingSystem(**{**kw, "A": [[0.4, 0.7], [0.2, 0.6]]})
    prior = HistoryPrior.repeated(np.zeros(2), prior_var * np.eye(2), 2)
    data = simulate_delay(truth_sys, HistoryPrior.repeated(np.zeros(2), np.eye(2), 2), 60, 3, seed=1)
    for est in (
        chain_lmmse(sys_, prior, data.y),
        augmented_lmmse(sys_, prior, data.y),
        reorganized_lmmse(sys_, prior, data.y),
    ):
        assert_healthy(est.mean, est.cov, est.pred_cov)


def test_hinf_filter_paper_gains_long_and_huge_inputs_stay_finite():
    """The printed gains are stable: 1e4 steps, and readings of 1e150, stay finite and bounded."""
    model = wang2010_model()
    w, v = wang2010_disturbances(10_000)
    sim = simulate_ross(model, 10_000, 2, x0=WANG2010_PAPER["x0"], w=w, v=v, seed=0)
    out = RegionalHinfFilter(WANG2010_PAPER["Af"], WANG2010_PAPER["Bf"], model.M).filter(sim.y)
    assert np.all(np.isfinite(out.mean)) and np.abs(out.mean).max() < 10
    big = RegionalHinfFilter(WANG2010_PAPER["Af"], WANG2010_PAPER["Bf"], model.M).filter(np.full((50, 2), 1e150))
    assert np.all(np.isfinite(big.mean)) and np.abs(big.mean).max() < 1e150


# --- the measured limit of the plain and Joseph forms -----------------------------------
def _hard_case():
    A = [[np.cos(W), -np.sin(W), 0.0], [np.sin(W), np.cos(W), 0.0], [0.0, 0.0, 0.99]]
    C = [[1.0, 0.0, 1.0], [0.0, 1.0, 1e-3]]
    s = tk.LinearSystem(A=A, C=C, Q=1e-10 * np.eye(3), R=1e-12 * np.eye(2), x0=[0.0] * 3, P0=1e8 * np.eye(3))
    truth = tk.LinearSystem(A=A, C=C, Q=1e-10 * np.eye(3), R=0.01 * np.eye(2), x0=[0.0] * 3, P0=np.eye(3))
    return s, tk.simulate(truth, 50, 2, seed=1)


def test_huge_prior_with_near_singular_R_each_alone_is_fine():
    s, data = _hard_case()
    for kw in (dict(R=1e-2 * np.eye(2)), dict(P0=np.eye(3))):  # either extreme alone
        s1 = tk.LinearSystem(
            A=s.A.array, C=s.C.array, Q=s.Q.array, R=kw.get("R", s.R.array), x0=s.x0, P0=kw.get("P0", s.P0)
        )
        for form in ("standard", "joseph"):
            out = tk.KalmanFilter(s1, covariance_update=form).filter(data.y)
            assert_healthy(out.mean, out.cov, out.pred_cov)


_NEEDS_SQRT = "P0/R = 1e20 with an unseen direction: needs the square-root form (covariance_update='square_root')"


@pytest.mark.parametrize(
    "form,backend",
    [
        # the compiled standard form (the default backend's) is indefinite here (-1.2 x scale, measured)
        pytest.param(
            "standard",
            "numba",
            marks=[
                pytest.mark.xfail(strict=True, reason=_NEEDS_SQRT + "; the compiled plain form is indefinite"),
                pytest.mark.skipif(not numba_available(), reason="needs numba"),
            ],
        ),
        # the numpy standard form's rounding happens to stay PSD on this case (measured); which way it
        # falls moves with the order of the operations: not strict (a backend="auto" that ran numpy once
        # made the strict form of this test, which did not name the backend, XPASS)
        pytest.param("standard", "numpy", marks=pytest.mark.xfail(strict=False, reason=_NEEDS_SQRT)),
        # the Joseph form is at rounding level here (-6e-3 x its own scale, within 1e-9 of the prior's
        # scale as measured today; it moves with any change of rounding): not strict
        pytest.param("joseph", "auto", marks=pytest.mark.xfail(strict=False, reason=_NEEDS_SQRT)),
        ("square_root", "auto"),
    ],
)
def test_huge_prior_with_near_singular_R_together_needs_square_root_form(form, backend):
    s, data = _hard_case()
    out = tk.KalmanFilter(s, covariance_update=form, backend=backend).filter(data.y)
    assert_healthy(out.mean, out.cov, out.pred_cov)


# A 60-digit reference of the hard case: the KF (Miller (2.3)-(2.6)) for one run in decimal
# arithmetic. Its rounding (1e-60 x P0 = 1e-52) is 40 orders below the updated covariance
# (~1e-12), so it is the exact filter output to float precision.
def _decimal_kf(s, y):
    from decimal import Decimal, localcontext

    def D(a):
        return [[Decimal(float(v)) for v in row] for row in np.atleast_2d(a)]

    def mul(X, Y):
        return [
            [sum((X[i][k] * Y[k][j] for k in range(len(Y))), Decimal(0)) for j in range(len(Y[0]))]
            for i in range(len(X))
        ]

    def tr(X):
        return [list(r) for r in zip(*X)]

    def add(X, Y, sign=1):
        return [[a + sign * b for a, b in zip(r, q)] for r, q in zip(X, Y)]

    def solve(M, B):  # Gauss-Jordan with partial pivoting, M (m, m), B (m, r)
        m = len(M)
        W = [list(M[i]) + list(B[i]) for i in range(m)]
        for c in range(m):
            p = max(range(c, m), key=lambda r: abs(W[r][c]))
            W[c], W[p] = W[p], W[c]
            for r in range(m):
                if r != c:
                    f = W[r][c] / W[c][c]
                    W[r] = [a - f * b for a, b in zip(W[r], W[c])]
        return [[W[i][j] / W[i][i] for j in range(m, len(W[0]))] for i in range(m)]

    with localcontext() as ctx:
        ctx.prec = 60
        A, C, Q, R = D(s.A.array), D(s.C.array), D(s.Q.array), D(s.R.array)
        x, P = [[Decimal(float(v))] for v in s.x0], D(s.P0)
        means, covs, pcovs = [], [], []
        for yk in y:
            x = mul(A, x)
            P = add(mul(mul(A, P), tr(A)), Q)
            pcovs.append([[float(v) for v in r] for r in P])
            PCt = mul(P, tr(C))
            K = tr(solve(add(mul(C, PCt), R), tr(PCt)))  # P C^T Ree^{-1} (Ree symmetric)
            x = add(x, mul(K, add([[Decimal(float(v))] for v in yk], mul(C, x), -1)))
            P = add(P, mul(K, tr(PCt)), -1)
            means.append([float(v[0]) for v in x])
            covs.append([[float(v) for v in r] for r in P])
    return np.array(means), np.array(covs), np.array(pcovs)


def test_square_root_form_matches_a_60_digit_reference_on_the_hard_case():
    """P0 = 1e8 I, R = 1e-12 I: the square-root form is the exact filter to 1e-6, PSD to rounding.

    Tolerance: the first update shrinks the seen directions by P0/R = 1e20; a backward-stable
    factorization of a factor (condition sqrt(1e20) = 1e10) can lose 1e10 x eps = 1e-6 of
    relative accuracy there (measured: 8e-9). The plain and Joseph forms are off by O(1)
    (relative errors of the means 2 to 80, of the covariances 4e2 to 2e4): the comparison
    tells the forms apart. PSD: the smallest eigenvalue >= -1e-12 x the matrix's own largest
    entry (P = S S^T is PSD by construction; eigvalsh of a PSD matrix errs by ~eps x scale).
    """
    s, data = _hard_case()
    tkf_batch = tk.TobitKalmanFilter(s, tk.Censoring(), covariance_update="square_root").filter(data.y)
    for r in range(data.y.shape[0]):
        mean, cov, pcov = _decimal_kf(s, data.y[r])
        for out in (
            tk.KalmanFilter(s, covariance_update="square_root").filter(data.y[r]),
            tk.TobitKalmanFilter(s, tk.Censoring(), covariance_update="square_root").filter(data.y[r]),
        ):
            err = np.abs(out.mean - mean).max(axis=-1) / np.abs(mean).max(axis=-1)
            assert err.max() <= 1e-6, err.max()
            for got, ref in ((out.cov, cov), (out.pred_cov, pcov)):
                rel = np.abs(got - ref).max(axis=(-1, -2)) / np.abs(ref).max(axis=(-1, -2))
                assert rel.max() <= 1e-6, rel.max()
                eig = np.linalg.eigvalsh(got)
                assert np.all(eig.min(axis=-1) >= -1e-12 * np.abs(got).max(axis=(-1, -2)))
        np.testing.assert_allclose(tkf_batch.mean[r], mean, rtol=0, atol=1e-6 * np.abs(mean).max())
        for form in ("standard", "joseph"):  # the criterion fails the forms that lose PSD here
            old = tk.KalmanFilter(s, covariance_update=form).filter(data.y[r])
            assert (np.abs(old.mean - mean).max(axis=-1) / np.abs(mean).max(axis=-1)).max() > 1e-3


def test_square_root_form_of_the_augmented_families_on_the_hard_case():
    """The fading filter (L = 0, unit gain: the KF) and the protocol filter (one sensor, no window, no
    failures: the KF) in square-root form match the same 60-digit reference to 1e-6 and stay PSD on the
    hard case (P0 = 1e8 I, R = 1e-12 I), where their Joseph form fails the same criterion (tolerances as
    above)."""
    from tobitkf.channels.fading import RiceFading
    from tobitkf.channels.protocol import ProtocolChannel

    s, data = _hard_case()
    s1 = tk.LinearSystem(A=s.A.array, C=s.C.array[:1], Q=s.Q.array, R=s.R.array[:1, :1], x0=s.x0, P0=s.P0)
    y1 = data.y[..., :1]
    cases = [
        (s, data.y, lambda f: FadingTobitKalmanFilter(s, RiceFading(0, [1.0]), None, covariance_update=f)),
        (s1, y1, lambda f: tk.ProtocolTobitKalmanFilter(s1, ProtocolChannel(1), covariance_update=f)),
    ]
    for sys_, y, make in cases:
        for r in range(y.shape[0]):
            mean, cov, pcov = _decimal_kf(sys_, y[r])
            out = make("square_root").filter(y[r])
            assert (np.abs(out.mean - mean).max(axis=-1) / np.abs(mean).max(axis=-1)).max() <= 1e-6
            for got, ref in ((out.cov, cov), (out.pred_cov, pcov)):
                assert (np.abs(got - ref).max(axis=(-1, -2)) / np.abs(ref).max(axis=(-1, -2))).max() <= 1e-6
                eig = np.linalg.eigvalsh(got)
                assert np.all(eig.min(axis=-1) >= -1e-12 * np.abs(got).max(axis=(-1, -2)))
            old = make("joseph").filter(y[r])
            bad_mean = (np.abs(old.mean - mean).max(axis=-1) / np.abs(mean).max(axis=-1)).max() > 1e-3
            bad_psd = np.linalg.eigvalsh(old.cov).min() < -1e-12 * np.abs(old.cov).max()
            assert bad_mean or bad_psd


def _assert_match_reference_and_psd(cases):
    """Each (system, readings, estimator) of ``cases``, run by run: means, covariances and predicted
    covariances within 1e-6 (relative to each step's largest entry) of the 60-digit KF reference, and PSD
    to 1e-12 of scale."""
    for sys_, y, est in cases:
        for r in range(y.shape[0]):
            mean, cov, pcov = _decimal_kf(sys_, y[r])
            out = est.filter(y[r])
            name = type(est).__name__
            assert (np.abs(out.mean - mean).max(axis=-1) / np.abs(mean).max(axis=-1)).max() <= 1e-6, name
            for got, ref in ((out.cov, cov), (out.pred_cov, pcov)):
                assert (np.abs(got - ref).max(axis=(-1, -2)) / np.abs(ref).max(axis=(-1, -2))).max() <= 1e-6, name
                eig = np.linalg.eigvalsh(got)
                assert np.all(eig.min(axis=-1) >= -1e-12 * np.abs(got).max(axis=(-1, -2))), name


def test_square_root_form_of_the_other_gaussian_families_on_the_hard_case():
    """The dropping KF (no limits), the fading KF (L = 0, unit gain), the protocol baseline (one sensor)
    and the assumed-density filter (no limits) reduce to the KF here: in square-root form each matches
    the 60-digit reference to 1e-6 and stays PSD on the hard case (tolerances as above). (The delay
    LMMSEs have the source's own covariance recursions: only the augmented one offers the square-root
    form, tested against its standard form in tests/filters/test_delay.py.)"""
    from tobitkf.channels.fading import RiceFading
    from tobitkf.channels.protocol import ProtocolChannel

    s, data = _hard_case()
    s1 = tk.LinearSystem(A=s.A.array, C=s.C.array[:1], Q=s.Q.array, R=s.R.array[:1, :1], x0=s.x0, P0=s.P0)
    y1 = data.y[..., :1]
    cases = [
        (s, data.y, tk.DroppingKalmanFilter(s, tk.Censoring(), covariance_update="square_root")),
        (s, data.y, tk.FadingKalmanFilter(s, RiceFading(0, [1.0]), covariance_update="square_root")),
        (s1, y1, tk.ProtocolTobitKalmanFilter.baseline(s1, ProtocolChannel(1), covariance_update="square_root")),
        (s, data.y, tk.AssumedDensityTobitFilter(s, tk.Censoring(), covariance_update="square_root")),
    ]
    _assert_match_reference_and_psd(cases)


def test_square_root_form_of_the_assumed_density_families_on_the_hard_case():
    """The fading ADF (L = 0, unit deterministic gain, no limits), the protocol ADF (one sensor, no window,
    no failures, tau = -inf) and the saturation ADF (mu = 0: never saturated; nu = 1: always arriving)
    reduce to the KF here: in square-root form each matches the 60-digit reference to 1e-6 and stays PSD
    on the hard case (tolerances as above)."""
    from tobitkf.channels.fading import RiceFading
    from tobitkf.channels.protocol import ProtocolChannel

    s, data = _hard_case()
    s1 = tk.LinearSystem(A=s.A.array, C=s.C.array[:1], Q=s.Q.array, R=s.R.array[:1, :1], x0=s.x0, P0=s.P0)
    y1 = data.y[..., :1]
    sq = "square_root"
    cases = [
        (s, data.y, tk.FadingAssumedDensityFilter(s, RiceFading(0, [1.0]), covariance_update=sq)),
        (s1, y1, tk.ProtocolAssumedDensityFilter(s1, ProtocolChannel(1), covariance_update=sq)),
        (
            s,
            data.y,
            tk.SaturationAssumedDensityFilter(s, tk.RandomSaturation([0.0, 0.0], [1.0, 1.0]), covariance_update=sq),
        ),
    ]
    _assert_match_reference_and_psd(cases)


def test_square_root_tobit_filter_on_the_hard_case_with_limits():
    """The TKF in square-root form stays healthy on the hard case with active two-sided limits."""
    s, data = _hard_case()
    cens = tk.Censoring(lower=-0.05, upper=0.05)
    y = np.clip(data.y, -0.05, 0.05)
    for nt in ("dissertation", "total_variance", "exact_pv"):
        out = tk.TobitKalmanFilter(s, cens, noise_term=nt, covariance_update="square_root").filter(y)
        assert_healthy(out.mean, out.cov, out.pred_cov)
        assert_healthy(out.pred_mean, out.pred_cov)


def test_diverging_fixed_gain_tobit_observer_warns_instead_of_returning_nan_silently():
    """A = -1, Xi = 0.1, sigma = 0.01: the steady-state (fixed-gain) TKF is not globally stable; its
    error grows geometrically and overflows after ~300 steps. The filter says so."""
    s = tk.LinearSystem(A=[[-1.0]], C=[[1.0]], Q=[[0.15]], R=[[1e-4]], x0=[0.0], P0=[[1.0]])
    d = tk.simulate(s, 1000, 2, seed=0)
    with np.errstate(over="ignore", invalid="ignore"), pytest.warns(RuntimeWarning, match="diverged .* run 0 at step"):
        out = SteadyStateTobitKalmanFilter(s, 0.1).filter_controlled(d.y_latent)
    assert not np.isfinite(out.mean).all()
    with np.errstate(over="ignore", invalid="ignore"):  # Xi = 0.5: stable on the same data, no warning
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("error")
            ok = SteadyStateTobitKalmanFilter(s, 0.5).filter_controlled(d.y_latent)
    assert np.isfinite(ok.mean).all() and np.abs(ok.mean - d.x[:, 1:]).max() < 50
