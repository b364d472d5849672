"""Deprecated module: the multi-target tracker moved to :mod:`tobitkf.filters.tracking`.
This alias will be removed in the next release."""

import warnings

from .filters.tracking import MultiTargetTracker, TrackResult, constant_velocity_pixel_model  # noqa: F401

warnings.warn("tobitkf.tracking is deprecated: import from tobitkf.filters.tracking", DeprecationWarning, stacklevel=2)
