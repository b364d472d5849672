"""Tests of the regional H∞ filter with ROSS and missing measurements (spec 004 §5).

Reference numbers come from the spec's independent reproduction (§6, and the second verifier's
notes), not from this module's output. LMI solves are few and small (each < 0.2 s).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tobitkf._validation import ShapeError, ValidationError
from tobitkf.channels.saturation import RandomSaturation, saturate
from tobitkf.design import hinf as H
from tobitkf.filters import hinf as F
from tobitkf.models import ross as M
from tobitkf.simulate import ross as S


def trajectory(Af, Bf, M, y, x0=None):
    """x̂_0..x̂_T of the filter (5) through its estimator API (rows x̂_1..x̂_T) plus the prior x̂_0."""
    out = F.RegionalHinfFilter(Af, Bf, M).filter(y, x0=x0)
    first = np.broadcast_to(
        np.zeros(np.shape(Af)[0]) if x0 is None else x0, out.mean.shape[:-2] + (1, out.mean.shape[-1])
    )
    return np.concatenate([first, out.mean], axis=-2)


PAPER = H.WANG2010_PAPER


@pytest.fixture(scope="module")
def model():
    return M.wang2010_model()


@pytest.fixture(scope="module")
def th3_feasible(model):
    return H.design(model)  # paper: γ = 1.5, feasibility


@pytest.fixture(scope="module")
def th3_min(model):
    return H.design(model, objective="min_gamma")


@pytest.fixture(scope="module")
def zero_gamma(model):
    return H.zero_filter_gamma(model)


@pytest.fixture(scope="module")
def improved(model):
    return H.design(model, method="coupled", objective="min_gamma")


def _random_eta(rng, n, scale=1.0):
    return rng.normal(scale=scale, size=2 * n)


# --------------------------------------------------------------------------------------------
# §5.1 model
# --------------------------------------------------------------------------------------------
def test_saturation_is_clip_and_local_sector_10():
    rng = np.random.default_rng(0)
    v = rng.normal(scale=3, size=10000)
    s = np.sign(v) * np.minimum(1, np.abs(v))
    np.testing.assert_array_equal(saturate(v), s)
    assert saturate(0.0) == 0.0
    a = 0.4
    inside = v[np.abs(v) <= 1 / a]
    assert ((saturate(inside) - a * inside) * (saturate(inside) - inside) <= 1e-15).all()
    outside = np.array([1 / a + 0.1, -3 / a])
    assert ((saturate(outside) - a * outside) * (saturate(outside) - outside) > 0).all()


def test_example_sector_condition_4(model):
    U = model.U1 - model.U2
    e3 = np.eye(3)[2]
    # |x3 sin x1 / sqrt(x1^2+x2^2+20)| <= |x3|/sqrt(20) and (U1+U2)/2 is the linear part of f
    assert np.linalg.eigvalsh(U @ U / 4 - 0.05 * np.outer(e3, e3)).min() > 3e-4
    np.testing.assert_allclose(
        (model.U1 + model.U2) / 2, [[-0.7, 0.05, 0.05], [-0.05, 0.85, 0], [-0.05, 0, -0.475]], atol=1e-15
    )
    rng = np.random.default_rng(1)
    for scale in (0.1, 1.0, 10.0, 100.0):
        x = rng.normal(scale=scale, size=(20000, 3))
        ratio = model.sector_value(x) / (x**2).sum(-1)
        assert ratio.max() < 0


def test_augmented_system_6_matches_direct_simulation(model):
    rng = np.random.default_rng(2)
    Af, Bf = rng.normal(scale=0.3, size=(3, 3)), rng.normal(scale=0.3, size=(3, 2))
    T = 15
    w, v = rng.normal(size=(T, 1)), rng.normal(size=(T, 2))
    sim = S.simulate_ross(model, T, 4, x0=rng.normal(size=(4, 3)), w=w, v=v, seed=3)
    xh = trajectory(Af, Bf, model.M, sim.y)
    eta = np.concatenate([sim.x, xh], axis=-1)
    for k in range(T):
        nxt = H.augmented_step(model, Af, Bf, eta[:, k], w[k], v[k], sim.alpha[:, k], sim.beta[:, k])
        np.testing.assert_allclose(nxt, eta[:, k + 1], rtol=0, atol=1e-13)


def _enumerate_expectation(model, Af, Bf, P, eta, w, v):
    ch = model.channel
    total = 0.0
    for bits in itertools.product([0, 1], repeat=2 * model.m):
        a = np.array(bits[: model.m], float)
        b = np.array(bits[model.m :], float)
        prob = np.prod(np.where(a == 1, ch.mu, 1 - ch.mu)) * np.prod(np.where(b == 1, ch.nu, 1 - ch.nu))
        nxt = H.augmented_step(model, Af, Bf, eta, w, v, a, b)
        total += prob * nxt @ P @ nxt
    return total


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_expected_lyapunov_increment_matches_enumeration(model, seed):
    rng = np.random.default_rng(seed)
    Af, Bf = rng.normal(size=(3, 3)), rng.normal(size=(3, 2))
    L = rng.normal(size=(6, 6))
    P = L @ L.T + np.eye(6)  # full P: the formula holds for any P
    eta, w, v = _random_eta(rng, 3, 2.0), rng.normal(size=1), rng.normal(size=2)
    ref = _enumerate_expectation(model, Af, Bf, P, eta, w, v)
    exact = H.expected_lyapunov_next(model, Af, Bf, P, eta, w, v, covariance="exact")
    assert abs(exact - ref) <= 1e-10 * max(1.0, abs(ref))
    bound = H.expected_lyapunov_next(model, Af, Bf, P, eta, w, v, covariance="paper")
    assert bound >= exact - 1e-12  # (14) is an upper bound


def test_psi_is_the_dissipation_quadratic_form(model):
    """ξ^TΨξ (exact covariance) = E V(η+) − V(η) + |z̃|² − γ²|w̄|² − ε1·sector_f − ε2·sector_σ."""
    rng = np.random.default_rng(5)
    Af, Bf = rng.normal(size=(3, 3)), rng.normal(size=(3, 2))
    L = rng.normal(size=(6, 6))
    P = L @ L.T + np.eye(6)
    Lam, e1, e2, g = np.array([0.3, 0.8]), 0.7, 1.9, 1.3
    psi = H.psi_matrix(model, Af, Bf, P, Lam, e1, e2, g, covariance="exact")
    for _ in range(3):
        eta, w, v = _random_eta(rng, 3, 1.5), rng.normal(size=1), rng.normal(size=2)
        x, xh = eta[:3], eta[3:]
        c = model.C @ x
        s = saturate(c)
        xi = np.concatenate([eta, model.f(x), s, w, v])
        rhs = (
            _enumerate_expectation(model, Af, Bf, P, eta, w, v)
            - eta @ P @ eta
            + np.sum((model.M @ (x - xh)) ** 2)
            - g**2 * (w @ w + v @ v)
            - e1 * model.sector_value(x)
            - e2 * (s - Lam * c) @ (s - c)
        )
        assert abs(xi @ psi @ xi - rhs) <= 1e-10 * max(1.0, abs(rhs))


def test_block_diagonal_psi_equals_paper_layout_17(model):
    """The numpy Ψ with P = diag(Q1, Q2) matches the block formula (17)–(18) typed from the spec."""
    rng = np.random.default_rng(6)
    n, m, p = 3, 2, 1
    Af, Bf = rng.normal(size=(n, n)), rng.normal(size=(n, m))
    A1, A2 = rng.normal(size=(n, n)), rng.normal(size=(n, n))
    Q1, Q2 = A1 @ A1.T + np.eye(n), A2 @ A2.T + np.eye(n)
    P = np.block([[Q1, np.zeros((n, n))], [np.zeros((n, n)), Q2]])
    Lam, e1, e2, g = np.array([0.5, 0.6]), 0.9, 1.4, 2.0
    ch, C, B, M, D = model.channel, model.C, model.B, model.M, np.diag(model.D)
    La, Lb = np.diag(ch.mu), np.diag(ch.nu)
    Hm = np.hstack([np.eye(n), np.zeros((n, n))])
    F = np.hstack([Bf @ (np.eye(m) - La) @ Lb @ C, Af])
    Mb = np.hstack([M, -M])
    BQB = Bf.T @ Q2 @ Bf
    dv = ch.var_beta + ch.varsigma
    ra = ch.var_alpha + ch.varsigma
    U1t = Hm.T @ (model.U1.T @ model.U2 + model.U2.T @ model.U1) @ Hm / 2
    U2t = -Hm.T @ (model.U1.T + model.U2.T) / 2
    V1 = Hm.T @ C.T @ np.diag(Lam) @ C @ Hm
    V2 = -Hm.T @ C.T @ (np.diag(Lam) + np.eye(m)) / 2
    Y11 = (
        F.T @ Q2 @ F
        + sum(dv[i] * BQB[i, i] * Hm.T @ np.outer(C[i], C[i]) @ Hm for i in range(m))
        - P
        + Mb.T @ Mb
        - e1 * U1t
        - e2 * V1
    )
    Y33 = La @ BQB @ La - e2 * np.eye(m) + np.diag(ra * np.diag(BQB))
    B1 = np.hstack([B, np.zeros((n, m))])
    B2 = np.hstack([np.zeros((n, p)), Bf @ D])
    Daug = np.block([[B, np.zeros((n, m))], [np.zeros((n, p)), Bf @ D]])
    Y44 = -(g**2) * np.eye(p + m) + Daug.T @ P @ Daug
    ref = np.block(
        [
            [Y11, -e1 * U2t, F.T @ Q2 @ Bf @ La - e2 * V2, F.T @ Q2 @ B2],
            [(-e1 * U2t).T, Q1 - e1 * np.eye(n), np.zeros((n, m)), Q1 @ B1],
            [(F.T @ Q2 @ Bf @ La - e2 * V2).T, np.zeros((m, n)), Y33, La @ Bf.T @ Q2 @ B2],
            [(F.T @ Q2 @ B2).T, (Q1 @ B1).T, (La @ Bf.T @ Q2 @ B2).T, Y44],
        ]
    )
    ours = H.psi_matrix(model, Af, Bf, P, Lam, e1, e2, g)
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-12)


def test_bernoulli_mode_frequencies(model):
    ch = model.channel
    a, b = ch.draw_modes(np.random.default_rng(7), (200000,))
    n = a.shape[0]
    probs = ch.mode_probabilities()
    for mode, freq in (
        ("saturated", a.mean(0)),
        ("normal", ((1 - a) * b).mean(0)),
        ("missing", ((1 - a) * (1 - b)).mean(0)),
    ):
        se = np.sqrt(probs[mode] * (1 - probs[mode]) / n)
        assert (np.abs(freq - probs[mode]) <= 6 * se).all(), mode
    # moments of §1.6
    am, bm = a - ch.mu, (1 - a) * b - (1 - ch.mu) * ch.nu
    np.testing.assert_allclose((am**2).mean(0), ch.var_alpha, atol=6e-3)
    np.testing.assert_allclose((bm**2).mean(0), ch.var_beta, atol=6e-3)
    np.testing.assert_allclose((am * bm).mean(0), -ch.varsigma, atol=6e-3)
    np.testing.assert_allclose(ch.var_alpha, [0.21, 0.24])
    np.testing.assert_allclose(ch.var_beta, [0.1659, 0.21])
    np.testing.assert_allclose(ch.varsigma, [0.147, 0.18])


@pytest.mark.parametrize("mu,nu,expect", [(0.0, 1.0, "linear"), (1.0, 0.3, "saturated"), (0.0, 0.0, "missing")])
def test_channel_special_cases(model, mu, nu, expect):
    m2 = model.with_channel(mu=[mu, mu], nu=[nu, nu])
    rng = np.random.default_rng(8)
    T = 10
    v = rng.normal(size=(T, 2))
    sim = S.simulate_ross(m2, T, 3, x0=[2.0, -1.5, 0.5], v=v, seed=9)
    cx = sim.x[:, :-1] @ m2.C.T
    ref = {"linear": cx, "saturated": np.clip(cx, -1, 1), "missing": 0 * cx}[expect] + v
    np.testing.assert_allclose(sim.y, ref, atol=1e-14)
    assert m2.channel.var_alpha.max() == m2.channel.var_beta.max() == m2.channel.varsigma.max() == 0


def test_simulation_is_seeded_and_batched(model):
    w, v = S.wang2010_disturbances(20)
    a = S.simulate_ross(model, 20, 5, x0=PAPER["x0"], w=w, v=v, seed=11)
    b = S.simulate_ross(model, 20, 5, x0=PAPER["x0"], w=w, v=v, seed=11)
    np.testing.assert_array_equal(a.y, b.y)
    assert a.x.shape == (5, 21, 3) and a.y.shape == (5, 20, 2) and a.z.shape == (5, 21, 2)
    out = F.RegionalHinfFilter(PAPER["Af"], PAPER["Bf"], model.M).filter(a.y)
    for r in range(5):
        one = F.RegionalHinfFilter(PAPER["Af"], PAPER["Bf"], model.M).filter(a.y[r])
        np.testing.assert_allclose(one.mean, out.mean[r], atol=1e-15)
    assert out.mean.shape == (5, 20, 3) and out.times.tolist() == list(range(1, 21))
    np.testing.assert_allclose(out.extras["z"], out.mean @ model.M.T, atol=1e-15)


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------
def test_bad_inputs(model):
    with pytest.raises(ValidationError, match=r"mu: expected probabilities in \[0, 1\]"):
        M.wang2010_model(mu=[1.2, 0.5])
    with pytest.raises(ValidationError, match=r"nu: expected probabilities"):
        RandomSaturation([0.5], [-0.1])
    with pytest.raises(ValidationError, match="level: expected saturation levels > 0"):
        M.wang2010_model(level=0.0)
    with pytest.raises(ValidationError, match="bounds look swapped"):
        M.wang2010_model(U1=model.U2, U2=model.U1)
    with pytest.raises(ValidationError, match="U1 - U2 symmetric"):
        M.wang2010_model(U1=model.U1 + np.triu(np.ones((3, 3)), 1))
    with pytest.raises(ShapeError, match=r"C: expected \(m, n\)"):
        M.wang2010_model(C=np.ones((2, 4)))
    with pytest.raises(ShapeError, match="mu, nu: expected length m=2"):
        M.wang2010_model(mu=[0.5], nu=[0.5])
    with pytest.raises(ShapeError, match=r"Af: expected shape \(3, 3\)"):
        H.analyze(model, np.zeros((2, 2)), np.zeros((3, 2)))
    with pytest.raises(ShapeError, match=r"Bf: expected shape \(3, 2\)"):
        H.psi_matrix(model, np.zeros((3, 3)), np.zeros((3, 3)), np.eye(6), [0.5, 0.5], 1, 1, 1)
    with pytest.raises(ValidationError, match="method: expected one of"):
        H.design(model, method="magic")
    with pytest.raises(ValidationError, match="gamma: expected a positive number"):
        H.design(model, gamma=-1.0)
    with pytest.raises(ValidationError, match="covariance='exact' is only available"):
        H.design(model, covariance="exact")
    with pytest.raises(ValidationError, match="rho: expected a positive value together with a fixed P"):
        H.analyze(model, PAPER["Af"], PAPER["Bf"], rho=0.2)
    with pytest.raises(ShapeError, match=r"w: expected \(5, 1\)"):
        S.simulate_ross(model, 5, 1, w=np.zeros((4, 1)))
    with pytest.raises(ValidationError, match="steps: expected a positive integer"):
        S.simulate_ross(model, 0)
    with pytest.raises(ValidationError, match="model.f: expected"):
        S.simulate_ross(M.wang2010_model(f=None), 5)


def test_infeasible_problem_returns_no_gains(model):
    cert = H.design(model, gamma=0.2)  # below the zero-filter bound: infeasible
    assert cert.status == "infeasible" and not cert.ok
    assert cert.Af is None and cert.Bf is None and cert.P is None
    with pytest.raises(ValidationError, match="expected a solved and verified design"):
        F.RegionalHinfFilter.from_certificate(cert, model)


def test_rejected_when_recheck_fails(model, monkeypatch):
    real = H.verify

    def failing(*args, **kwargs):
        v = real(*args, **kwargs)
        return H.Verification(
            ok=False,
            reasons=["forced failure"],
            max_eig=v.max_eig,
            max_eig_region=v.max_eig_region,
            min_eig_P=v.min_eig_P,
            gamma_min=None,
        )

    monkeypatch.setattr(H, "verify", failing)
    cert = H.design(model)
    assert cert.status == "rejected" and cert.Af is None
    assert cert.verification.reasons == ["forced failure"]


def test_verify_catches_tampered_certificate(th3_feasible, model):
    c = th3_feasible
    ok = H.verify(model, c.Af, c.Bf, c.P, c.Lambda, c.eps1, c.eps2, 1.5, pi=c.pi, rho=c.rho, block_diagonal=True)
    assert ok.ok
    bad = H.verify(model, c.Af, c.Bf, c.P, c.Lambda, c.eps1, c.eps2, 0.5, pi=c.pi, rho=c.rho)
    assert not bad.ok and "Psi (17)" in bad.reasons[0]
    bad = H.verify(model, c.Af, c.Bf, c.P, c.Lambda, c.eps1, c.eps2, 1.5, pi=c.pi, rho=10 * c.rho_star)
    assert any("not inside L" in r for r in bad.reasons)
    bad = H.verify(model, c.Af, c.Bf, c.P, np.array([1.2, 0.5]), c.eps1, c.eps2, 1.5)
    assert any("(9)" in r for r in bad.reasons)


# --------------------------------------------------------------------------------------------
# §5.2 LMIs
# --------------------------------------------------------------------------------------------
def test_theorem3_feasible_at_paper_gamma_and_rechecked(th3_feasible, model):
    c = th3_feasible
    assert c.status == "optimal" and c.ok and c.gamma == 1.5
    assert c.verification.ok and c.verification.max_eig < 0
    assert np.abs(c.P[:3, 3:]).max() == 0  # P = diag{Q1, Q2}
    # Ω(P,ρ) ⊂ ℒ by the closed form ρ a_i² C_i Q1^{-1} C_i^T <= 1, and ρ* >= ρ
    g = np.einsum("ij,jk,ik->i", model.C, np.linalg.inv(c.Q1), model.C)
    assert (c.rho * c.Lambda**2 * g <= 1 + 1e-7).all()
    assert c.rho_star >= c.rho * (1 - 1e-9)
    np.testing.assert_allclose(c.rho_star, 1 / np.max(c.Lambda**2 * g), rtol=1e-12)


def test_theorem3_feasible_with_scs(model):
    c = H.design(model, solver="SCS", fallback=None)
    assert c.status == "optimal" and c.solver == "SCS" and c.verification.ok


def test_theorem3_min_gamma_is_the_zero_filter(th3_min, zero_gamma):
    c = th3_min
    assert c.ok and abs(c.gamma - 1.05189) < 5e-3  # spec F2 / verifier 1.0518935
    assert np.abs(c.Af).max() < 1e-6 and np.abs(c.Bf).max() < 1e-6
    # spec F3: structural fact about this theorem, asserted
    assert zero_gamma.ok and abs(c.gamma - zero_gamma.gamma) < 1e-3


def test_zero_filter_dominance_certificate_transfer(model):
    """F3 proof: any block-diagonal certificate of a filter also certifies the zero filter
    (same Q1, Λ, ε, π; Q2 large), so γ(theorem) >= γ(zero filter)."""
    cert = H.analyze(model, PAPER["Af"], PAPER["Bf"], objective="feasibility", gamma=1.5)
    assert cert.ok
    Q2 = 1e4 * np.eye(3)
    P0 = np.block([[cert.Q1, np.zeros((3, 3))], [np.zeros((3, 3)), Q2]])
    zero = H.verify(
        model,
        np.zeros((3, 3)),
        np.zeros((3, 2)),
        P0,
        cert.Lambda,
        cert.eps1,
        cert.eps2,
        1.5,
        pi=cert.pi,
        rho=cert.rho,
        block_diagonal=True,
    )
    assert zero.ok


def test_printed_gains_theorem2(model):
    c = H.analyze(model, PAPER["Af"], PAPER["Bf"])  # P free, block-diagonal
    assert c.ok and abs(c.gamma - 1.1607) < 5e-3  # spec F4 / verifier 1.160728
    assert c.gamma > 1.0519  # F3: worse than the zero filter


def test_printed_P_theorem3(model):
    P = PAPER["P"]
    c = H.design(model, objective="min_gamma", fixed_Q=(P[:3, :3], P[3:, 3:]))
    assert c.ok and abs(c.gamma - 1.2988) < 5e-3  # spec F5


def test_printed_triple_theorem1_holds_theorem2_fails(model):
    P, rho = PAPER["P"], PAPER["rho"]
    t1 = H.analyze(model, PAPER["Af"], PAPER["Bf"], theorem=1, P=P, rho=rho, objective="max_margin")
    assert t1.ok and t1.verification.ok and abs(t1.verification.max_eig - (-3.96e-3)) < 5e-4
    t2 = H.analyze(model, PAPER["Af"], PAPER["Bf"], theorem=2, P=P, rho=rho, objective="max_margin", gamma=100.0)
    assert t2.status == "infeasible" and t2.Af is None and t2.best_max_eig > 0


def test_narrower_sector_does_not_increase_gamma(model, th3_min):
    A0 = (model.U1 + model.U2) / 2
    U = model.U1 - model.U2
    narrow = M.wang2010_model(U1=A0 + 0.25 * U, U2=A0 - 0.25 * U)
    c = H.design(narrow, objective="min_gamma")
    assert c.ok and c.gamma <= th3_min.gamma + 1e-4


@pytest.mark.parametrize(
    "mu,nu,D", [(0.0, 1.0, 1.0), (1.0, 0.5, 1.0), (0.0, 0.6, 1.0), (0.0, 0.0, 1.0), (0.7, 0.7, 0.1)]
)
def test_theorem3_special_cases_all_give_the_zero_filter_gamma(mu, nu, D, zero_gamma):
    m2 = M.wang2010_model(mu=[mu, mu], nu=[nu, nu], D=[D, D])
    c = H.design(m2, objective="min_gamma")
    assert c.ok and abs(c.gamma - zero_gamma.gamma) < 2e-3  # F3: independent of the sensors


# --------------------------------------------------------------------------------------------
# The improved design
# --------------------------------------------------------------------------------------------
def test_improved_design_beats_the_zero_filter(improved, zero_gamma, model):
    c = improved
    assert c.ok and c.verification.ok
    assert c.gamma < zero_gamma.gamma - 0.5  # 0.444 vs 1.052
    assert np.abs(c.P[:3, 3:]).max() > 1e-3  # the coupling is what helps
    # independent numpy re-check from scratch, at the certified γ
    v = H.verify(model, c.Af, c.Bf, c.P, c.Lambda, c.eps1, c.eps2, c.gamma, pi=c.pi, rho=c.rho)
    assert v.ok and v.gamma_min <= c.gamma
    # independent second solve: full-P Theorem-2 analysis of the returned gains
    ana = H.analyze(model, c.Af, c.Bf, lyapunov="full")
    assert ana.ok and ana.gamma <= c.gamma + 1e-3
    # with the paper's block-diagonal P the same gains certify no better than the zero filter
    blk = H.analyze(model, c.Af, c.Bf, lyapunov="block")
    assert not blk.ok or blk.gamma >= zero_gamma.gamma - 1e-3


def test_exact_covariance_option_changes_gamma(model, improved):
    ex = H.design(model, method="coupled", objective="min_gamma", covariance="exact")
    assert ex.ok and ex.gamma < improved.gamma - 0.05  # bound (14) costs γ
    v = H.verify(
        model, ex.Af, ex.Bf, ex.P, ex.Lambda, ex.eps1, ex.eps2, ex.gamma, pi=ex.pi, rho=ex.rho, covariance="exact"
    )
    assert v.ok
    vp = H.verify(
        model, ex.Af, ex.Bf, ex.P, ex.Lambda, ex.eps1, ex.eps2, ex.gamma, pi=ex.pi, rho=ex.rho, covariance="paper"
    )
    assert not vp.ok  # not a paper (14) certificate


def _inside_scale(model, cert, w, v, runs, seed):
    """Largest scaling (bisection) of w̄ keeping every run inside Ω(P, ρ) (spec A10)."""
    lo, hi = 0.0, 1.0
    for _ in range(20):
        s = 0.5 * (lo + hi)
        sim = S.simulate_ross(model, w.shape[0], runs, w=s * w, v=s * v, seed=seed)
        xh = trajectory(cert.Af, cert.Bf, model.M, sim.y)
        eta = np.concatenate([sim.x, xh], axis=-1)
        peak = np.einsum("...i,ij,...j->...", eta, cert.P, eta).max() / cert.rho
        lo, hi = (s, hi) if peak <= 1 else (lo, s)
    return lo


@pytest.mark.parametrize("which", ["improved", "th3"])
def test_empirical_l2_gain_below_certified_gamma(model, improved, th3_feasible, which):
    cert = improved if which == "improved" else th3_feasible
    T, runs = 60, 400
    k = np.arange(T)
    cases = [
        S.wang2010_disturbances(T),
        (np.cos(np.pi * k)[:, None] * np.exp(-0.05 * k)[:, None], np.zeros((T, 2))),  # ω = π
        (np.zeros((T, 1)), np.stack([np.cos(np.pi * k), np.cos(2 * k)], -1) * np.exp(-0.05 * k)[:, None]),
    ]
    for w, v in cases:
        s = _inside_scale(model, cert, w, v, 50, 21)
        assert s > 0
        sim = S.simulate_ross(model, T, runs, w=s * w, v=s * v, seed=22)
        xh = trajectory(cert.Af, cert.Bf, model.M, sim.y)
        err = ((sim.z - xh @ model.M.T) ** 2).sum(-1).mean(0).sum()
        ratio = np.sqrt(err / sim.disturbance_energy[0])
        assert ratio < cert.gamma, (ratio, cert.gamma)


def test_dissipation_with_nonzero_initial_state_A9(model, improved):
    c = improved
    T, runs = 60, 400
    w, v = S.wang2010_disturbances(T)
    x0 = 0.3 * np.sqrt(c.rho) * np.array([1.0, 0.0, 0.0]) / np.sqrt(c.P[0, 0])
    s = 0.05
    sim = S.simulate_ross(model, T, runs, x0=x0, w=s * w, v=s * v, seed=23)
    xh = trajectory(c.Af, c.Bf, model.M, sim.y)
    eta = np.concatenate([sim.x, xh], axis=-1)
    assert np.einsum("...i,ij,...j->...", eta, c.P, eta).max() <= c.rho
    err = ((sim.z - xh @ model.M.T) ** 2).sum(-1).mean(0).sum()
    assert err <= c.gamma**2 * sim.disturbance_energy[0] + eta[0, 0] @ c.P @ eta[0, 0]


# --------------------------------------------------------------------------------------------
# §5.3 simulation
# --------------------------------------------------------------------------------------------
def test_mean_square_stability_inside_omega(model, th3_feasible):
    c = th3_feasible
    rng = np.random.default_rng(30)
    u = rng.normal(size=6)
    u /= np.linalg.norm(u)
    L = np.linalg.cholesky(c.P)
    eta0 = np.sqrt(c.rho) * np.linalg.solve(L.T, u)  # η0^T P η0 = ρ
    runs, T = 1000, 25
    sim = S.simulate_ross(model, T, runs, x0=eta0[:3], seed=31)
    xh = trajectory(c.Af, c.Bf, model.M, sim.y, x0=eta0[3:])
    eta = np.concatenate([sim.x, xh], axis=-1)
    V = np.einsum("...i,ij,...j->...", eta, c.P, eta).mean(0)
    np.testing.assert_allclose(V[0], c.rho, rtol=1e-9)
    assert V[5] < 0.5 * V[0] and V[-1] < 1e-3 * V[0]


def test_paper_scenario_smoke_values(model):
    """Spec §5.3.3 (loose tolerances; these are the spec's reproduction numbers, not paper facts)."""
    T, runs = 100, 2000
    w, v = S.wang2010_disturbances(T)
    for x0, paper_ref, zero_ref in ((PAPER["x0"], 0.158, 0.177), (np.zeros(3), 0.114, 0.135)):
        sim = S.simulate_ross(model, T, runs, x0=x0, w=w, v=v, seed=40)
        assert abs(sim.disturbance_energy[0] - 19.86) < 0.01
        for Af, Bf, ref in ((PAPER["Af"], PAPER["Bf"], paper_ref), (np.zeros((3, 3)), np.zeros((3, 2)), zero_ref)):
            xh = trajectory(Af, Bf, model.M, sim.y)
            err = ((sim.z - xh @ model.M.T) ** 2).sum(-1).mean(0).sum()
            assert abs(err - ref) < 0.006, (err, ref)
    # η^T P η leaves Ω at k = 2 (spec F7: peak 1.43 at k = 2 with the printed P)
    sim = S.simulate_ross(model, T, 1, x0=PAPER["x0"], w=w, v=v, seed=41)
    xh = trajectory(PAPER["Af"], PAPER["Bf"], model.M, sim.y)
    eta = np.concatenate([sim.x, xh], axis=-1)[0]
    V = np.einsum("ki,ij,kj->k", eta, PAPER["P"], eta)
    assert V[0] <= PAPER["rho"] and V.max() > PAPER["rho"] and V.argmax() == 2


def test_iterate_never_worse_than_coupled(model, improved):
    it = H.design(model, method="iterate", objective="min_gamma", iterations=2)
    assert it.ok and it.verification.ok
    assert it.gamma <= improved.gamma + 1e-6
    assert all(b <= a + 1e-12 for a, b in zip(it.history, it.history[1:]))


def test_coupled_feasibility_at_paper_gamma(model):
    c = H.design(model, method="coupled", gamma=1.5)
    assert c.ok and c.gamma == 1.5 and c.verification.ok and c.verification.gamma_min < 1.5


def test_theorem1_stability_check_for_given_gains(model):
    c = H.analyze(model, PAPER["Af"], PAPER["Bf"], theorem=1)
    assert c.ok and c.gamma is None and c.verification.ok
    # Φ (12) is the top-left block of Ψ (17) minus M̄^T M̄ (spec §2.2): (17) ⇒ (12)
    psi = H.psi_matrix(model, PAPER["Af"], PAPER["Bf"], c.P, c.Lambda, c.eps1, c.eps2, 1.0)
    phi = H.psi_matrix(model, PAPER["Af"], PAPER["Bf"], c.P, c.Lambda, c.eps1, c.eps2, None)
    Mb = np.hstack([model.M, -model.M])
    np.testing.assert_allclose(psi[:11, :11] - phi, np.pad(Mb.T @ Mb, ((0, 5), (0, 5))), atol=1e-12)


def test_saturation_level_extension_A13(model):
    m2 = model.with_channel(level=[2.0, 0.5])
    c = H.design(m2)
    assert c.ok
    g = np.einsum("ij,jk,ik->i", m2.C, np.linalg.inv(c.Q1), m2.C)
    assert (c.rho * c.Lambda**2 * g <= np.array([4.0, 0.25]) * (1 + 1e-7)).all()
    np.testing.assert_allclose(c.rho_star, np.min(np.array([4.0, 0.25]) / (c.Lambda**2 * g)), rtol=1e-12)


_prob = st.sampled_from([0.0, 1.0]) | st.floats(0.0, 1.0)


@settings(max_examples=30, deadline=None)
@given(mu1=_prob, mu2=_prob, nu1=_prob, nu2=_prob, seed=st.integers(0, 2**16))
def test_expectation_identity_for_any_probabilities(mu1, mu2, nu1, nu2, seed):
    model = M.wang2010_model(mu=[mu1, mu2], nu=[nu1, nu2])
    rng = np.random.default_rng(seed)
    Af, Bf = rng.normal(size=(3, 3)), rng.normal(size=(3, 2))
    L = rng.normal(size=(6, 6))
    P = L @ L.T + 0.1 * np.eye(6)
    eta, w, v = rng.normal(scale=2, size=6), rng.normal(size=1), rng.normal(size=2)
    ref = _enumerate_expectation(model, Af, Bf, P, eta, w, v)
    exact = H.expected_lyapunov_next(model, Af, Bf, P, eta, w, v, covariance="exact")
    bound = H.expected_lyapunov_next(model, Af, Bf, P, eta, w, v, covariance="paper")
    assert abs(exact - ref) <= 1e-10 * max(1.0, abs(ref))
    assert bound >= exact - 1e-10 * max(1.0, abs(ref))


# --------------------------------------------------------------------------------------------
# verify's rounding margin, the reported slack, iterate without a second solver (WH-22)
# --------------------------------------------------------------------------------------------
def test_verify_refuses_a_slack_lost_in_rounding(improved, model):
    """λmax(Ψ) = -1.1e-11 on a Ψ of norm 67 is within rounding (about 2e-11): not a certificate."""
    c = improved
    g_min = c.verification.gamma_min
    tight = np.sqrt(g_min**2 + 1e-10)
    v = H.verify(model, c.Af, c.Bf, c.P, c.Lambda, c.eps1, c.eps2, tight, pi=c.pi, rho=c.rho)
    assert v.max_eig < 0  # the old test (λmax < 0) accepted it
    assert -v.max_eig < v.rounding
    assert not v.ok and any("beyond rounding" in r for r in v.reasons)
    roomy = H.verify(model, c.Af, c.Bf, c.P, c.Lambda, c.eps1, c.eps2, np.sqrt(g_min**2 + 1e-6), pi=c.pi, rho=c.rho)
    assert roomy.ok and roomy.margin > roomy.rounding


def test_certificate_reports_the_slack_it_has(improved):
    v = improved.verification
    assert v.margin == pytest.approx(-v.max_eig) and v.margin > v.rounding > 0
    s = improved.summary()
    assert s["verified_margin"] == v.margin and s["lmi_margin"] == improved.lmi_margin


def test_iterate_does_not_retry_its_steps_with_a_second_solver(model, monkeypatch):
    calls = []
    real = H._solve

    def spy(prob, solver, fallback):
        calls.append(fallback)
        return real(prob, solver, fallback)

    monkeypatch.setattr(H, "_solve", spy)
    it = H.design(model, method="iterate", objective="min_gamma", iterations=2)
    assert it.ok
    assert calls[0] == "SCS"  # the initial coupled design keeps its fallback
    assert len(calls) > 1 and all(f is None for f in calls[1:])
