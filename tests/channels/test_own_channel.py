"""The tutorial's channel of one's own (docs/tutorials/own_channel.md), loaded from its own file outside the
package: the generic filters, the particle filter, the registry and the sweep files take it, and its updates
are the exact ones (brute-force quadrature, closed forms)."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.special import ndtr

import tobitkf as tk
from tobitkf.channels.base import registered_channels

PAGE = Path(__file__).resolve().parents[2] / "docs" / "tutorials" / "own_channel.md"


@pytest.fixture(scope="module")
def dead_band(tmp_path_factory):
    """The tutorial's first code block written to ``dead_band.py`` and imported from there."""
    code = re.findall(r"```python\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.S)[0]
    path = tmp_path_factory.mktemp("own") / "dead_band.py"
    path.write_text(code, encoding="utf-8")
    spec = importlib.util.spec_from_file_location("dead_band", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_file_defines_a_channel_that_registers_itself(dead_band):
    assert dead_band.DeadBand.__module__ == "dead_band"
    assert registered_channels()["dead_band"] is dead_band.DeadBand
    band = dead_band.DeadBand(0.5)
    np.testing.assert_array_equal(band.censor(np.array([-0.7, -0.2, 0.49, 0.5])), [-0.7, 0.0, 0.0, 0.5])


def _quadrature(m, P, c, r, lo, hi, pts=801):
    """Moments of N(x; m, P) * p(reading | x) on a grid of the prior's whitened coordinates; an exact reading
    (lo == hi) has likelihood N(lo; c x, r), an interval P(lo < c x + v < hi)."""
    L = np.linalg.cholesky(P)
    g = np.linspace(-10, 10, pts)
    Z = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    X = m + Z @ L.T
    mu = X @ c
    like = (
        np.exp(-0.5 * (lo - mu) ** 2 / r) if lo == hi else ndtr((hi - mu) / np.sqrt(r)) - ndtr((lo - mu) / np.sqrt(r))
    )
    w = np.exp(-0.5 * (Z * Z).sum(1)) * like
    w /= w.sum()
    mean = w @ X
    d = X - mean
    return mean, (w[:, None] * d).T @ d


@pytest.mark.parametrize("reading", [0.0, 0.8, -1.3])
def test_one_update_is_the_exact_posterior(dead_band, reading):
    P0 = np.array([[0.6, 0.2], [0.2, 0.3]])
    sys_ = tk.LinearSystem(A=np.eye(2), C=[[1.0, 1.0]], Q=np.zeros((2, 2)), R=[[0.02]], x0=[0.3, -0.1], P0=P0)
    band = dead_band.DeadBand(0.5)
    out = tk.AssumedDensityFilter(sys_, band).filter([[reading]])
    lo, hi = (-0.5, 0.5) if reading == 0.0 else (reading, reading)
    mean, cov = _quadrature(np.array([0.3, -0.1]), P0, np.array([1.0, 1.0]), 0.02, lo, hi)
    np.testing.assert_allclose(out.mean[0], mean, atol=1e-9)
    np.testing.assert_allclose(out.cov[0], cov, atol=1e-9)
    # and the particle filter's one-step posterior mean, within its Monte Carlo error (both proposals; the
    # prior's weights are uneven: its effective sample size sets the error)
    for proposal in ("optimal", "prior"):
        res = tk.ParticleFilter(sys_, band, particles=40000, proposal=proposal, seed=3).filter([[reading]])
        se = np.sqrt(np.diagonal(cov) / res.extras["ess"][0])
        assert (np.abs(res.mean[0] - mean) < 5 * se + 1e-12).all(), (proposal, res.mean[0], mean, se)


def test_filter_step_smooth_and_likelihood(dead_band):
    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.2]], R=[[0.05]], x0=[0.0], P0=[[1.0]])
    band = dead_band.DeadBand(0.4)
    d = tk.simulate(sys_, 30, 4, channel=band, seed=7)
    assert (d.y == 0).any() and (d.y != 0).any()
    adf = tk.AssumedDensityFilter(sys_, band)
    res = adf.filter(d.y)
    st = adf.init(batch_shape=(4,))
    for k in range(30):
        st = adf.step(st, d.y[:, k])
    np.testing.assert_allclose(st.mean, res.mean[:, -1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(adf.log_likelihood(d.y), res.extras["log_likelihood"].sum(-1), rtol=1e-12)
    sm = adf.smooth(d.y)
    assert (sm.cov <= res.cov + 1e-12).all()
    # one step from the prior: the log-probability of the reading exactly
    one = tk.AssumedDensityFilter(
        tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.05]], x0=[0.1], P0=[[1.0]]), band
    )
    s = np.sqrt(1.05)
    assert float(one.log_likelihood([[0.0]])) == pytest.approx(np.log(ndtr(0.3 / s) - ndtr(-0.5 / s)), rel=1e-13)
    with pytest.raises(tk.ValidationError, match="inside the dead band"):
        adf.filter([[0.1]])


