"""The two packers of the compiled loop's arguments and the shared compiled square roots.

:class:`~tobitkf.filters._loop_specs.LoopArguments` (Python) and
:func:`~tobitkf.filters._compiled_entries.loop_call` (compiled) name the arguments of
:func:`~tobitkf.filters._compiled_loop.compiled_loop` once each: a change of the loop's signature that one of
them does not follow would hand the loop its arrays in the wrong places.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest

pytest.importorskip("numba")


def _loop_parameters() -> list[str]:
    from tobitkf.filters._compiled_loop import compiled_loop

    return list(inspect.signature(compiled_loop.py_func).parameters)


def test_python_packer_fields_are_the_loop_parameters_in_order():
    from tobitkf.filters._loop_specs import LoopArguments

    assert list(LoopArguments._fields) == _loop_parameters()


def test_compiled_packer_takes_every_loop_parameter_by_name():
    from tobitkf.filters._compiled_entries import loop_call

    assert sorted(inspect.signature(loop_call.py_func).parameters) == sorted(_loop_parameters())


def test_filled_arguments_are_what_the_loop_reads_as_absent():
    """The made arrays: writable, C-contiguous, float64 (``cls`` int8), with a T axis of length 0 for the outputs
    (not written) and the family's own arrays untouched."""
    from tobitkf.filters._compiled_moments import kind
    from tobitkf.filters._loop_specs import LoopArguments

    N, T, m, n = 3, 5, 2, 4
    y, A, x0 = np.zeros((N, T, m)), np.zeros((1, 1, n, n)), np.zeros((N, n))
    means = np.zeros((N, T, n))
    args = LoopArguments(kind(7), y, A=A, Qd=A, H=np.zeros((1, m, n)), x0=x0, P0=np.zeros((1, n, n)), means=means,
                         x_last=x0, P_last=np.zeros((N, n, n))).filled()  # fmt: skip
    assert args.means is means and args.y is y
    assert (args.J, args.npass, args.noise_code, args.joseph) == (0, 1, 0, False)
    assert args.cls.shape == (N, 0, m) and args.cls.dtype == np.int8
    assert args.covs.shape == (N, 0, n, n) and args.comp.shape == (N, 0, m, 0) and args.ll.shape == (N, 0)
    assert args.F.shape == (1, m, 0, n) and args.par.shape == (1, m, 0) and args.bu.shape == (N, 0, n)
    for a in args:
        if isinstance(a, np.ndarray):
            assert a.flags.c_contiguous and a.flags.writeable


@pytest.mark.parametrize("n", [1, 3, 5])
def test_psd_root_of_definite_and_singular_matrices(n):
    """LL^T = M: the Cholesky factor (lower triangular) of a definite M, an eigen root of a singular one, as
    :func:`tobitkf._linalg.psd_sqrt`; ``cholesky_lower`` says which."""
    from tobitkf._compiled_linalg import cholesky_lower, psd_root

    rng = np.random.default_rng(n)
    B = rng.normal(size=(n, n))
    definite = B @ B.T + 0.1 * np.eye(n)
    singular = np.ones((n, n))  # rank one: the second pivot is exactly 1 - 1 = 0
    L = np.empty((n, n))
    assert cholesky_lower(definite, L)
    np.testing.assert_allclose(L, np.linalg.cholesky(definite), rtol=0, atol=1e-12)
    psd_root(definite, L)
    np.testing.assert_allclose(L, np.linalg.cholesky(definite), rtol=0, atol=1e-12)
    if n > 1:
        assert not cholesky_lower(singular, L)
    psd_root(singular, L)
    np.testing.assert_allclose(L @ L.T, singular, rtol=0, atol=1e-12)
