"""Input audit (issue 9 item 1): every public entry point refuses a bad argument with a
ValueError/TypeError subclass whose message names the argument.

One row per hostile input: the call, the exception class and a regex the message must
match (the argument's name, and where it matters what was expected). Rows marked
``# bug`` failed with a numpy/Python error (AttributeError, IndexError, broadcasting...)
or silently before the audit.
"""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf import ShapeError, ValidationError
from tobitkf.channels.fading import RiceFading
from tobitkf.channels.laws import PMF, Gaussian, Uniform
from tobitkf.channels.protocol import ProtocolChannel
from tobitkf.channels.saturation import RandomSaturation
from tobitkf.control import certify_tkf_stability, dlqr, quadratic_cost, reference_gain, simulate_closed_loop, tobit_lqe
from tobitkf.design.hinf import WANG2010_PAPER
from tobitkf.design.protocol_bounds import protocol_covariance_bounds
from tobitkf.filters.delay_augmented import augmented_lmmse
from tobitkf.filters.delay_chain import chain_lmmse
from tobitkf.filters.fading import FadingKalmanFilter, FadingTobitKalmanFilter
from tobitkf.filters.hinf import RegionalHinfFilter
from tobitkf.filters.protocol import ProtocolTobitKalmanFilter
from tobitkf.filters.steady_state import SteadyStateTobitKalmanFilter, tobit_kalman_filter_controlled
from tobitkf.filters.tracking import MultiTargetTracker
from tobitkf.models.delay import DelayFadingSystem, HistoryPrior, paper_example, paper_prior
from tobitkf.models.ross import wang2010_model
from tobitkf.simulate.delay import simulate_delay
from tobitkf.simulate.ross import simulate_ross

GOOD = dict(A=[[1.0]], C=[[1.0]], Q=[[0.01]], R=[[1.0]], x0=[0.0], P0=[[1.0]])


def S(**kw):
    return tk.LinearSystem(**{**GOOD, **kw})


SYS = S()
SYS2 = tk.LinearSystem(A=np.eye(2), C=np.eye(2), Q=0.01 * np.eye(2), R=0.1 * np.eye(2), x0=[0.0, 0.0], P0=np.eye(2))
CENS = tk.Censoring(lower=0.0)
Y = np.abs(np.random.default_rng(0).normal(size=(3, 10, 1)))
ROSS = wang2010_model()
W = WANG2010_PAPER
DSYS, DPRI = paper_example(), paper_prior()
DBASE = dict(A=[[0.4, 0.7], [0.2, 0.6]], H=[[0.5, 1.0]], Gamma=[[1.0], [1.0]], Qw=0.3, Qv=0.3, S=0.3, d=3)


CA, CB = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])
PLANT = tk.LinearSystem(A=CA, C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.1]], x0=[1.0, 0.0], P0=0.1 * np.eye(2), Bu=CB)
CK = dlqr(CA, CB, np.eye(2), [[1.0]]).gain


class _NoDraw:
    pass