def test_the_registry_and_sweep_files_take_it(dead_band):
    from tobitkf.filters.registry import make
    from tobitkf.sweep import parse_sweep

    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.2]], R=[[0.05]], x0=[0.0], P0=[[1.0]])
    band = dead_band.DeadBand(0.4)
    assert type(make("AssumedDensityFilter", sys_, dead_band=band)) is tk.AssumedDensityFilter
    text = """
[sweep]
runs = 4
steps = 5
seed = 0
[model]
A = [[0.9]]
C = [[1.0]]
Q = [[0.2]]
R = [[0.05]]
x0 = [0.0]
P0 = [[1.0]]
[dead_band]
width = 0.4
[estimators.adf]
type = "AssumedDensityFilter"
"""
    assert parse_sweep(text).channels == {"dead_band": {"width": 0.4}}
    with pytest.raises(tk.ValidationError, match="dead_band.depth"):
        parse_sweep(text.replace("width = 0.4", "width = 0.4\ndepth = 1"))


def _same(a, b, tol=1e-12):
    for key in ("mean", "cov", "pred_mean", "pred_cov"):
        va, vb = getattr(a, key), getattr(b, key)
        np.testing.assert_allclose(vb, va, rtol=0, atol=tol * max(1.0, np.abs(va).max()), err_msg=key)
    la, lb = a.extras["log_likelihood"], b.extras["log_likelihood"]
    np.testing.assert_array_equal(np.isfinite(lb), np.isfinite(la))
    fin = np.isfinite(la)
    np.testing.assert_allclose(lb[fin], la[fin], rtol=0, atol=tol * max(1.0, np.abs(la[fin]).max()))


