"""The particle filter's source of random numbers: a seed turned into a generator state, and back.

One place for the numpy path (:mod:`tobitkf.filters.particle`) and the compiled loop
(:mod:`tobitkf.filters._compiled_particle`): the state of the ``numpy.random`` bit generator travels
in the filter's :class:`~tobitkf.filters.core.FilterState` (a plain dict, so a pickled state resumes
with the same draws), and both paths rebuild the same ``numpy.random.Generator`` from it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .._validation import ValidationError

__all__ = ["rng_state", "generator"]


def rng_state(seed: Any) -> dict:
    """The bit generator's state (a dict) for ``seed``: an int, a ``SeedSequence``, a ``Generator`` (its
    current state) or None (fresh entropy, drawn now).

    Raises
    ------
    ValidationError
        A seed of another type (a bool, a string, a negative int...).
    """
    if isinstance(seed, np.random.Generator):
        return dict(seed.bit_generator.state)
    if isinstance(seed, bool):
        raise ValidationError(f"seed: expected an int, SeedSequence, Generator or None, got {seed!r}")
    try:
        ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    except (TypeError, ValueError) as exc:
        raise ValidationError(f"seed: expected an int, SeedSequence, Generator or None, got {seed!r} ({exc})") from None
    return dict(np.random.PCG64(ss).state)


def generator(state: dict) -> np.random.Generator:
    """A ``numpy.random.Generator`` restored from a bit generator's ``state`` (as :func:`rng_state` gives)."""
    bg = getattr(np.random, state["bit_generator"])()
    bg.state = state
    return np.random.Generator(bg)
