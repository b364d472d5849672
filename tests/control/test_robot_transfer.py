"""Robot of §6.3 (setup, trilateration, options) and the TKF-LQG transfer functions of §6.4.1."""

import numpy as np
import pytest

from tobitkf._validation import ValidationError
from tobitkf.control.lqg import lqr
from tobitkf.control.plants import dc_motor_speed
from tobitkf.control.robot import TRANSMITTERS, robot_setup, simulate_robot, trilaterate
from tobitkf.control.transfer import observer_based_reference_response, tkf_lqg_loop


def test_trilateration_is_exact_for_consistent_ranges():
    rng = np.random.default_rng(0)
    p = rng.uniform(-30, 30, size=(20, 2))
    d = np.linalg.norm(p[:, None, :] - TRANSMITTERS[None], axis=-1)
    assert trilaterate(d) == pytest.approx(p, abs=1e-9)


def test_robot_constants_and_printed_input_matrix():
    s = robot_setup()
    assert s.eta_d == pytest.approx(0.014240, abs=5e-7)  # (6.37)-(6.40)
    assert 10 ** (-s.limit / (10 * s.alpha)) == pytest.approx(31.62, abs=0.01)  # -90 dBm range
    assert np.all(np.abs(np.linalg.eigvals(s.Ap - s.Bp @ s.K)) < 1)
    with pytest.raises(ValidationError, match="not stabilizable"):
        robot_setup(input_matrix="printed")


def test_robot_half_log_option_changes_the_range_input_and_uncensored_loop_tracks():
    s = robot_setup(limit=-1000.0)  # nothing censored: the loop must track a small circle
    a = simulate_robot(s, radius=8.0, steps=300, runs=2, seed=3)
    b = simulate_robot(s, radius=8.0, steps=300, runs=2, seed=3, half_log=True)
    assert not np.allclose(a.estimate_tkf[..., 4:], b.estimate_tkf[..., 4:])
    track = np.linalg.norm(a.x[:, 1:, [0, 2]] - a.reference, axis=-1)
    assert np.median(track[:, 100:]) < 2.0 and not a.diverged.any()
    # with no censoring the TKF and the KF see the same data and agree
    assert a.estimate_tkf == pytest.approx(a.estimate_kf, abs=1e-8)
    with pytest.raises(ValidationError, match="feedback"):
        simulate_robot(s, feedback="ekf")


def test_transfer_functions_of_6_48():
    import control

    p = dc_motor_speed()
    K = lqr(p.A, p.B, np.diag([100.0, 0.0]), [[1e-6]]).gain
    t1, _, _ = tkf_lqg_loop(p.A, p.B, p.G, p.C, p.W, 0.05, K, 1.0, gain="tobit")
    t2, _, _ = tkf_lqg_loop(p.A, p.B, p.G, p.C, p.W, 0.05, K, 1.0, gain="uncensored")
    assert float(np.real(control.dcgain(t1))) == pytest.approx(1.0, rel=1e-9)  # N for unit DC gain at ED = 1
    assert float(np.real(control.dcgain(t2))) == pytest.approx(1.0, rel=1e-9)
    dc = [
        float(np.real(control.dcgain(tkf_lqg_loop(p.A, p.B, p.G, p.C, p.W, 0.05, K, xi)[0]))) for xi in (0.9, 0.5, 0.1)
    ]
    assert dc[0] > dc[1] > dc[2]  # degradation grows with censoring (Fig 6.14)
    assert dc[1] > 0.9  # little degradation at 50 % censored
    Nbar = -1.0 / (p.C @ np.linalg.solve(p.A - p.B @ K, p.B))
    obs = observer_based_reference_response(p.A, p.B, p.C, K, Nbar)
    assert float(np.real(control.dcgain(obs))) == pytest.approx(1.0, rel=1e-9)
    with pytest.raises(ValidationError, match="gain"):
        tkf_lqg_loop(p.A, p.B, p.G, p.C, p.W, 0.05, K, 0.5, gain="both")