def test_its_compiled_block_is_the_numpy_update(dead_band):
    """The tutorial's compiled block (``backend="numba"``: the compiled loop of the assumed-density filter, and the
    step loop taking the block's moments) equals the numpy update from ``region`` to 1e-12: readings in the band
    and outside, missing ones, the band 40 predicted standard deviations away, a degenerate latent."""
    pytest.importorskip("numba")
    sys_ = tk.LinearSystem(
        A=[[1.0, 0.1], [0.0, 0.95]], C=[[1.0, 0.0]], Q=np.diag([1e-4, 4e-3]), R=[[0.01]], x0=[0.0, 0.0],
        P0=np.diag([0.5, 0.1]),
    )  # fmt: skip
    band = dead_band.DeadBand(0.5)
    y = tk.simulate(sys_, 30, 6, channel=band, seed=5).y.copy()
    y[1, 3:7] = np.nan
    assert (y == 0.0).any() and (np.abs(y) > 0.5).any()
    fast, ref = (tk.AssumedDensityFilter(sys_, band, backend=be) for be in ("numba", "numpy"))
    for x0 in ([0.0, 0.0], [45.0, 0.0], [-30.0, 1.0]):  # a start 40 sigma and more from the band
        a, b = ref.filter(y, x0=x0), fast.filter(y, x0=x0)
        assert np.isfinite(a.extras["log_likelihood"]).all()
        _same(a, b)
    st_a, st_b = ref.init((6,)), fast.init((6,))
    for t in range(5):
        st_a, st_b = ref.step(st_a, y[:, t]), fast.step(st_b, y[:, t])  # the step loop: the block's moments
        np.testing.assert_allclose(st_b.mean, st_a.mean, rtol=0, atol=1e-12)
        np.testing.assert_allclose(st_b.cov, st_a.cov, rtol=0, atol=1e-12)
    # no noise, a known state: no update; the term 0 where the reading allows the state, else -inf
    exact = tk.LinearSystem(A=[[1.0]], C=[[1.0]], Q=[[0.0]], R=[[0.0]], x0=[0.2], P0=[[0.0]])
    yd = np.array([[[0.0]], [[0.7]], [[-0.9]]])
    for x0, want in (([0.2], [0.0, -np.inf, -np.inf]), ([0.7], [-np.inf, 0.0, -np.inf])):
        lls = [tk.AssumedDensityFilter(exact, band, backend=be).filter(yd, x0=x0).extras["log_likelihood"][:, 0]
               for be in ("numpy", "numba")]  # fmt: skip
        np.testing.assert_array_equal(lls[0], want)
        np.testing.assert_array_equal(lls[1], lls[0])


def test_its_block_key_follows_its_code_not_its_file(dead_band):
    """The compiled loop's version for a block is cached under the hash of the block's code and of the globals it
    reads: the same source elsewhere (another file, code run without one) has the same key, an edited one
    another."""
    pytest.importorskip("numba")
    from tobitkf.filters import _compiled_moments as cm

    code = re.findall(r"```python\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.S)[0]

    def block_of(source):
        ns: dict = {"__name__": "elsewhere"}
        exec(compile(source, "<elsewhere>", "exec"), ns)  # noqa: S102 - the tutorial's own code
        return ns["dead_band_block"]

    key = cm._block_key(dead_band.dead_band_block)
    assert cm._block_key(block_of(code)) == key
    assert cm._block_key(block_of(code.replace("pu[b] = 1.0", "pu[b] = 0.5"))) != key
    other_global = code.replace("import MISSING, interval_update", "import interval_update\n\nMISSING = 7")
    assert cm._block_key(block_of(other_global)) != key  # a global it reads, another value
    assert cm.channel_kind(dead_band.DeadBand(0.5)) == cm.block_kind(dead_band.dead_band_block)


@pytest.mark.heavy
def test_its_compiled_loop_loads_from_the_cache_in_another_process(tmp_path):
    """The loop's version for the tutorial's block, compiled in one process, loads from numba's on-disk cache in the
    next one (the block's file loaded by path, as the tutorial's readers may): no compile there."""
    pytest.importorskip("numba")
    import subprocess
    import sys

    code = re.findall(r"```python\n(.*?)```", PAGE.read_text(encoding="utf-8"), re.S)[0]
    (tmp_path / "dead_band.py").write_text(code, encoding="utf-8")
    script = f"""
import importlib.util, numpy as np, tobitkf as tk
from tobitkf._compiled import compile_stats
spec = importlib.util.spec_from_file_location("dead_band", {str(tmp_path / "dead_band.py")!r})
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.2]], R=[[0.05]], x0=[0.0], P0=[[1.0]])
y = np.array([[[0.0], [0.8], [np.nan]]])
print(tk.AssumedDensityFilter(sys_, mod.DeadBand(0.5), backend="numba").filter(y).mean.sum(), compile_stats()["compiled"])
"""
    src = str(Path(tk.__file__).resolve().parents[1])  # the package under test, in the child processes too
    env = {**__import__("os").environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": src}
    outs = [subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
            for _ in range(2)]  # fmt: skip
    (m1, c1), (m2, c2) = (o.stdout.split() for o in outs)
    assert int(c1) > 0 and int(c2) == 0, (c1, c2)
    assert m1 == m2
