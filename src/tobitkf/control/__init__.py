"""Control with censored measurements (Miller 2015, Ch. 4–6; deviations in docs/sources/miller2015-ch1-4.md
and miller2015-ch5-7.md).

- :mod:`.lqg`: LQR / LQE (CT and DT, via python-control, Newton-refined), the Tobit LQE (modified ARE,
  ``tobit_lqe`` / ``tobit_dlqe``), setpoint gains, exact ZOH discretization; Riccati failures raise
  errors naming the equation. Results unpack like python-control's (``L, P, E = lqe(...)``).
- :mod:`.closed_loop`: batched closed-loop LQG with KF, TKF or steady-state TKF observers.
- :mod:`.stability`: the Tobit observer Jacobian, the printed (5.56) diagnostic, a polytopic
  Lyapunov certificate, mean-field error dynamics.
- :mod:`.plants`: the DC motor (speed/position) and the scalar example of Ch. 5.
- :mod:`.transfer`: transfer functions of the steady-state TKF-LQG (§6.4.1).
- :mod:`.panning`: censoring-limit control laws for a panning camera (§6.7.3).
- :mod:`.robot`: the RSS-localised mobile robot of §6.3.
"""

from .closed_loop import OBSERVERS, ClosedLoopResult, quadratic_cost, simulate_closed_loop
from .lqg import (
    EstimatorGain,
    RegulatorGain,
    controlled_noise,
    discretize,
    dlqe,
    dlqr,
    equilibrium,
    is_stable,
    lqe,
    lqr,
    reference_gain,
    tobit_dlqe,
    tobit_lqe,
)
from .panning import centred_window, covariance_panning_step, imr_panning_step, keep_in_view_limit, moving_window_tkf
from .plants import dc_motor_position, dc_motor_speed, scalar_example
from .robot import robot_setup, simulate_robot, trilaterate
from .stability import (
    COUNTEREXAMPLE,
    COUNTEREXAMPLE_TWO_OUTPUTS,
    StabilityCertificate,
    certify_tkf_stability,
    dissertation_jacobian_5_56,
    mean_field_error,
    mean_observer_map,
    tobit_error_jacobian,
    tobit_jacobian,
)
from .transfer import observer_based_reference_response, tkf_lqg_loop

__all__ = [
    "lqr",
    "dlqr",
    "lqe",
    "dlqe",
    "tobit_lqe",
    "tobit_dlqe",
    "controlled_noise",
    "reference_gain",
    "equilibrium",
    "discretize",
    "is_stable",
    "RegulatorGain",
    "EstimatorGain",
    "simulate_closed_loop",
    "ClosedLoopResult",
    "quadratic_cost",
    "OBSERVERS",
    "tobit_jacobian",
    "tobit_error_jacobian",
    "mean_observer_map",
    "dissertation_jacobian_5_56",
    "certify_tkf_stability",
    "StabilityCertificate",
    "mean_field_error",
    "COUNTEREXAMPLE",
    "COUNTEREXAMPLE_TWO_OUTPUTS",
    "keep_in_view_limit",
    "centred_window",
    "imr_panning_step",
    "covariance_panning_step",
    "moving_window_tkf",
    "dc_motor_speed",
    "dc_motor_position",
    "scalar_example",
    "robot_setup",
    "simulate_robot",
    "trilaterate",
    "tkf_lqg_loop",
    "observer_based_reference_response",
]
