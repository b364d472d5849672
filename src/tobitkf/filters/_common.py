"""Former home of the shared filter pieces, now in :mod:`tobitkf.filters.core` (re-exported here)."""

from .core import (
    FilterResult,
    check_keywords,
    check_prior,
    gain_update,
    predict,
    prepare_inputs,
    prepare_measurements,
    process_roots,
    psd_sqrt,
    sqrt_predict,
    sqrt_update,
    symmetrize,
)

__all__ = [
    "FilterResult",
    "check_keywords",
    "check_prior",
    "gain_update",
    "predict",
    "prepare_inputs",
    "prepare_measurements",
    "process_roots",
    "psd_sqrt",
    "sqrt_predict",
    "sqrt_update",
    "symmetrize",
]
