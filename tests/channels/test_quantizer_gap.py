"""Where the assumed-density filter of a quantized sensor falls short of the optimum: a binary sensor (two
levels, the sign of the latent reading) of a slowly drifting state read with little noise. Each reading says
only on which side of 0 the state lies, so the posterior is a normal cut at 0, far from Gaussian, and the
filter's mean-squared error is measurably above the converged particle filter's (the gap the
``tobitkf.channels.quantizer`` docstring reports). On the coarse quantizers of ``test_quantizer.py`` the two agree
within Monte Carlo error.

The particle filter is first shown converged on the same readings (N_p and 2 N_p within 3 standard errors of
each other); the gap is then the paired ratio of the mean-squared errors over the runs, whose standard error
(delta method over the runs) sets both bounds: more than 2 standard errors above 1, and below 1.15.
"""

from __future__ import annotations

import numpy as np
import pytest

import tobitkf as tk


def _ratio(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """mean(a) / mean(b) of paired per-run values and its standard error (delta method over the runs)."""
    r = a.mean() / b.mean()
    d = (a - a.mean()) / a.mean() - (b - b.mean()) / b.mean()
    return float(r), float(r * np.sqrt((d * d).sum() / (a.size * (a.size - 1))))


@pytest.mark.heavy
def test_a_binary_sensor_of_a_slow_state_leaves_a_gap_to_the_particle_filter():
    sys_ = tk.LinearSystem(A=[[0.99]], C=[[1.0]], Q=[[0.01]], R=[[1e-4]], x0=[0.0], P0=[[1.0]])
    sign = tk.Quantizer(1.0, offset=0.5, lower=-0.5, upper=0.5)  # levels -0.5 and 0.5: y* < 0 or y* >= 0
    d = tk.simulate(sys_, 40, 600, channel=sign, seed=21)

    def mse(result):
        return ((result.mean - d.x[:, 1:]) ** 2).mean(axis=(1, 2))

    adf = mse(tk.AssumedDensityFilter(sys_, sign, backend="numpy").filter(d.y, outputs=("mean",)))
    pf1, pf2 = (
        mse(tk.ParticleFilter(sys_, sign, particles=n, seed=22).filter(d.y, outputs=("mean",))) for n in (1000, 2000)
    )
    conv, conv_se = _ratio(pf1, pf2)
    assert abs(conv - 1.0) < 3 * conv_se, (conv, conv_se)  # the optimum is converged at this size
    gap, se = _ratio(adf, pf2)
    assert 1.0 + 2 * se < gap < 1.15, (gap, se)
