"""What a ``filter`` call asks to record: the output names, their parsing, and the memory check before the loop
allocates them (for the shared loop of :mod:`tobitkf.filters.core` and the compiled paths alike)."""

from __future__ import annotations

from typing import Any

from .._progress import plural
from .._validation import ValidationError, check_memory

__all__ = ["OUTPUTS", "parse_outputs", "check_output_memory"]

#: the names ``outputs`` may list
OUTPUTS = ("mean", "cov", "var", "pred_mean", "pred_cov", "extras")


def parse_outputs(outputs: Any) -> frozenset[str]:
    """The per-step outputs a ``filter`` call records: ``"all"`` (default: mean, cov, pred_mean,
    pred_cov, extras), ``"last"`` (only the final state), or names from :data:`OUTPUTS`."""
    if outputs is None or (isinstance(outputs, str) and outputs == "all"):
        return frozenset(("mean", "cov", "pred_mean", "pred_cov", "extras"))
    if isinstance(outputs, str) and outputs == "last":
        return frozenset()
    if isinstance(outputs, str):
        names: tuple[Any, ...] = (outputs,)
    else:
        try:
            names = tuple(outputs)
        except TypeError:
            raise ValidationError(
                f"outputs: expected 'all', 'last', a name or a list of names from {', '.join(OUTPUTS)}, got "
                f"{outputs!r} ({type(outputs).__name__})"
            ) from None
    bad = [o for o in names if not isinstance(o, str) or o not in OUTPUTS]
    if bad:
        raise ValidationError(f"outputs: expected 'all', 'last' or names from {', '.join(OUTPUTS)}, got {bad[0]!r}")
    return frozenset(names)


_OUTPUT_SIZES = {"mean": 1, "pred_mean": 1, "var": 1, "cov": 2, "pred_cov": 2}


def check_output_memory(want: frozenset[str], N: int, T: int, n: int, name: str) -> None:
    """Refuse, before the loop allocates them, outputs that cannot fit in memory (``name``: the readings)."""
    per = sum(n ** _OUTPUT_SIZES[key] for key in want if key in _OUTPUT_SIZES)
    if per:
        check_memory(
            8 * N * T * per,
            name,
            f"the outputs ({', '.join(sorted(want & set(_OUTPUT_SIZES)))}) of {plural(N, 'run')} x {plural(T, 'step')}",
        )
