"""The package's censored-series type (:class:`CensoredSeries`), in a module of its own so that both the
data loaders (:mod:`tobitkf.data`) and the readers (:mod:`tobitkf.data.readers`) build on it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["CensoredSeries"]


@dataclass(frozen=True)
class CensoredSeries:
    r"""One censored scalar time series as recorded.

    Attributes
    ----------
    name : str
        Short name of the data set.
    y : (T,) ndarray
        Readings; a censored reading holds its limit, an interval reading a value strictly inside its
        interval (the readers write the midpoint; it is not used); NaN marks a missing reading.
    censored : (T,) bool ndarray
        The censoring indicator recorded with the data (False for missing readings).
    lower, upper : (T,) ndarray
        Censoring limits of each reading (``-inf`` / ``+inf``: no limit on that side). A reading is
        left-censored when it is flagged and at ``lower`` (its value at most ``lower``), right-censored when
        flagged and at ``upper``, and an *interval* reading when flagged and strictly between two finite
        limits (its value known only to lie in ``[lower, upper]``; :attr:`interval`).
    covariates : dict of str to (T,) ndarray
        Known regressors (e.g. ``"lQ"``, the log discharge).
    time : (T,) ndarray of str
        Time labels as recorded.
    description : str
        One line on what the series is.
    times : (T,) ndarray of datetime64 or float, or None
        When each reading was taken (``datetime64[D]`` calendar dates for the dated records), where the
        record has them.
    """

    name: str
    y: np.ndarray
    censored: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    covariates: dict[str, np.ndarray] = field(default_factory=dict)
    time: np.ndarray | None = None
    description: str = ""
    times: np.ndarray | None = None

    @property
    def steps(self) -> int:
        """Number of readings T."""
        return int(self.y.shape[0])

    @property
    def interval(self) -> np.ndarray:
        """(T,) bool: interval readings, flagged censored and strictly between two finite limits."""
        with np.errstate(invalid="ignore"):
            inside = (self.y > self.lower) & (self.y < self.upper) & np.isfinite(self.lower) & np.isfinite(self.upper)
            return np.asarray(self.censored, dtype=bool) & inside

    @property
    def missing(self) -> np.ndarray:
        """(T,) bool: readings that are missing."""
        return np.isnan(self.y)

    def censoring(self):
        """The limits as a :class:`~tobitkf.Censoring` of one channel, ``(T, 1)``."""
        from ..channels.censoring import Censoring

        return Censoring(lower=self.lower[:, None], upper=self.upper[:, None])

    def design(self, *names: str, intercept: bool = True) -> np.ndarray:
        """The regressor matrix ``(T, l)``: a column of ones (when ``intercept``) and the named covariates."""
        cols = [np.ones(self.steps)] if intercept else []
        for nm in names:
            if nm not in self.covariates:
                from .._validation import ValidationError

                raise ValidationError(f"names: unknown covariate {nm!r}; known: {', '.join(self.covariates) or 'none'}")
            cols.append(self.covariates[nm])
        return np.column_stack(cols) if cols else np.zeros((self.steps, 0))
