"""The ROSS channel used through the core simulator (hook ``draw``)."""

import numpy as np
import pytest

from tobitkf._validation import ShapeError, ValidationError
from tobitkf.channels.saturation import RandomSaturation
from tobitkf.models import LinearSystem
from tobitkf.simulate import simulate


def test_core_simulate_hook_reproduces_eq2():
    sys_ = LinearSystem(
        A=np.eye(2) * 0.9, C=[[1.0, 0.0], [1.0, 1.0]], Q=np.eye(2), R=np.eye(2) * 0.01, x0=[3.0, -2.0], P0=np.eye(2)
    )
    ch = RandomSaturation([0.5, 0.2], [0.6, 0.9], level=[1.0, 2.0])
    data = simulate(sys_, 30, 7, measurement=ch, seed=3)
    a, b = data.extras["alpha"], data.extras["beta"]
    cx = data.x[:, 1:] @ np.array([[1.0, 0.0], [1.0, 1.0]]).T
    v = data.y_latent - (a * np.clip(cx, [-1, -2], [1, 2]) + (1 - a) * b * cx)
    assert np.abs(v).max() < 1.0  # what is left is the Gaussian noise (std 0.1)
    missing = (a == 0) & (b == 0)
    assert missing.any()
    np.testing.assert_allclose(np.std(v), 0.1, rtol=0.2)


def test_bad_channel_inputs():
    with pytest.raises(ShapeError, match="same length m"):
        RandomSaturation([0.5, 0.5], [0.5])
    with pytest.raises(ShapeError, match=r"level: expected a scalar or shape \(2,\)"):
        RandomSaturation([0.5, 0.5], [0.5, 0.5], level=[1.0, 1.0, 1.0])
    with pytest.raises(ValidationError, match="level: expected saturation levels > 0"):
        RandomSaturation([0.5], [0.5], level=-1.0)
    with pytest.raises(ShapeError, match="cx: expected last axis of length m=1"):
        RandomSaturation([0.5], [0.5]).measure(np.zeros((3, 2)), 0, 0)
