"""Each family's version of the one compiled loop holds its own update alone.

The loop (:func:`tobitkf.filters._compiled_loop.compiled_loop`) is compiled once per family: the family arrives as a
kind (:func:`tobitkf.filters._compiled_moments.kind`, a tuple whose length is the update code), numba reads the
length as a constant before typing and prunes the other families' branches. Compiled with a run-time code instead,
every version held every family's update (the Kalman filter's took minutes to compile). The assumed-density moments
(:func:`~tobitkf.filters._compiled_moments.family_block`, called by the linear loop and by the nonlinear filters'
loop) are chosen the same way. These tests run numba's own front end and its branch pruning on the functions'
source (no compilation: about a second) and check which compiled functions each family's version still calls.
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
    cl.TOBIT: "tobit_stats_block",
    cl.PROTOCOL_TKF: "_protocol_tkf_update",
    cl.FIXED_GAIN: "_fixed_gain_means",
    cl.FADING: "fading_lower_block",
    **{code: "_channel_updates" for code in (*cm.FAMILIES.values(), cm.BLOCK)},
}


def _called(code: int, fn=cl.compiled_loop, at: int = 0) -> set[str]:
    """The globals the version of the compiled function ``fn`` (whose argument ``at`` is the kind, the others typed
    None) for ``code`` names after numba's constant rewrite and branch pruning (the steps of its untyped pipeline
    that run before typing)."""
    fir = run_frontend(fn.py_func)
    args = [types.none] * fn.py_func.__code__.co_argcount
    args[at] = typeof(cm.kind(code))
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


def test_a_kind_of_no_update_is_refused():
    """A kind beyond the codes keeps the loop's error branch (it raises when run); the families' versions do not."""
    assert "ValueError" in _called(max(cl.CODES) + 1)
    assert not any("ValueError" in _called(code) for code in cl.CODES)


def test_the_kalman_filter_version_has_no_assumed_density_code():
    """The case that cost most: the KF's version named the assumed-density moments (``_channel_updates`` and,
    through it, every family's block function) although the KF never calls them."""
    called = _called(cl.KALMAN)
    assert "_channel_updates" not in called and "_shared_gain_means" in called


def test_a_family_code_becomes_its_kind():
    """The kinds: a tuple per code, of length the code, one numba type per code; the arguments of a call from
    Python must carry the kind, not the integer (which the loop no longer turns into a kind)."""
    from tobitkf.filters._loop_specs import LoopArguments

    assert len(set(cl.CODES)) == len(cl.CODES) and max(*cm.FAMILIES.values(), cm.BLOCK) < cl.KALMAN
    assert len({typeof(cm.kind(code)) for code in cl.CODES}) == len(cl.CODES)
    for code in cl.CODES:
        k = cm.kind(code)
        assert len(k) == code and len(typeof(k)) == code
    assert cl.KALMAN_KIND == cm.kind(cl.KALMAN) and cl.FADING_KIND == cm.kind(cl.FADING)
    assert cl.FIXED_GAIN_KIND == cm.kind(cl.FIXED_GAIN) and cl.PROTOCOL_TKF_KIND == cm.kind(cl.PROTOCOL_TKF)
    N, T, m, n = 2, 3, 1, 2
    y, A, x0 = np.zeros((N, T, m)), np.zeros((1, 1, n, n)), np.zeros((N, n))
    kw = dict(A=A, Qd=A, H=np.zeros((1, m, n)), x0=x0, P0=np.zeros((1, n, n)), x_last=x0, P_last=np.zeros((N, n, n)))
    assert LoopArguments(cl.TOBIT_KIND, y, **kw).filled().family == cm.kind(cl.TOBIT)
    with pytest.raises(TypeError, match="expected a kind"):
        LoopArguments(cl.TOBIT, y, **kw).filled()


#: the block function of each assumed-density family
BLOCKS = {
    cm.CENSORED: "censored_block",
    cm.SATURATION: "saturation_block",
    cm.PROTOCOL: "protocol_block",
    cm.BLOCK: "call_block",  # a channel's own block, named by the handle's type
}


@pytest.mark.parametrize("code", sorted(BLOCKS))
def test_each_family_moments_call_their_own_block_only(code):
    """:func:`~tobitkf.filters._compiled_moments.family_block` for a family's kind names that family's block
    function and no other's (and no error branch): the linear loop's and the nonlinear filters' assumed-density
    update compile one family's moments each."""
    called = _called(code, cm.family_block)
    assert BLOCKS[code] in called
    assert not (set(BLOCKS.values()) - {BLOCKS[code]}) & called
    assert "ValueError" not in called
    assert set(BLOCKS.values()) - {"call_block"} == set(cm.FAMILIES), "every block function is a family of the registry"


def test_a_kind_of_no_family_is_refused():
    """A kind of no assumed-density family keeps the error branch alone (it raises when run)."""
    called = _called(cl.KALMAN, cm.family_block)
    assert "ValueError" in called and not set(BLOCKS.values()) & called


def test_nonlinear_filters_pass_their_family_as_a_kind():
    """The nonlinear filters' compiled loop is handed the channel's family as a kind (its assumed-density update
    then compiles that family's moments alone): censoring, a quantizer (its own block's kind), random saturation;
    the Kalman and Tobit filters, which read no moments, the censored kind."""
    import tobitkf as tk
    from tobitkf.filters._compiled_nonlinear_loop import channel_arrays

    def f(x, k):
        return x

    def h(x, k):
        return x[..., :1]

    sys_ = tk.NonlinearSystem(f, h, 0.1 * np.eye(2), [[0.2]], np.zeros(2), np.eye(2))
    cases = {
        cm.CENSORED: tk.NonlinearAssumedDensityFilter(sys_, tk.Censoring(lower=0.0)),
        cm.SATURATION: tk.SaturationNonlinearAssumedDensityFilter(sys_, tk.RandomSaturation([0.3], [0.7], level=[0.4])),
    }
    cases_kf = (tk.UnscentedKalmanFilter(sys_), tk.TobitUnscentedKalmanFilter(sys_, tk.Censoring(lower=0.0)))
    for code, est in cases.items():
        assert channel_arrays(est, 0, 3)[0] == cm.kind(code)
    quantized = channel_arrays(tk.NonlinearAssumedDensityFilter(sys_, tk.Quantizer(0.5)), 0, 3)[0]
    assert quantized == cm.block_kind(tk.Quantizer.compiled_block) and len(quantized) == cm.BLOCK
    for est in cases_kf:
        assert channel_arrays(est, 0, 3)[0] == cm.kind(cm.CENSORED)


def test_each_nonlinear_update_compiles_alone():
    """The nonlinear filters' loop (:func:`~tobitkf.filters._compiled_nonlinear_loop.nonlinear_loop`, compiled in
    every process: it is specialised on the user's functions) takes its update as a kind too: the Kalman and
    Tobit filters' versions hold the joint update and not the assumed-density one, the ADF's the reverse."""
    from tobitkf.filters import _compiled_nonlinear as nl
    from tobitkf.filters._compiled_nonlinear_loop import nonlinear_loop

    at = nonlinear_loop.py_func.__code__.co_varnames.index("code")
    for code in (nl.KALMAN, nl.TOBIT):
        called = _called(code, nonlinear_loop, at)
        assert "_update_joint" in called and not {"_adf_project", "_adf_channel_start"} & called
    called = _called(nl.ADF, nonlinear_loop, at)
    assert {"_adf_project", "_adf_channel_start"} <= called and "_update_joint" not in called
