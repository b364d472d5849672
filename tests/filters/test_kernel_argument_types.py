"""Every array a Python caller hands to a compiled kernel is C-contiguous and writable.

numba compiles one specialisation per argument type, and a read-only array (a broadcast view, even of the array's
own shape; noise given by the user) or a strided one (a row of a record) is a type of its own: each such call
compiled the kernel once more, in every process with a fresh numba cache (for the whole-record loops a minute or
more of CPU each). Each test runs paths that handed such arrays over, first with the real kernels (a compiled caller
of a kernel is compiled against it), then through spies that record every array argument that is not C-contiguous
and writable: none may be.
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk

pytest.importorskip("numba")

from tobitkf.filters._compiled_censored import GL_W, GL_X  # noqa: E402


class _Spies:
    """Replaces kernels (module attributes) by wrappers that record their calls and their bad array arguments."""

    def __init__(self, monkeypatch):
        self.monkeypatch = monkeypatch
        self.calls: list[str] = []
        self.bad: list[tuple[str, int, str]] = []

    def spy(self, module, name: str) -> None:
        real = getattr(module, name)

        def call(*args):
            self.calls.append(name)
            for i, a in enumerate(args):
                if isinstance(a, np.ndarray) and not (a.flags.c_contiguous and a.flags.writeable):
                    self.bad.append((name, i, "read-only" if a.flags.c_contiguous else "strided"))
            return real(*args)

        self.monkeypatch.setattr(module, name, call)


def _system() -> tk.LinearSystem:
    return tk.LinearSystem(
        A=[[0.9, 0.1], [0.0, 0.8]], C=[[1.0, 0.0]], Q=0.1 * np.eye(2), R=[[0.2]], x0=[0.0, 0.0], P0=np.eye(2)
    )


@pytest.mark.vectorised_step  # the runs-vectorised steps too (n = 2: versions tests/filters/test_compiled_soa.py compiles)
def test_kalman_and_tobit_loops_take_writable_covariances(monkeypatch):
    """One run with a missing reading (its covariance broadcast to its own shape: a read-only view) and a record
    continued from per-run covariances, for the KF and the TKF."""
    from tobitkf.filters import _compiled_entries, _compiled_loop, _compiled_soa

    sys_ = _system()
    cens = tk.Censoring(lower=0.0)
    y = cens.censor(tk.simulate(sys_, 8, 3, seed=1).y)
    y[0, 2, 0] = np.nan
    ests = (tk.KalmanFilter(sys_, backend="numba"), tk.TobitKalmanFilter(sys_, cens, backend="numba"))

    def calls():
        for est in ests:
            est.filter(y[:1])
            first = est.filter(y[:, :4])
            est.filter(y[:, 4:], state=first.final)

    calls()
    spies = _Spies(monkeypatch)
    for name in ("kalman_loop", "tobit_loop"):
        spies.spy(_compiled_entries, name)
    spies.spy(_compiled_loop, "compiled_loop")
    for name in ("soa_tobit_loop", "soa_kalman_loop"):  # the runs-vectorised steps
        spies.spy(_compiled_soa, name)
    calls()
    assert {"kalman_loop", "soa_kalman_loop"} & set(spies.calls) and {"tobit_loop", "soa_tobit_loop"} & set(spies.calls)
    assert spies.bad == []


def test_censored_moments_take_writable_arrays(monkeypatch):
    """The compiled censored moments of the assumed-density update, with per-run limits and noise variances (each
    broadcast to its own shape) and a covariance shared by the runs."""
    from tobitkf.filters import _compiled_moments
    from tobitkf.filters.assumed_density import censored_channel_update

    rng = np.random.default_rng(3)
    N = 4
    x, P = rng.normal(size=(N, 2)), np.eye(2)[None]
    y = np.array([0.0, 0.3, np.nan, 1.2])
    lo, hi, r = np.zeros(N), np.full(N, np.inf), np.full(N, 0.2)

    def calls():
        return censored_channel_update(x, P, None, y, np.array([1.0, 0.0]), r, lo, hi, compiled=True)

    want = calls()
    spies = _Spies(monkeypatch)
    spies.spy(_compiled_moments, "family_array")
    got = calls()
    assert spies.calls == ["family_array"] and spies.bad == []
    for a, b in zip(got, want):
        if a is not None:
            np.testing.assert_array_equal(a, b)


def test_shared_update_takes_a_writable_mask(monkeypatch):
    """The compiled shared update with a validity mask given as a read-only view."""
    from tobitkf.filters import _update
    from tobitkf.filters.core import MeasurementPrediction

    kern = _update._core_compiled_module()
    N = 3
    x, P = np.zeros((N, 2)), np.broadcast_to(np.eye(2), (N, 2, 2)).copy()
    valid = np.broadcast_to(np.ones((N, 1), dtype=bool), (N, 1))  # a view of its own shape: contiguous, read-only
    mp = MeasurementPrediction(
        expected=np.zeros((N, 1)), H0=np.array([[1.0, 0.0]]), noise=np.array([[0.2]]), valid=valid
    )
    innov = np.array([[0.5], [-0.1], [0.2]])

    def calls():
        return _update._compiled_measurement_update(kern, x, P, innov, mp.valid, mp, False)

    want = calls()
    spies = _Spies(monkeypatch)
    spies.spy(kern, "measurement_update_runs")
    got = calls()
    assert spies.calls == ["measurement_update_runs"] and spies.bad == []
    np.testing.assert_array_equal(got[0], want[0])


def test_closed_loop_takes_writable_noise_and_covariance(monkeypatch):
    """The compiled closed loop with the noise given by the user (taken as broadcast views) and one run (the
    observer's covariance broadcast to its own shape)."""
    from tobitkf.control import _compiled_closed
    from tobitkf.control.closed_loop import simulate_closed_loop
    from tobitkf.control.lqg import dlqr

    plant = tk.LinearSystem(
        A=[[1.0, 0.1], [0.0, 0.9]], Bu=[[0.0], [0.1]], C=[[1.0, 0.0]], Q=0.01 * np.eye(2), R=[[0.04]],
        x0=[0.0, 0.0], P0=0.1 * np.eye(2),
    )  # fmt: skip
    K = dlqr(plant.transition(0), plant.Bu.at(1), np.eye(2), np.eye(1)).gain
    T = 12
    rng = np.random.default_rng(5)
    noise = {
        "x0": rng.normal(size=(1, 2)),
        "w": 0.1 * rng.normal(size=(1, T, 2)),
        "v": 0.2 * rng.normal(size=(1, T, 1)),
    }

    def calls():
        return simulate_closed_loop(
            plant, K, T, 1, observer="tkf", censoring=tk.Censoring(upper=0.5), noise=noise, backend="numba"
        )

    want = calls()
    spies = _Spies(monkeypatch)
    spies.spy(_compiled_closed, "compiled_closed_loop")
    got = calls()
    assert spies.calls == ["compiled_closed_loop"] and spies.bad == []
    np.testing.assert_array_equal(got.x, want.x)


def test_delay_steps_take_contiguous_readings(monkeypatch):
    """The compiled whole steps of the time-delay filters, from a record (a reading is a strided row) and online."""
    from tobitkf.filters import _compiled_delay
    from tobitkf.filters.delay_augmented import AugmentedLMMSE
    from tobitkf.filters.delay_chain import ChainLMMSE
    from tobitkf.models.delay import HistoryPrior, paper_example
    from tobitkf.simulate.delay import simulate_delay

    d = 1
    sys_ = paper_example(S=0.2, q=0.3, d=d)
    prior = HistoryPrior.uncorrelated([np.full(2, 0.1 * k) for k in range(d + 1)], [np.eye(2) * 0.01] * (d + 1))
    y = simulate_delay(sys_, prior, 10, 3, seed=2).y

    def calls(make):
        est = make()
        est.filter(y)
        s = est.init((3,))
        for k in range(3):
            s = est.step(s, y[:, k])

    makers = (
        lambda: AugmentedLMMSE(sys_, prior, window=d + 1, backend="numba"),
        lambda: ChainLMMSE(sys_, prior, backend="numba"),
    )
    for make in makers:
        calls(make)
    spies = _Spies(monkeypatch)
    spies.spy(_compiled_delay, "aug_step")
    spies.spy(_compiled_delay, "chain_step")
    for make in makers:  # built after the spies: the estimators keep their kernel
        calls(make)
    assert {"aug_step", "chain_step"} <= set(spies.calls)
    assert spies.bad == []


def test_state_space_likelihood_takes_writable_arrays(monkeypatch):
    """The compiled log-likelihood of the state-space fit, one channel (R's diagonal is a read-only view) and a
    read-only record."""
    from tobitkf.inference import _compiled_ss
    from tobitkf.inference.state_space import _Likelihood

    sys_ = tk.LinearSystem(A=[[0.8]], C=[[1.0]], Q=[[0.1]], R=[[0.2]], x0=[0.0], P0=[[1.0]])
    cens = tk.Censoring(lower=0.0)
    y = cens.censor(tk.simulate(sys_, 20, 1, seed=4).y[0])
    y.setflags(write=False)

    def calls():
        return _Likelihood(y, None, cens, None).of_system(sys_)

    want = calls()
    spies = _Spies(monkeypatch)
    spies.spy(_compiled_ss, "log_likelihood")
    got = calls()
    assert spies.calls == ["log_likelihood"] and spies.bad == []
    assert got == want and np.isfinite(got)


# --------------------------------------------------------------------------- one version for both kinds of caller
#
# A kernel that is called from Python and from other compiled code is compiled for each argument type it meets: a
# module-level array read inside compiled code is a read-only constant to numba, a view of a work array is of any
# layout ('A'). The arrays the two kinds of caller hand over must have one type, or the kernel must be declared for
# both.


def test_the_quadrature_nodes_from_python_have_the_type_of_the_compiled_constant():
    """The compiled loops read the censored statistics' Gauss-Legendre nodes and weights as module constants
    (read-only); a kernel handed the module's arrays from Python (the closed loop, the river mixture filter, the
    protocol TKF's moments, the testing aids) sees the same type: a function of the nodes is compiled once for both
    (handed writable copies, ``_window_stats``, ``_quadrature_moments`` and ``_two_sided`` were compiled twice)."""
    import numba

    @numba.njit
    def nodes(glx, glw):
        return glx.shape[0] + glw.shape[0]

    @numba.njit
    def from_compiled_code():
        return nodes(GL_X, GL_W)  # module globals: read-only constants to numba

    assert from_compiled_code() == nodes(GL_X, GL_W) == 2 * 64
    assert len(nodes.signatures) == 1


def test_gauss_solve_is_one_version_for_whole_arrays_and_work_views():
    """:func:`~tobitkf._compiled_linalg.gauss_solve` takes whole arrays (the TKF's gain, the NEES) and strided views
    of a work array (the time-delay filters' work blocks): one compiled version serves both (it compiled two), with
    the same numbers, those of ``numpy.linalg.solve`` to rounding."""
    from tobitkf._compiled_linalg import gauss_solve

    rng = np.random.default_rng(7)
    M = rng.normal(size=(3, 3)) + 3.0 * np.eye(3)
    W = rng.normal(size=(3, 2))
    X = W.copy()
    assert gauss_solve(M.copy(), X)
    work = np.zeros((2, 4, 4))
    Mv, Wv = work[0, :3, :3], work[1, :3, :2]  # as the delay filters' work blocks: neither is C-contiguous
    assert not (Mv.flags.c_contiguous or Wv.flags.c_contiguous)
    Mv[...], Wv[...] = M, W
    assert gauss_solve(Mv, Wv)
    np.testing.assert_array_equal(Wv, X)
    np.testing.assert_allclose(X, np.linalg.solve(M, W), rtol=1e-12)
    assert len(gauss_solve.signatures) == 1
