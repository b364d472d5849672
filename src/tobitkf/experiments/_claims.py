r"""The claims rule: how every experiment states a source's claim and judges it.

One rule for every experiment, so that a verdict means the same thing everywhere:

1. **A claim states what is measured and how it is judged.** Every claim carries

   * ``claim``: the source's statement, with its own figure, equation or section number
     (or "(not in the source)" for a statement of ours);
   * ``quantity``: the number (or numbers) measured, in words;
   * ``measured``: the measured value(s);
   * ``test``: the comparison that decides the verdict, e.g. ``|q - 0.05| <= tol``;
   * ``tolerance``: the value of ``tol`` and where it comes from;
   * ``holds``: ``True`` (held), ``False`` (not held) or ``None`` (n/a).

   Whose claim it is (:func:`claim_origin`) decides what a failure means. A **source's claim**
   that our faithful implementation does not reproduce is a finding about the source (the
   claim's ``note`` or ``explanation`` says what we measured and why; ``docs/sources/`` lists the
   source's errors), not a defect of the package. A claim of **this package** ("(not in the
   source)", or any claim of an experiment whose source is tobitkf itself) that fails is a defect,
   or a limitation that its ``explanation`` states with the reason. An optional ``origin`` field
   (``"source"`` or ``"package"``) overrides the rule.

2. **The tolerance of a random quantity comes from its Monte Carlo error.** A Monte Carlo
   mean, RMSE or fraction has a standard error from the run count (:func:`jackknife_se` over the
   runs, :func:`mean_se`); the tolerance is ``K_SE`` = 3 standard errors. A deterministic
   quantity (a Riccati gain, an eigenvalue, an identity) has a numerical tolerance: half a unit
   of the source's last printed digit for a printed number, a rounding tolerance (``1e-9``
   relative or the like) for an exact identity.

3. **The direction of the tolerance follows the kind of claim.** A claimed *equality or bound*
   (``q = target``, ``q <= bound``) holds unless it is violated by more than the tolerance
   (:func:`close`, :func:`at_most`, :func:`at_least`). A claimed *difference or ordering*
   (``a < b``, "better than") holds only if the data show it beyond the tolerance
   (:func:`less`, :func:`greater`): a difference within the Monte Carlo error is not a shown
   difference, and is reported as not held.

4. **n/a only for what cannot be measured** (:func:`not_measurable`, with the reason: a figure
   we do not have, a quantity the source does not define). A measured claim is held or not
   held, never n/a.

Every registered experiment's claims are checked against this rule (:func:`check_claims`) when
the experiment returns; an experiment that breaks it raises :class:`ClaimError`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .._validation import ValidationError

__all__ = [
    "K_SE",
    "ClaimError",
    "claim",
    "close",
    "at_most",
    "at_least",
    "less",
    "greater",
    "not_measurable",
    "check_claim",
    "check_claims",
    "mean_se",
    "jackknife_se",
    "fmt",
    "mc_tolerance",
    "rmse_time_avg",
    "rmse_whole_run",
    "rmse_difference",
    "half_unit",
    "matches_print",
    "rmse_masked",
    "claim_origin",
    "ORIGINS",
]

K_SE = 3.0
"""Tolerance of a Monte Carlo quantity, in standard errors (two-sided, about 99.7 %)."""

REQUIRED = ("claim", "quantity", "measured", "test", "tolerance")
ORIGINS = ("source", "package")
"""Whose claim it is: a source's (a paper's) or this package's own."""
_OURS = "(not in the source"


def claim_origin(c: Any, source: str = "") -> str:
    """``"source"`` for a claim of the source, ``"package"`` for a claim of this package.

    A claim is the package's when its ``origin`` field says so, when its text begins with
    "(not in the source" (the claims rule's mark for a statement of ours), or when the
    experiment's ``source`` is tobitkf itself (begins with "tobitkf"); any other claim is the
    source's. ``c`` is a claim dict (anything else is taken as the source's claim).
    """
    if not isinstance(c, dict):
        return "source"
    origin = c.get("origin")
    if origin in ORIGINS:
        return str(origin)
    text = str(c.get("claim") or "").lstrip().lower()
    if text.startswith(_OURS) or str(source or "").lstrip().lower().startswith("tobitkf"):
        return "package"
    return "source"


