r"""Small pure helpers shared by the smoothers, likelihoods and fits (batched over leading axes).

They are defined with the filters that use them, below this package, and handed on here:

* :func:`censoring_sides`: which readings are censored and at which limit, from an explicit
  indicator or (the default) from the limit rule (:mod:`tobitkf.filters._readings`);
* :func:`gaussian_log_density`: :math:`\log N(e; 0, S)` over the observed channels only
  (:mod:`tobitkf.filters.likelihood`);
* :func:`solve_psd`: :math:`S^{-1}B` for symmetric PSD :math:`S`, a pseudo-inverse where singular
  (:mod:`tobitkf.filters.smoothing`);
* :func:`assumed_density_filter`: the package's one assumed-density filter as the smoothers,
  likelihoods and fits run it (:mod:`tobitkf.filters.assumed_density`).
"""

from __future__ import annotations

from ..filters._readings import _as_indicator, censoring_sides
from ..filters.assumed_density import assumed_density_filter
from ..filters.likelihood import LOG_2PI, gaussian_log_density
from ..filters.smoothing import solve_psd

__all__ = ["censoring_sides", "gaussian_log_density", "solve_psd", "assumed_density_filter", "LOG_2PI", "_as_indicator"]
