"""The multi-region TKF (Miller §6.6: several censored windows per output, stacked as sensors by
:func:`tobitkf.multi_region`) on the compiled TKF kernel against the numpy reference path.

``backend="auto"`` must run the kernel for it (with and without control inputs, which the stacked
model keeps), and the kernel must reproduce numpy to rounding (1e-12): one- and two-sided windows,
windows that leave a gap, lost readings (NaN: one sensor, both sensors, a stretch of steps), the
prediction 40 sigma beyond every window, every noise term and both covariance forms.
"""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters import _backend
from tobitkf.filters import kalman as kalman_module

from ._compare import assert_results_equal, assert_same

pytest.importorskip("numba")
from tobitkf.filters import _compiled_tobit  # noqa: E402

SIGMA = 0.05  # measurement noise of every sensor (Miller §6.6 Examples 1 and 3; docs/sources MB-36)

WINDOWS = {
    "example1": [[(-np.inf, 0.0), (0.0, np.inf)]],  # a right- and a left-censored sensor at 0
    "example3": [[(-1.5, -0.1), (0.1, 1.5)]],  # two saturation windows with a gap between them
    "two_outputs": [[(-np.inf, -0.2), (-0.3, 0.3), (0.2, np.inf)], [(-0.5, 0.5)]],
}


def base_system(outputs: int, with_input: bool, x0: float = 0.0) -> tk.LinearSystem:
    """x_{k+1} = 0.99 x_k + w (Q = 0.01), one or two outputs of the scalar state, noise SIGMA."""
    C = [[1.0]] if outputs == 1 else [[1.0], [0.5]]
    extra = {"Bu": [[0.05]], "D": [[0.1]] * outputs} if with_input else {}
    return tk.LinearSystem(A=[[0.99]], C=C, Q=[[0.01]], R=SIGMA**2 * np.eye(outputs), x0=[x0], P0=[[0.01]], **extra)


def stacked(name: str, with_input: bool, x0: float = 0.0):
    windows = WINDOWS[name]
    return tk.multi_region(base_system(len(windows), with_input, x0), windows)


def lose_readings(y: np.ndarray, seed: int) -> np.ndarray:
    y = y.copy()
    rng = np.random.default_rng(seed)
    y[rng.random(y.shape) < 0.1] = np.nan  # scattered single readings
    y[:, 20:30, 0] = np.nan  # sensor 0 lost for ten steps
    y[:, 40:43, :] = np.nan  # every sensor lost: predict only
    return y


def record(sys_, cens, runs, steps, seed, with_input):
    u = np.random.default_rng(seed + 1).normal(size=(runs, steps, 1)) if with_input else None
    sim = tk.simulate(sys_, steps, runs, censoring=cens, inputs=u, seed=seed)
    return lose_readings(sim.y, seed + 2), u


class _Trap:
    """Stands in for the kernels module: any kernel the dispatcher reaches raises, naming it."""

    NOISE_CODES = _compiled_tobit.NOISE_CODES
    GL_X, GL_W = _compiled_tobit.GL_X, _compiled_tobit.GL_W

    def __getattr__(self, name):
        raise AssertionError(f"kernel {name} used")


@pytest.mark.parametrize("with_input", [False, True])
@pytest.mark.parametrize("name", sorted(WINDOWS))
def test_auto_runs_the_kernel_for_multi_region(name, with_input, monkeypatch):
    sys_, cens = stacked(name, with_input)
    y, u = record(sys_, cens, runs=2, steps=50, seed=0, with_input=with_input)
    monkeypatch.setattr(_backend, "_load", lambda: _Trap())
    monkeypatch.setattr(kalman_module, "_load_entries", lambda: _Trap())
    with pytest.raises(AssertionError, match="kernel tobit_loop used"):
        tk.TobitKalmanFilter(sys_, cens).filter(y, u=u)
    # the online step too (its one-step entry without an input)
    with pytest.raises(AssertionError, match="kernel tobit_loop used" if with_input else "kernel tobit_step used"):
        est = tk.TobitKalmanFilter(sys_, cens)
        est.step(est.init((2,)), y[:, 0], u=None if u is None else u[:, 0])


@pytest.mark.parametrize("cu", ["standard", "joseph"])
@pytest.mark.parametrize("with_input", [False, True])
@pytest.mark.parametrize(
    "name, noise_term",
    # Example 3 with the dissertation's term is ill-conditioned: checked step by step below
    [
        (name, nt)
        for name in sorted(WINDOWS)
        for nt in ("dissertation", "exact_pv")
        if (name, nt) != ("example3", "dissertation")
    ],
)
def test_multi_region_kernel_equals_numpy(name, noise_term, with_input, cu):
    sys_, cens = stacked(name, with_input)
    y, u = record(sys_, cens, runs=40, steps=120, seed=3, with_input=with_input)  # a full block and a part
    kw = {"noise_term": noise_term, "covariance_update": cu}
    a = tk.TobitKalmanFilter(sys_, cens, backend="numba", **kw).filter(y, u=u)
    b = tk.TobitKalmanFilter(sys_, cens, backend="numpy", **kw).filter(y, u=u)
    assert_results_equal(a, b)


