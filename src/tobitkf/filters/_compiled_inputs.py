"""The known inputs of a compiled nonlinear loop (:mod:`tobitkf.filters._compiled_nonlinear_loop`): which of the model's
functions take them, and the rows of the runs still taking part in an assumed-density update."""

from __future__ import annotations

import numpy as np
from numba import types
from numba.extending import overload

__all__ = ["active_inputs"]


def active_inputs(u, r0, nb, t, rows, U, act):  # pragma: no cover - compiled only (its overload below)
    """The inputs of the runs r0 + b (b < nb) with ``act[b]`` at step t, each repeated for its ``rows`` points and
    stacked in order in ``U`` (as the points of those runs are stacked); None without inputs."""


@overload(active_inputs)
def _active_inputs_overload(u, r0, nb, t, rows, U, act):
    if isinstance(u, types.NoneType):
        return lambda u, r0, nb, t, rows, U, act: None

    def rows_of(u, r0, nb, t, rows, U, act):
        q = 0
        for b in range(nb):
            if not act[b]:
                continue
            for i in range(rows):
                U[q * rows + i] = u[r0 + b, t]
            q += 1
        return U[: q * rows]

    return rows_of


def _model_inputs(system, u2, N: int, T: int):
    """``(uf, uh)``: the inputs (N, T, p) of ``f`` and of ``h`` (None for a function that takes none; zeros when
    the function takes one and none is given, :math:`u = 0` as on the numpy path), C-contiguous and writable."""
    if system.p is None:
        return None, None
    u = np.zeros((N, T, system.p)) if u2 is None else np.require(u2, dtype=float, requirements=("C", "W"))
    return (u if system.f_takes_input else None), (u if system.h_takes_input else None)
