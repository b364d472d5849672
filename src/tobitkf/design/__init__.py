"""Designs: analyses and syntheses that solve LMIs or Riccati equations before any data is seen.

- :mod:`tobitkf.design.hinf`: regional H∞ filter analysis (Theorems 1–2), design (Theorem 3 and the
  coupled and iterated certificates) and their independent verification (Wang, Shen & Liu).
- :mod:`tobitkf.design.protocol_bounds`: the upper and lower bounds on the protocol-based TKF's expected
  covariance (Theorems 3–5 of Geng et al.).
- :mod:`tobitkf.design.pcrlb`: the posterior Cramér–Rao bound of a channel's readings (drawn trajectories
  through :func:`~tobitkf.simulate`), the yardstick of the estimators.
"""

from .hinf import HinfCertificate, Verification, analyze, design, verify, zero_filter_gamma

__all__ = ["HinfCertificate", "Verification", "analyze", "design", "verify", "zero_filter_gamma"]
