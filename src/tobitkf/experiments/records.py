r"""Records as users have them: a sparse river record beside WRTDS, a censored panel, a short irregular series.

The record experiments live one module per record, on shared pieces:

- :mod:`~tobitkf.experiments.records_common`: the batched assumed-density pass (:func:`adf_pass`), the
  finite-difference derivatives of a batched likelihood and the maximum-likelihood fit (:func:`fit_ml`);
- :mod:`~tobitkf.experiments.records_river`: the drifting-coefficient censored model of a sample record with
  daily covariates (:class:`RiverModel`) and its batched leave-one-out refits (:func:`batched_loo_refit`);
- :mod:`~tobitkf.experiments.records_arkansas`: ``data-arkansas``, the Arkansas River's ammonia against WRTDS;
- :mod:`~tobitkf.experiments.records_hiv`: ``data-hiv``, the censored HIV viral-load panel (:class:`PanelModel`);
- :mod:`~tobitkf.experiments.records_niagara`: ``data-niagara``, the Niagara River's short record.

This module gathers their public names.
"""

from __future__ import annotations

from .records_arkansas import (
    ARKANSAS_CANDIDATES,
    ARKANSAS_MODEL,
    FLUX_FACTOR,
    LOO_GTOL,
    STATIC_MODEL,
    arkansas,
    fit_river,
    run_arkansas,
)
from .records_common import adf_pass, fd_gradient, fd_hessian, fit_ml, gap_matrices
from .records_hiv import HIV_CANDIDATES, PanelModel, hiv, last_visit_predictions, run_hiv
from .records_niagara import niagara, niagara_model
from .records_river import RiverModel, batched_loo_refit

__all__ = [
    "RiverModel",
    "PanelModel",
    "adf_pass",
    "fit_ml",
    "arkansas",
    "run_arkansas",
    "hiv",
    "run_hiv",
    "niagara",
    "batched_loo_refit",
    "last_visit_predictions",
    "niagara_model",
    "ARKANSAS_MODEL",
    "ARKANSAS_CANDIDATES",
    "HIV_CANDIDATES",
    "fit_river",
    "gap_matrices",
    "STATIC_MODEL",
    "FLUX_FACTOR",
    "LOO_GTOL",
    "fd_gradient",
    "fd_hessian",
]