class ClaimError(ValidationError):
    """A claim that does not follow the claims rule (a missing field, a bad verdict)."""


def fmt(x: Any, digits: int = 4) -> str:
    """A number (or list of numbers) as short text, ``digits`` significant digits."""
    if x is None:
        return "none"
    if isinstance(x, (bool, np.bool_)):
        return str(bool(x))
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    arr = np.asarray(x, dtype=float)
    if arr.ndim == 0:
        v = float(arr)
        return f"{v:.{digits}g}" if np.isfinite(v) else str(v)
    return "[" + ", ".join(fmt(v, digits) for v in arr.ravel()) + "]"


def mean_se(samples: Any, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean over ``axis`` (the runs) and its standard error ``std(ddof=1) / sqrt(N)``."""
    s = np.asarray(samples, dtype=float)
    n = s.shape[axis]
    if n < 2:
        return s.mean(axis=axis), np.full(np.delete(s.shape, axis), np.inf)
    return s.mean(axis=axis), s.std(axis=axis, ddof=1) / np.sqrt(n)


def jackknife_se(per_run: Any, stat: Callable[[np.ndarray], Any]) -> np.ndarray:
    r"""Standard error of a statistic of the run average, by the jackknife over the runs.

    ``per_run`` is ``(N, ...)``: one term per run (e.g. squared errors ``(N, T, n)``); the
    statistic is ``stat(mean over runs)`` (e.g. ``lambda m: np.sqrt(m).mean(-2)`` for the
    time-averaged RMSE). ``stat`` must accept a leading batch axis: it is evaluated on the N
    leave-one-out means at once. Returns :math:`\sqrt{(N-1)/N\,\sum_i(\theta_{(i)} - \bar\theta)^2}`
    (``inf`` for fewer than 2 runs).
    """
    g = np.asarray(per_run, dtype=float)
    n = g.shape[0]
    if n < 2:
        return np.full(np.shape(stat(g.mean(axis=0, keepdims=True))[0]), np.inf)
    loo = (g.sum(axis=0, keepdims=True) - g) / (n - 1)
    theta = np.asarray(stat(loo), dtype=float)
    return np.sqrt((n - 1) / n * ((theta - theta.mean(axis=0)) ** 2).sum(axis=0))


def _err2(err: Any, skip: int) -> np.ndarray:
    e = np.asarray(err, dtype=float)
    if e.ndim == 2:
        e = e[..., None]
    return e[:, skip:] ** 2


def rmse_time_avg(err: Any, skip: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Time average of the per-step RMSE (the ``rmse_time_avg`` of :func:`tobitkf.metrics.summarize`)
    and its jackknife standard error. ``err`` is ``(N, T, n)`` (estimate − truth per run)."""
    e2 = _err2(err, skip)

    def stat(m):
        return np.sqrt(m).mean(axis=-2)

    return stat(e2.mean(axis=0)), jackknife_se(e2, stat)


def rmse_whole_run(err: Any, skip: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Whole-run RMSE, the root of the mean over runs *and* steps of the squared error, and its
    jackknife standard error (not the time-averaged per-step RMSE of :func:`rmse_time_avg`)."""
    e2 = _err2(err, skip)

    def stat(m):
        return np.sqrt(m.mean(axis=-2))

    return stat(e2.mean(axis=0)), jackknife_se(e2, stat)


def rmse_difference(err_a: Any, err_b: Any, skip: int = 0, whole_run: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``RMSE(b) − RMSE(a)`` per component (time-averaged per-step RMSE, or whole-run RMSE) on the
    same runs, and its jackknife standard error (paired: common random numbers cancel)."""
    g = np.stack([_err2(err_a, skip), _err2(err_b, skip)], axis=1)  # (N, 2, T, n)

    def stat(m):
        r = np.sqrt(m.mean(axis=-2)) if whole_run else np.sqrt(m).mean(axis=-2)
        return r[..., 1, :] - r[..., 0, :]

    return stat(g.mean(axis=0)), jackknife_se(g, stat)


def mc_tolerance(se: Any, runs: int, what: str = "") -> tuple[float, str]:
    """``K_SE`` standard errors and the sentence saying so."""
    tol = K_SE * float(np.max(se))
    return tol, f"{K_SE:g} standard errors of {what or 'the Monte Carlo estimate'} over {runs} runs = {fmt(tol, 3)}"


def _verdict(holds: Any) -> bool:
    if isinstance(holds, (bool, np.bool_)):
        return bool(holds)
    raise ClaimError(f"holds: a measured claim is held (True) or not held (False), got {holds!r}")


def claim(
    text: str,
    *,
    quantity: str,
    measured: Any,
    test: str,
    tolerance: str,
    holds: Any,
    note: str = "",
    explanation: str = "",
) -> dict[str, Any]:
    """A measured claim with an explicit test and tolerance (the general form)."""
    out = {
        "claim": text,
        "quantity": quantity,
        "measured": measured if isinstance(measured, str) else fmt(measured),
        "test": test,
        "tolerance": tolerance,
        "holds": _verdict(holds),
    }
    if note:
        out["note"] = note
    if explanation:
        out["explanation"] = explanation
    return check_claim(out)


def close(
    text: str,
    *,
    quantity: str,
    value: Any,
    target: Any,
    tol: float,
    tolerance: str,
    note: str = "",
    explanation: str = "",
    digits: int = 4,
) -> dict[str, Any]:
    """Claimed equality: holds iff every ``|value - target| <= tol``."""
    v, t = np.asarray(value, dtype=float), np.asarray(target, dtype=float)
    dev = float(np.max(np.abs(v - t)))
    return claim(
        text,
        quantity=quantity,
        measured=f"{fmt(v, digits)} (target {fmt(t, digits)}; deviation {fmt(dev, 3)})",
        test="|quantity - target| <= tol",
        tolerance=tolerance,
        holds=bool(dev <= tol),
        note=note,
        explanation=explanation,
    )


def at_most(text: str, *, value: Any, bound: Any, tol: float, **fields: Any) -> dict[str, Any]:
    """Claimed upper bound: holds iff every ``value <= bound + tol``; ``fields`` as :func:`_bound`."""
    return _bound(text, value, bound, tol, upper=True, **fields)


def at_least(text: str, *, value: Any, bound: Any, tol: float, **fields: Any) -> dict[str, Any]:
    """Claimed lower bound: holds iff every ``value >= bound - tol``; ``fields`` as :func:`_bound`."""
    return _bound(text, value, bound, tol, upper=False, **fields)


def _bound(
    text: str,
    value: Any,
    bound: Any,
    tol: float,
    *,
    upper: bool,
    quantity: str,
    tolerance: str,
    note: str = "",
    explanation: str = "",
    digits: int = 4,
) -> dict[str, Any]:
    """A claimed bound on ``value`` (upper: ``value <= bound + tol``, else ``value >= bound - tol``), every entry."""
    v, b = np.asarray(value, dtype=float), np.asarray(bound, dtype=float)
    return claim(
        text,
        quantity=quantity,
        measured=f"{fmt(v, digits)} (bound {fmt(b, digits)})",
        test="quantity <= bound + tol" if upper else "quantity >= bound - tol",
        tolerance=tolerance,
        holds=bool(np.all(v <= b + tol) if upper else np.all(v >= b - tol)),
        note=note,
        explanation=explanation,
    )


def less(
    text: str,
    *,
    quantity: str,
    a: Any,
    b: Any,
    tol: float | np.ndarray,
    tolerance: str,
    names: tuple[str, str] = ("a", "b"),
    note: str = "",
    explanation: str = "",
    digits: int = 4,
) -> dict[str, Any]:
    """Claimed ordering ``a < b``: holds iff every ``b - a > tol`` (shown beyond the tolerance)."""
    av, bv = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    margin = bv - av
    return claim(
        text,
        quantity=quantity,
        measured=f"{names[0]} {fmt(av, digits)}, {names[1]} {fmt(bv, digits)} (margin {names[1]} - "
        f"{names[0]} = {fmt(margin, 3)})",
        test=f"{names[1]} - {names[0]} > tol",
        tolerance=tolerance,
        holds=bool(np.all(margin > tol)),
        note=note,
        explanation=explanation,
    )


def greater(text: str, *, a: Any, b: Any, names: tuple[str, str] = ("a", "b"), **fields: Any) -> dict[str, Any]:
    """Claimed ordering ``a > b``: holds iff every ``a - b > tol``; :func:`less` with the two sides swapped
    (``fields`` as there)."""
    return less(text, a=b, b=a, names=(names[1], names[0]), **fields)


def half_unit(printed: str) -> float:
    """Half a unit of the last printed digit of a number as printed (``"73.1575"`` -> 5e-5,
    ``".305"`` -> 5e-4, ``"2.3025E-10"`` -> 5e-15)."""
    text = printed.strip().replace(" ", "").replace("−", "-")
    mant, _, exp = text.upper().partition("E")
    decimals = len(mant.split(".")[1]) if "." in mant else 0
    return 0.5 * 10.0 ** (-decimals + (int(exp) if exp else 0))


def matches_print(
    text: str, *, quantity: str, value: Any, printed: list[str], note: str = "", explanation: str = "", digits: int = 8
) -> dict[str, Any]:
    """Claimed printed numbers: holds iff every value rounds to its printed digits
    (``|value - printed| <= half a unit of the last printed digit``)."""
    v = np.atleast_1d(np.asarray(value, dtype=float))
    want = np.array([float(p.replace("−", "-").replace(" ", "")) for p in printed])
    tol = np.array([half_unit(p) for p in printed])
    ok = np.abs(v - want) <= tol * (1 + 1e-9)
    return claim(
        text,
        quantity=quantity,
        measured=f"{fmt(v, digits)} (printed [{', '.join(printed)}])",
        test="|computed - printed| <= half a unit of the last printed digit, every entry",
        tolerance="per entry: " + ", ".join(fmt(t, 1) for t in tol),
        holds=bool(ok.all()),
        note=note,
        explanation=explanation,
    )


def rmse_masked(err: Any, mask: Any) -> tuple[float, float]:
    """RMSE over the samples selected by ``mask`` (``(N, T)``, pooled over runs) and its jackknife
    standard error over the runs. ``err`` is ``(N, T)``."""
    e, m = np.asarray(err, dtype=float), np.asarray(mask, dtype=bool)
    g = np.stack([np.where(m, e**2, 0.0).sum(axis=1), m.sum(axis=1).astype(float)], axis=-1)  # (N, 2)

    def stat(mm):
        return np.sqrt(mm[..., 0] / np.maximum(mm[..., 1], 1e-300))

    return float(stat(g.mean(axis=0))), float(jackknife_se(g, stat))


def not_measurable(text: str, *, reason: str, note: str = "") -> dict[str, Any]:
    """A claim that cannot be measured here (n/a), with the reason."""
    out = {
        "claim": text,
        "quantity": "none (not measurable)",
        "measured": "not measurable: " + reason,
        "test": "none",
        "tolerance": "none",
        "holds": None,
        "not_measurable": reason,
    }
    if note:
        out["note"] = note
    return check_claim(out)


def check_claim(c: Any) -> dict[str, Any]:
    """Check one claim against the rule; returns it unchanged or raises :class:`ClaimError`."""
    if not isinstance(c, dict):
        raise ClaimError(f"claim: expected a dict, got {type(c).__name__}")
    for key in REQUIRED:
        if not isinstance(c.get(key), str) or not c[key].strip():
            raise ClaimError(f"claim {c.get('claim')!r}: the field {key!r} is missing or empty (claims rule 1)")
    holds = c.get("holds", "missing")
    if holds is None:
        if not str(c.get("not_measurable", "")).strip():
            raise ClaimError(f"claim {c['claim']!r}: n/a needs the reason it cannot be measured (claims rule 4)")
    elif not isinstance(holds, bool):
        raise ClaimError(f"claim {c['claim']!r}: holds must be True, False or None, got {holds!r}")
    elif c.get("not_measurable"):
        raise ClaimError(f"claim {c['claim']!r}: a measured claim cannot also be 'not measurable'")
    if "origin" in c and c["origin"] not in ORIGINS:
        raise ClaimError(f"claim {c['claim']!r}: origin must be one of {ORIGINS}, got {c['origin']!r}")
    return c


def check_claims(claims: Any, exp_id: str = "") -> list[dict[str, Any]]:
    """Check every claim of an experiment (:func:`check_claim`), naming the experiment on failure."""
    if not isinstance(claims, list):
        raise ClaimError(f"{exp_id}: claims must be a list, got {type(claims).__name__}")
    for i, c in enumerate(claims, start=1):
        try:
            check_claim(c)
        except ClaimError as exc:
            raise ClaimError(f"{exp_id} claim {i}: {exc}") from None
    return claims
