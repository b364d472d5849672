r"""Plants of Miller (2015) Ch. 5–6: DC motor (speed and position), the scalar example.

Source: Miller §5.3.3 (scalar), §5.4.1 (5.58)–(5.61) and §5.4.2 (5.64)–(5.66).

DC motor, state :math:`[\dot\theta, i]` (speed) or :math:`[\theta, \dot\theta, i]` (position):

.. math::

    A_{speed} = \begin{bmatrix} -b/j & k/j \\ -k/l & -r/l \end{bmatrix}, \quad
    G = B = \begin{bmatrix} 0 \\ 1/l \end{bmatrix}, \quad C = [1\ 0], \quad
    W = \sigma_q^2, \quad V = \sigma_r^2

Deviations from the source (all needed to reproduce the printed numbers; docs/sources MB-09 to MB-12, MB-24):

* k = 9.73E−3, not the printed 9.37E−3 (a digit transposition; only 9.73E−3 gives the
  printed A and L);
* A11 = −b/j and A22 = −r/l (the printed (5.58)/(5.64) have + signs, the numeric (5.59)/(5.65) −);
* G = [0; 1/l] (printed [0; l] in (5.58)); the printed Q of (5.60) is inconsistent and replaced by
  G σ_q² G^T;
* σ_q = 0.01 and σ_r = 0.05 are standard deviations (the text says "variances");
* B (the voltage input) is not given; B = G, the standard DC-motor voltage input.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._validation import as_float

__all__ = ["ContinuousPlant", "DC_MOTOR", "dc_motor_speed", "dc_motor_position", "scalar_example"]

DC_MOTOR = {"b": 3.5077e-6, "j": 4.2937e-5, "k": 9.73e-3, "r": 4.27, "l": 0.288e-6, "sigma_q": 0.01, "sigma_r": 0.05}
"""Parameters of §5.4.1 (k corrected to 9.73E-3, MB-09)."""


class ContinuousPlant(NamedTuple):
    """A CT plant :math:`\\dot x = Ax + Bu + Gw`, :math:`y = Cx + v`; W, V noise covariances."""

    A: np.ndarray
    B: np.ndarray
    G: np.ndarray
    C: np.ndarray
    W: np.ndarray
    V: np.ndarray


def dc_motor_speed(*, k: float = DC_MOTOR["k"]) -> ContinuousPlant:
    """DC-motor speed model (5.59) with the corrections of the module docstring; ``k=9.37e-3`` gives the printed typo."""
    p = dict(DC_MOTOR, k=as_float(k, "k", low=0.0, low_open=True))
    A = np.array([[-p["b"] / p["j"], p["k"] / p["j"]], [-p["k"] / p["l"], -p["r"] / p["l"]]])
    G = np.array([[0.0], [1.0 / p["l"]]])
    C = np.array([[1.0, 0.0]])
    return ContinuousPlant(A, G.copy(), G, C, np.array([[p["sigma_q"] ** 2]]), np.array([[p["sigma_r"] ** 2]]))


def dc_motor_position(*, k: float = DC_MOTOR["k"]) -> ContinuousPlant:
    """DC-motor position model (5.65) (state [θ, θ̇, i]); corrections as in the module docstring."""
    s = dc_motor_speed(k=k)
    A = np.zeros((3, 3))
    A[0, 1] = 1.0
    A[1:, 1:] = s.A
    G = np.vstack([[0.0], s.G])
    C = np.array([[1.0, 0.0, 0.0]])
    return ContinuousPlant(A, G.copy(), G, C, s.W, s.V)


def scalar_example() -> ContinuousPlant:
    """§5.3.3: A = −0.8, C = 1, σ = 0.5, σ_q = 0.1 (standard deviations, MB-12)."""
    one = np.array([[1.0]])
    return ContinuousPlant(np.array([[-0.8]]), one, one, one, np.array([[0.01]]), np.array([[0.25]]))
