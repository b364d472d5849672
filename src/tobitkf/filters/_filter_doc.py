"""The docstring of every estimator's ``filter``, written once and completed by each family.

:meth:`tobitkf.filters.core.Estimator.filter` is the one record filter; a family says what differs in three
class attributes, and :func:`document_filter` (called for every subclass of ``Estimator``) writes the
numpy-style docstring of that family's ``filter`` from them:

* ``_filter_doc``: the summary, naming the family's equations (required for a generated docstring);
* ``_filter_params``: the text of the family's own keywords (``censored``, ``keep_augmented``, ...) and of
  the shared ones it reads differently (a mapping ``name -> "type\\n    description"``);
* ``_filter_raises``: what else the family refuses (appended to the ``ValidationError`` entry).

The Parameters section follows the function's signature, so a keyword is documented exactly when it is
accepted. A family whose ``filter`` has a signature of its own writes the method (its own keywords, calling
``super().filter`` or the loop) without a docstring and gets the generated one; a ``filter`` with a docstring of
its own keeps it (the estimators whose record is not an ``(..., T, m)`` array: the tracker, the delay family).
"""

from __future__ import annotations

import inspect
import textwrap
import types
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["document_filter", "filter_docstring"]

#: the shared parameters' text (type line, then the description, indented by four spaces)
PARAMETERS: Mapping[str, str] = {
    "y": "(..., T, m) array_like\n    The readings y_1..y_T of each run; NaN = a missing reading (that step only predicts).",
    "u": "(T, p) or (..., T, p) array_like, optional\n"
    "    Control inputs (through ``Bu``, and ``D`` where the reading has a feed-through).",
    "x0": "array_like, optional\n    Override the prior mean of :math:`x_0`, ``(n,)`` or laid out like the batch ``(..., n)``.",
    "P0": "array_like, optional\n    Override the prior covariance, ``(n, n)`` or ``(..., n, n)``.",
    "outputs": 'str or sequence of str, default "all"\n'
    '    What is recorded per step: ``"all"``, ``"last"`` (only ``final``) or names from\n'
    "    ``mean, cov, var, pred_mean, pred_cov, extras``.",
    "state": "FilterState, optional\n"
    "    Continue from this state (e.g. ``result.final`` of an earlier record) instead of the prior; not with\n"
    "    ``x0``/``P0``.",
    "times": "(T,) array_like, optional\n"
    "    The sample times of the readings, for a :class:`~tobitkf.ContinuousLinearSystem` (each gap discretised\n"
    "    exactly; the prior at the first time).",
}

_RETURNS = """\
FilterResult
    Per step (rows ``times``, the time index k of each reading): ``mean`` (..., T, n) and ``cov``
    (..., T, n, n) of the filtered state, ``var`` (..., T, n) its variances, ``pred_mean`` and ``pred_cov``
    the predictions, ``extras`` the family's per-step quantities; ``final`` the state after the last
    reading (pass it as ``state`` to continue). What ``outputs`` leaves out is None."""

_RAISES = (
    "A non-finite reading the family cannot take, an unknown name in ``outputs``, both ``state`` and ``x0``/``P0``,"
    " a predicted ``state`` (from ``predict``) or one of another estimator"
)


def filter_docstring(cls: type, fn: Callable[..., Any]) -> str:
    """The docstring of ``cls``'s ``filter`` ``fn``: the family's summary, then Parameters (one entry per
    parameter of ``fn``'s signature: the family's text, else the shared one), Returns and Raises.

    Raises
    ------
    TypeError
        ``cls`` has no ``_filter_doc``, or a parameter of ``fn`` has no text (neither the family's nor a
        shared one): raised when the class is defined.
    """
    doc = getattr(cls, "_filter_doc", None)
    if not doc:
        raise TypeError(f"{cls.__qualname__}.filter: give the class a _filter_doc (its summary) or a docstring")
    own: Mapping[str, str] = getattr(cls, "_filter_params", {})
    entries = []
    names = list(inspect.signature(fn).parameters)[1:]  # after self
    for name in names:
        text = own.get(name, PARAMETERS.get(name))
        if text is None:
            raise TypeError(f"{cls.__qualname__}.filter: parameter {name!r} has no text in _filter_params")
        entries.append(f"{name} : {text}")
    extra = getattr(cls, "_filter_raises", "")
    refused = textwrap.fill(
        _RAISES + (f"; {extra}." if extra else "."), 108, initial_indent="    ", subsequent_indent="    "
    )
    inputs = "``y`` or ``u``" if "u" in names else "``y``"
    raises = f"ShapeError\n    Malformed {inputs}, a prior of the wrong shape, or a ``state`` of another batch.\n"
    raises += f"ValidationError\n{refused}"
    params = "\n".join(entries)
    return f"{inspect.cleandoc(doc)}\n\nParameters\n----------\n{params}\n\nReturns\n-------\n{_RETURNS}\n\nRaises\n------\n{raises}\n"


def document_filter(cls: type) -> None:
    """Give ``cls`` its ``filter`` docstring: for a ``filter`` of its own without a docstring, and for an
    inherited one when ``cls`` has a ``_filter_doc`` of its own (then a copy of the inherited function, the
    same code and defaults, takes this family's text). Anything else is left as it is."""
    own = cls.__dict__
    fn = own.get("filter")
    if fn is None:
        if "_filter_doc" not in own or not callable(getattr(cls, "filter", None)):
            return
        base = cls.filter  # type: ignore[attr-defined]
        fn = types.FunctionType(base.__code__, base.__globals__, "filter", base.__defaults__, base.__closure__)
        fn.__kwdefaults__ = base.__kwdefaults__
        fn.__annotations__ = dict(base.__annotations__)
        fn.__qualname__ = f"{cls.__qualname__}.filter"
        fn.__module__ = cls.__module__
        type.__setattr__(cls, "filter", fn)
    elif not isinstance(fn, types.FunctionType) or fn.__doc__:
        return
    fn.__doc__ = filter_docstring(cls, fn)
