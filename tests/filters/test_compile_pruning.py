"""Each family's version of the one compiled loop holds its own update alone.

The loop (:func:`tobitkf.filters._compiled_loop.compiled_loop`) is compiled once per family: the family arrives as a
kind (:func:`tobitkf.filters._compiled_moments.kind`, a tuple whose length is the update code), numba reads the
length as a constant before typing and prunes the other families' branches. Compiled with a run-time code instead,
every version held every family's update (the Kalman filter's took minutes to compile). These tests run numba's own
front end and its branch pruning on the loop's source (no compilation: about a second) and check which compiled
functions each family's version still calls.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("numba")

from numba import typeof  # noqa: E402
from numba.core import ir, types  # noqa: E402
from numba.core.analysis import dead_branch_prune, rewrite_semantic_constants  # noqa: E402
from numba.core.compiler import run_frontend  # noqa: E402

from tobitkf.filters import _compiled_loop as cl  # noqa: E402
from tobitkf.filters import _compiled_moments as cm  # noqa: E402

#: the update each family calls, and no other family does
OWN = {
    cl.KALMAN: "_kalman_moments",
    cl.TOBIT: "tobit_update_block",
    cl.PROTOCOL_TKF: "_protocol_tkf_update",
    cl.FIXED_GAIN: "_fixed_gain_means",
    cl.FADING: "fading_update_block",
    **{code: "_channel_updates" for code in cm.FAMILIES.values()},
}


def _called(code: int) -> set[str]:
    """The globals the loop's version for ``code`` names after numba's constant rewrite and branch pruning (the
    steps of its untyped pipeline that run before typing)."""
    fir = run_frontend(cl._kind_loop.py_func)
    args = [typeof(cm.kind(code))] + [types.none] * (cl._kind_loop.py_func.__code__.co_argcount - 1)
    rewrite_semantic_constants(fir, args)
    dead_branch_prune(fir, args)
    return {
        st.value.name
        for block in fir.blocks.values()
        for st in block.body
        if isinstance(st, ir.Assign) and isinstance(st.value, (ir.Global, ir.FreeVar))
    }


@pytest.mark.parametrize("code", cl.CODES)
def test_each_family_version_calls_its_own_update_only(code):
    called = _called(code)
    assert OWN[code] in called
    others = {name for c, name in OWN.items() if name != OWN[code]}
    assert not others & called, f"code {code} still calls {sorted(others & called)}"


def test_the_kalman_filter_version_has_no_assumed_density_code():
    """The case that cost most: the KF's version named the assumed-density moments (``_channel_updates`` and,
    through it, every family's block function) although the KF never calls them."""
    called = _called(cl.KALMAN)
    assert "_channel_updates" not in called and "_shared_gain_means" in called


def test_a_family_code_becomes_its_kind():
    """The kinds: a tuple per code, of length the code, one numba type from Python and in compiled code; the
    arguments of a call from Python carry the kind, not the integer."""
    from tobitkf.filters._loop_specs import LoopArguments

    assert len(set(cl.CODES)) == len(cl.CODES) and max(cm.FAMILIES.values()) < cl.KALMAN
    for code in cl.CODES:
        k = cm.kind(code)
        assert len(k) == code and cm.kind_code(typeof(k)) == code
    assert cl.KALMAN_KIND == cm.kind(cl.KALMAN) and cl.FADING_KIND == cm.kind(cl.FADING)
    N, T, m, n = 2, 3, 1, 2
    y, A, x0 = np.zeros((N, T, m)), np.zeros((1, 1, n, n)), np.zeros((N, n))
    args = LoopArguments(cl.TOBIT, y, A=A, Qd=A, H=np.zeros((1, m, n)), x0=x0, P0=np.zeros((1, n, n)),
                         x_last=x0, P_last=np.zeros((N, n, n))).filled()  # fmt: skip
    assert args.family == cm.kind(cl.TOBIT)