CASES = [
    # --- LinearSystem ---------------------------------------------------------------
    ("LinearSystem A NaN", lambda: S(A=[[np.nan]]), ValidationError, r"^A: expected finite"),
    ("LinearSystem A not square", lambda: S(A=[[1.0, 2.0]]), ShapeError, r"^A: expected a square"),
    ("LinearSystem A text", lambda: S(A="abc"), ValidationError, r"^A: expected an array of numbers"),
    ("LinearSystem A complex", lambda: S(A=np.array([[1 + 1j]])), ValidationError, r"^A: expected real"),  # bug
    ("LinearSystem C columns", lambda: S(C=[[1.0, 2.0]]), ShapeError, r"^C: expected \(m, 1\)"),
    ("LinearSystem Q negative", lambda: S(Q=[[-1.0]]), ValidationError, r"^Q: expected a positive semi-definite"),
    (
        "LinearSystem Q asymmetric",
        lambda: S(Q=[[1.0, 2.0], [3.0, 4.0]], A=np.eye(2), C=[[1.0, 0.0]], x0=[0, 0], P0=np.eye(2)),
        ValidationError,
        r"^Q: expected a symmetric",
    ),
    ("LinearSystem R negative", lambda: S(R=[[-1e-3]]), ValidationError, r"^R: expected a positive semi-definite"),
    ("LinearSystem x0 inf", lambda: S(x0=[np.inf]), ValidationError, r"^x0: expected finite"),
    ("LinearSystem P0 shape", lambda: S(P0=np.eye(2)), ShapeError, r"^P0: expected shape \(1, 1\)"),
    ("LinearSystem callable A NaN", lambda: S(A=lambda k: [[np.nan]]), ValidationError, r"^A\(0\): expected finite"),
    ("LinearSystem callable Q indefinite", lambda: S(Q=lambda k: [[-1.0]]), ValidationError, r"^Q\(0\)"),
    # --- Censoring ------------------------------------------------------------------
    ("Censoring lower NaN", lambda: tk.Censoring(lower=np.nan), ValidationError, r"^lower: expected finite"),
    ("Censoring lower >= upper", lambda: tk.Censoring(lower=1.0, upper=0.0), ValidationError, r"^lower/upper"),
    ("Censoring shapes", lambda: tk.Censoring(lower=[0, 1], upper=[1, 2, 3]), ShapeError, r"^lower/upper"),
    ("Censoring lower +inf", lambda: tk.Censoring(lower=np.inf), ValidationError, r"^lower: \+inf"),
    (
        "multi_region noise_var short",
        lambda: tk.multi_region(SYS, [[(0.0, 1.0)]], noise_var=[[]]),
        ShapeError,
        r"^noise_var: expected one variance per window",
    ),  # bug (IndexError)
    # --- simulate -------------------------------------------------------------------
    ("simulate steps 0", lambda: tk.simulate(SYS, 0), ValidationError, r"^steps: expected a positive integer"),
    ("simulate runs float", lambda: tk.simulate(SYS, 5, 2.0), ValidationError, r"^runs"),
    ("simulate seed text", lambda: tk.simulate(SYS, 5, seed="x"), ValidationError, r"^seed"),
    ("simulate system", lambda: tk.simulate("x", 5), ValidationError, r"^system: expected a LinearSystem"),
    (
        "simulate censoring channels",
        lambda: tk.simulate(SYS, 5, censoring=tk.Censoring(lower=[0, 1])),
        ShapeError,
        r"^censoring limits",
    ),
    (
        "simulate measurement without draw",
        lambda: tk.simulate(SYS, 5, measurement=_NoDraw()),
        ValidationError,
        r"^measurement: expected an object with a draw",
    ),  # bug (AttributeError)
    (
        "simulate post without apply",
        lambda: tk.simulate(SYS, 5, post=[_NoDraw()]),
        ValidationError,
        r"^post\[0\]: expected an object with an apply",
    ),  # bug (AttributeError)
    ("simulate unknown keyword", lambda: tk.simulate(SYS, 5, bogus=1), TypeError, r"bogus"),
    # --- KF / DKF / TKF -------------------------------------------------------------
    ("KF option", lambda: tk.KalmanFilter(SYS, covariance_update="x"), ValidationError, r"^covariance_update"),
    ("KF system", lambda: tk.KalmanFilter("x"), ValidationError, r"^system"),
    (
        "KF y inf",
        lambda: tk.KalmanFilter(SYS).filter(np.full((2, 5, 1), np.inf)),
        ValidationError,
        r"^y: expected finite",
    ),
    ("KF y 1-d", lambda: tk.KalmanFilter(SYS).filter(np.ones(5)), ShapeError, r"^y: expected \(\.\.\., T, 1\)"),
    ("KF y channels", lambda: tk.KalmanFilter(SYS).filter(np.ones((2, 5, 2))), ShapeError, r"^y: expected last axis"),
    (
        "KF y no steps",
        lambda: tk.KalmanFilter(SYS).filter(np.ones((2, 0, 1))),
        ShapeError,
        r"^y: expected at least one",
    ),
    (
        "KF y ragged",
        lambda: tk.KalmanFilter(SYS).filter([[1.0], [2.0, 3.0]]),
        ValidationError,
        r"^y: expected an array",
    ),
    (
        "KF y complex",
        lambda: tk.KalmanFilter(SYS).filter(np.ones((2, 5, 1)) * (1 + 1j)),
        ValidationError,
        r"^y: expected real",
    ),  # bug (imaginary part dropped with a warning)
    ("KF P0 override indefinite", lambda: tk.KalmanFilter(SYS).filter(Y, P0=[[-1.0]]), ValidationError, r"^P0"),
    ("KF x0 override shape", lambda: tk.KalmanFilter(SYS).filter(Y, x0=[1.0, 2.0]), ShapeError, r"x0"),
    (
        "KF u without Bu",
        lambda: tk.KalmanFilter(SYS).filter(Y, u=np.ones((10, 1))),
        ShapeError,
        r"^u: the system has no",
    ),
    ("DKF rtol text", lambda: tk.DroppingKalmanFilter(SYS, CENS, rtol="x"), ValidationError, r"^rtol"),
    (
        "DKF y below limit",
        lambda: tk.DroppingKalmanFilter(SYS, CENS).filter(Y - 5),
        ValidationError,
        r"^y: measurement .* outside its censoring limits",
    ),
    ("TKF censoring type", lambda: tk.TobitKalmanFilter(SYS, "x"), ValidationError, r"^censoring"),
    ("TKF R zero", lambda: tk.TobitKalmanFilter(S(R=[[0.0]]), CENS), ValidationError, r"^R: .*positive"),
    (
        "TKF R not diagonal",
        lambda: tk.TobitKalmanFilter(
            tk.LinearSystem(A=np.eye(2), C=np.eye(2), Q=np.eye(2), R=[[1, 0.5], [0.5, 1]], x0=[0, 0], P0=np.eye(2)),
            tk.Censoring(lower=0.0),
        ),
        ValidationError,
        r"^R: .*diagonal",
    ),
    (
        "TKF limits channels",
        lambda: tk.TobitKalmanFilter(SYS, tk.Censoring(lower=[0, 0])),
        ShapeError,
        r"censoring limits",
    ),
    (
        "TKF y outside limits",
        lambda: tk.TobitKalmanFilter(SYS, CENS).filter(Y - 5),
        ValidationError,
        r"^y: measurement .* outside",
    ),
    ("TKF noise_term", lambda: tk.TobitKalmanFilter(SYS, CENS, noise_term="x"), ValidationError, r"^noise_term"),
    ("TKF unknown keyword", lambda: tk.TobitKalmanFilter(SYS, CENS, bogus=1), TypeError, r"bogus"),
    # --- steady-state TKF -----------------------------------------------------------
    ("SSTKF xi 0", lambda: SteadyStateTobitKalmanFilter(SYS, 0.0), ValidationError, r"^xi_uncensored"),
    (
        "SSTKF xi length",
        lambda: SteadyStateTobitKalmanFilter(SYS, [0.5, 0.5]),
        ShapeError,
        r"^xi_uncensored: expected a scalar or shape \(1,\)",
    ),  # bug (broadcast error)
    ("SSTKF side", lambda: SteadyStateTobitKalmanFilter(SYS, 0.5, side="x"), ValidationError, r"^side"),
    (
        "SSTKF undetectable",
        lambda: SteadyStateTobitKalmanFilter(S(A=[[2.0]], C=[[0.0]]), 0.5),
        ValidationError,
        r"modified DARE",
    ),
    (
        "SSTKF x0 shape",
        lambda: SteadyStateTobitKalmanFilter(SYS, 0.5).filter(Y, x0=[1.0, 2.0]),
        ShapeError,
        r"^x0: expected",
    ),  # bug (broadcast error)
    (
        "SSTKF NaN sample",
        lambda: SteadyStateTobitKalmanFilter(SYS, 0.5).filter(np.where(Y > 1, np.nan, Y)),
        ValidationError,
        r"^y: .*cannot skip missing samples",
    ),  # bug (NaN output)
    (
        "SSTKF controlled NaN",
        lambda: SteadyStateTobitKalmanFilter(SYS, 0.5).filter_controlled(np.full((1, 3, 1), np.nan)),
        ValidationError,
        r"^y_latent: .*missing",
    ),  # bug (NaN output)
    (
        "controlled TKF system",
        lambda: tobit_kalman_filter_controlled("x", 0.5, Y),
        ValidationError,
        r"^system",
    ),  # bug (AttributeError)
    (
        "controlled TKF xi length",
        lambda: tobit_kalman_filter_controlled(SYS, [0.5, 0.2], Y),
        ShapeError,
        r"^xi_uncensored",
    ),  # bug (broadcast error)
    # --- fading ---------------------------------------------------------------------
    ("RiceFading order", lambda: RiceFading(-1, [1.0]), ValidationError, r"^order"),
    ("RiceFading coefficients", lambda: RiceFading(1, [1.0]), ShapeError, r"^coefficients"),
    ("RiceFading variance", lambda: RiceFading.gaussian(0, [1.0], [-1.0]), ValidationError, r"^variance"),
    (
        "Gaussian sample size",
        lambda: Gaussian([1.0]).sample(np.random.default_rng(0), -1),
        ValidationError,
        r"^shape",
    ),  # bug (numpy 'negative dimensions')
    ("Uniform low > high", lambda: Uniform(1.0, 0.0), ValidationError, r"^low/high"),
    ("PMF sums", lambda: PMF([0, 1], [0.5, 0.6]), ValidationError, r"^probs"),
    (
        "FTKF option",
        lambda: FadingTobitKalmanFilter(SYS, RiceFading(0, [1.0]), CENS, p_uncensored_mode="x"),
        ValidationError,
        r"^p_uncensored_mode",
    ),
    (
        "FTKF bool option",
        lambda: FadingTobitKalmanFilter(SYS, RiceFading(0, [1.0]), CENS, fading_variance_term="yes"),
        ValidationError,
        r"^fading_variance_term",
    ),
    ("FTKF fading type", lambda: FadingTobitKalmanFilter(SYS, "x", CENS), ValidationError, r"^fading"),
    (
        "FTKF y outside",
        lambda: FadingTobitKalmanFilter(SYS, RiceFading(0, [1.0]), CENS).filter(Y - 5),
        ValidationError,
        r"^y: measurement",
    ),
    (
        "FKF covariance option",
        lambda: FadingKalmanFilter(SYS, RiceFading(0, [1.0]), covariance_update="x"),
        ValidationError,
        r"^covariance_update",
    ),
    # --- H-infinity -----------------------------------------------------------------
    ("RandomSaturation mu", lambda: RandomSaturation([1.5], [0.5]), ValidationError, r"^mu: expected probabilities"),
    ("RandomSaturation level", lambda: RandomSaturation([0.5], [0.5], 0.0), ValidationError, r"^level"),
    ("RossModel U swapped", lambda: wang2010_model(U1=ROSS.U2, U2=ROSS.U1), ValidationError, r"^U1, U2: .*swapped"),
    ("RossModel f", lambda: wang2010_model(f=3), ValidationError, r"^f: expected a callable"),
    (
        "hinf y NaN",
        lambda: RegionalHinfFilter(W["Af"], W["Bf"], ROSS.M).filter(np.full((5, 2), np.nan)),
        ValidationError,
        r"^y",
    ),
    (
        "hinf x0 shape",
        lambda: RegionalHinfFilter(W["Af"], W["Bf"], ROSS.M).filter(np.ones((5, 2)), x0=[1.0, 2.0]),
        ShapeError,
        r"^x0",
    ),  # bug (broadcast error)
    (
        "RegionalHinfFilter gains",
        lambda: RegionalHinfFilter(W["Af"], np.ones((2, 2)), ROSS.M),
        ShapeError,
        r"^Af, Bf, M",
    ),
    (
        "RegionalHinfFilter cert",
        lambda: RegionalHinfFilter.from_certificate("x", ROSS),
        ValidationError,
        r"^cert",
    ),  # bug (AttributeError)
    ("simulate_ross model", lambda: simulate_ross("x", 5, seed=0), ValidationError, r"^model"),  # bug
    (
        "simulate_ross w callable length",
        lambda: simulate_ross(ROSS, 5, w=lambda k: [1.0, 2.0], seed=0),
        ShapeError,
        r"^w\(0\)",
    ),  # bug (reshape error)
    (
        "simulate_ross w callable NaN",
        lambda: simulate_ross(ROSS, 5, w=lambda k: [np.nan], seed=0),
        ValidationError,
        r"^w\(0\): expected finite",
    ),  # bug (NaN accepted)
    ("simulate_ross seed", lambda: simulate_ross(ROSS, 5), ValidationError, r"^seed"),
    # --- protocol -------------------------------------------------------------------
    ("ProtocolChannel sensors", lambda: ProtocolChannel(0), ValidationError, r"^sensors"),
    ("ProtocolChannel threshold NaN", lambda: ProtocolChannel(2, threshold=np.nan), ValidationError, r"^threshold"),
    ("ProtocolChannel failure law", lambda: ProtocolChannel(2, failures=Uniform(0, 2)), ValidationError, r"^failures"),
    ("PTKF system/channel", lambda: ProtocolTobitKalmanFilter(SYS2, ProtocolChannel(3)), ShapeError, r"^system"),
    (
        "PTKF P0_aug",
        lambda: ProtocolTobitKalmanFilter(SYS2, ProtocolChannel(2, window=1), P0_aug=-np.eye(4)).filter(Y),
        ValidationError,
        r"^P0_aug",
    ),
    (
        "PTKF y below threshold",
        lambda: ProtocolTobitKalmanFilter(SYS2, ProtocolChannel(2, threshold=0.0)).filter(Y - 5),
        ValidationError,
        r"^y: readings below the threshold",
    ),
    (
        "protocol bounds system",
        lambda: protocol_covariance_bounds("x", ProtocolChannel(2), 5),
        ValidationError,
        r"^system",
    ),  # bug (AttributeError)
    # --- time delay -----------------------------------------------------------------
    ("DelayFadingSystem d", lambda: DelayFadingSystem(**{**DBASE, "d": -1}), ValidationError, r"^d:"),
    ("DelayFadingSystem S", lambda: DelayFadingSystem(**{**DBASE, "S": 1.0}), ValidationError, r"^S: .*indefinite"),
    (
        "HistoryPrior covs",
        lambda: HistoryPrior.uncorrelated(np.zeros((4, 2)), -np.ones((4, 2, 2))),
        ValidationError,
        r"^covs",
    ),
    (
        "chain_lmmse prior length",
        lambda: chain_lmmse(DSYS, paper_prior(d=2), np.ones((2, 5, 1))),
        ValidationError,
        r"^prior",
    ),
    ("chain_lmmse y NaN", lambda: chain_lmmse(DSYS, DPRI, np.full((2, 5, 1), np.nan)), ValidationError, r"^y"),
    ("chain_lmmse lags", lambda: chain_lmmse(DSYS, DPRI, np.ones((2, 5, 1)), lags=[-1]), ValidationError, r"^lags"),
    (
        "augmented_lmmse window",
        lambda: augmented_lmmse(DSYS, DPRI, np.ones((2, 5, 1)), window=-1),
        ValidationError,
        r"^window",
    ),
    ("simulate_delay system", lambda: simulate_delay("x", DPRI, 5), ValidationError, r"^system"),
    # --- control and tracking -------------------------------------------------------
    ("dlqr R singular", lambda: dlqr(CA, CB, np.eye(2), [[0.0]]), ValidationError, r"^R: .*positive definite"),
    (
        "dlqr not stabilizable",
        lambda: dlqr(np.diag([2.0, 0.5]), [[0.0], [1.0]], np.eye(2), [[1.0]]),
        ValidationError,
        r"stabilizable",
    ),
    (
        "tobit_lqe xi length",
        lambda: tobit_lqe(CA, np.eye(2), [[1.0, 0.0]], np.eye(2), V=[[0.09]], xi_uncensored=[0.5, 0.5]),
        ShapeError,
        r"^xi_uncensored",
    ),  # bug (broadcast error)
    (
        "reference_gain K shape",
        lambda: reference_gain(CA, CB, [[1.0, 0.0]], np.ones((2, 2)), domain="dt"),
        ShapeError,
        r"^K: expected shape",
    ),  # bug (matmul error)
    (
        "closed loop observer",
        lambda: simulate_closed_loop(PLANT, CK, 5, 2, observer="x"),
        ValidationError,
        r"^observer",
    ),
    (
        "closed loop noise keys",
        lambda: simulate_closed_loop(PLANT, CK, 5, 2, noise={"x0": np.ones(3)}),
        ValidationError,
        r"^noise: expected keys .* missing w, v",
    ),  # bug (KeyError)
    (
        "closed loop divergence_bound",
        lambda: simulate_closed_loop(PLANT, CK, 5, 2, divergence_bound=-1.0),
        ValidationError,
        r"^divergence_bound",
    ),  # bug (accepted: every run flagged diverged at once)
    (
        "quadratic_cost Q shape",
        lambda: quadratic_cost(simulate_closed_loop(PLANT, CK, 5, 2), np.eye(3), [[1.0]]),
        ShapeError,
        r"^Q, R",
    ),  # bug (broadcast error)
    (
        "certify grid",
        lambda: certify_tkf_stability(CA, 0.5 * np.ones((2, 1)), [[1.0, 0.0]], domain="dt", grid="x"),
        ValidationError,
        r"^grid",
    ),  # bug (TypeError from '>')
    ("tracker Q indefinite", lambda: MultiTargetTracker(Q=-np.eye(4)), ValidationError, r"^Q: .*positive"),  # bug
    ("tracker initial text", lambda: MultiTargetTracker().track("x", []), ValidationError, r"^initial"),  # bug
    # --- metrics --------------------------------------------------------------------
    (
        "summarize skip",
        lambda: tk.metrics.summarize(np.ones((3, 5, 2)), np.zeros((3, 5, 2)), skip=10),
        ValidationError,
        r"^skip",
    ),  # bug (all-NaN time averages)
]


@pytest.mark.parametrize("call, exc, match", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_raises_named_error(call, exc, match):
    with pytest.raises(exc, match=match) as info:
        call()
    assert isinstance(info.value, (ValueError, TypeError))


def test_every_error_class_is_a_value_error():
    assert issubclass(ShapeError, ValidationError) and issubclass(ValidationError, ValueError)