@pytest.mark.parametrize(
    "name, noise_term",
    [(name, "total_variance") for name in sorted(WINDOWS)] + [("example3", "dissertation")],
)
@pytest.mark.parametrize("with_input", [False, True])
def test_multi_region_each_step_equals_numpy(name, noise_term, with_input):
    """``noise_term="total_variance"`` lets the filter run off (its gain grows like a^2 when the prediction
    sits deep in a censored region; see tobitkf.filters.tobit), and the dissertation's term on Example 3
    overshoots when the state re-enters a window from the gap (gamma at the prior, Assumption A1, jumps
    from ~0 to ~1), which amplifies rounding ~1e4-fold (shown on numpy alone by
    :func:`test_example3_recursion_amplifies_one_ulp`); so whole trajectories differ by more than rounding.
    What the kernel must do, one predict + update equal to numpy's from the same state, is checked at every
    step of numpy's own trajectory (1e-12), inputs and lost readings included."""
    sys_, cens = stacked(name, with_input)
    y, u = record(sys_, cens, runs=40, steps=120, seed=3, with_input=with_input)
    ref = tk.TobitKalmanFilter(sys_, cens, noise_term=noise_term, backend="numpy")
    fast = tk.TobitKalmanFilter(sys_, cens, noise_term=noise_term, backend="numba")
    traj = ref.filter(y, u=u)
    for k in range(1, y.shape[1]):
        state = ref.init(batch_shape=(y.shape[0],), x0=traj.mean[:, k - 1], P0=traj.cov[:, k - 1])
        uk = None if u is None else u[:, k]
        a, b = fast.step(state, y[:, k], u=uk), ref.step(state, y[:, k], u=uk)
        assert_same(a.x, b.x, 1e-12)
        assert_same(a.P, b.P, 1e-12)
        assert_same(a.extras["p_uncensored"], b.extras["p_uncensored"], 1e-12)


def test_example3_recursion_amplifies_one_ulp():
    """Why Example 3 with the dissertation's term is compared step by step: on the numpy path alone, one
    ulp added to the estimate at step 70 of the record above moves later estimates by far more than 1e-12
    relative (the overshoot of run 13 after its re-entry from the gap)."""
    sys_, cens = stacked("example3", False)
    y, _ = record(sys_, cens, runs=40, steps=120, seed=3, with_input=False)
    ref = tk.TobitKalmanFilter(sys_, cens, backend="numpy")
    traj = ref.filter(y)
    k0 = 70
    st = ref.init((40,), x0=traj.mean[:, k0 - 1], P0=traj.cov[:, k0 - 1])
    bumped = ref.init((40,), x0=traj.mean[:, k0 - 1] * (1 + 2.0**-52), P0=traj.cov[:, k0 - 1])
    a, b = ref.filter(y[:, k0:], state=st), ref.filter(y[:, k0:], state=bumped)
    assert np.abs(a.mean - b.mean).max() > 1e-12 * max(1.0, np.abs(a.mean).max())


@pytest.mark.parametrize("noise_term", tk.filters.tobit.NOISE_TERMS)
@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("name", sorted(WINDOWS))
def test_multi_region_40_sigma_beyond_every_window(name, sign, noise_term):
    """The state starts and stays 40 measurement sigmas beyond the outermost finite limit (above, or below):
    every sensor with a finite limit on that side reads its limit, gamma underflows towards 0 for those, the
    sensor open on that side reads normally; some readings lost. Both paths must agree to 1e-12."""
    lims = [v for win in WINDOWS[name] for pair in win for v in pair if np.isfinite(v)]
    edge = max(lims) if sign > 0 else min(lims)
    x0 = edge + sign * 40.0 * SIGMA
    sys_, cens = stacked(name, False, x0=x0)
    sys_ = tk.LinearSystem(
        A=[[1.0]], C=sys_.measurement(1), Q=[[1e-6]], R=sys_.measurement_cov(1), x0=[x0], P0=[[1e-6]]
    )
    y, _ = record(sys_, cens, runs=4, steps=60, seed=7, with_input=False)
    b = tk.TobitKalmanFilter(sys_, cens, noise_term=noise_term, backend="numpy").filter(y)
    assert np.nanmin(b.extras["p_uncensored"]) < 1e-300  # the readings do sit 40 sigma out
    a = tk.TobitKalmanFilter(sys_, cens, noise_term=noise_term, backend="numba").filter(y)
    assert_results_equal(a, b)
    assert np.all(np.isfinite(a.mean))
