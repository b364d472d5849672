"""Batched Monte Carlo simulation of truth and measurements, from an explicit seed.

- :func:`simulate` (:mod:`tobitkf.simulate.core`): a :class:`~tobitkf.LinearSystem` through any
  channel (censoring, Rice fading, the protocol channel, random saturation).
- :func:`simulate_delay` (:mod:`tobitkf.simulate.delay`): the delay system of Li, Li & Wang.
- :func:`simulate_ross` (:mod:`tobitkf.simulate.ross`): the H∞ plant of Wang, Shen & Liu.
"""

from .core import SimulationData, as_generator, psd_sqrt, simulate
from .delay import full_states, simulate_delay
from .ross import RossSimulation, simulate_ross, wang2010_disturbances

__all__ = [
    "SimulationData",
    "simulate",
    "as_generator",
    "psd_sqrt",
    "simulate_delay",
    "full_states",
    "RossSimulation",
    "simulate_ross",
    "wang2010_disturbances",
]
