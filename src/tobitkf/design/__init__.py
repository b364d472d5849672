"""Designs: analyses and syntheses that solve LMIs or Riccati equations before any data is seen.

- :mod:`tobitkf.design.hinf`: regional H∞ filter analysis (Theorems 1–2), design (Theorem 3 and the
  coupled and iterated certificates) and their independent verification (Wang, Shen & Liu).
"""

from .hinf import HinfCertificate, Verification, analyze, design, verify, zero_filter_gamma

__all__ = ["HinfCertificate", "Verification", "analyze", "design", "verify", "zero_filter_gamma"]
