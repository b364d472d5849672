"""Small matplotlib helpers shared by the experiments' figure functions."""

from __future__ import annotations

import contextlib
import contextvars
from pathlib import Path
from typing import Any

import numpy as np

from ._extras import require

__all__ = ["new_figure", "save", "plot_rmse_over_time", "ESTIMATOR_STYLE", "record_caption", "collect_captions"]

_CAPTIONS: contextvars.ContextVar[dict[str, str] | None] = contextvars.ContextVar("figure_captions", default=None)


def record_caption(name: str, caption: str) -> None:
    """Record the caption of figure ``name`` for the enclosing :func:`collect_captions` (if any)."""
    captions = _CAPTIONS.get()
    if captions is not None:
        captions[name] = " ".join(caption.split())


@contextlib.contextmanager
def collect_captions():
    """Collect the captions :func:`save` records inside the block: ``with collect_captions() as c: ...``."""
    captions: dict[str, str] = {}
    token = _CAPTIONS.set(captions)
    try:
        yield captions
    finally:
        _CAPTIONS.reset(token)


ESTIMATOR_STYLE: dict[str, dict[str, Any]] = {
    "truth": {"color": "black", "lw": 1.2, "label": "truth"},
    "kf": {"color": "tab:blue", "lw": 1.0, "ls": "--", "label": "standard KF (censored values as data)"},
    "ikf": {"color": "tab:orange", "lw": 1.0, "ls": "-.", "label": "intermittent-measurements KF (drops censored)"},
    "tkf": {"color": "tab:red", "lw": 1.2, "label": "Tobit KF"},
    "sstkf": {"color": "tab:green", "lw": 1.2, "label": "steady-state TKF"},
}


def new_figure(rows: int = 1, cols: int = 1, *, width: float = 7.0, height: float = 3.0, **kw):
    """A figure with ``rows x cols`` axes (always a 2-D array of axes)."""
    plt = require("matplotlib.pyplot", extra="plot")

    fig, axes = plt.subplots(rows, cols, figsize=(width, height * rows), squeeze=False, **kw)
    return fig, axes


def save(fig, outdir: Path, name: str, *, caption: str = "", dpi: float = 110, tight: bool = True) -> Path:
    """Save ``fig`` as ``outdir/name`` atomically (after ``tight_layout`` unless ``tight=False``) and close it.

    ``caption`` says what the figure shows (which source figure it reproduces, what each curve is);
    inside a registered experiment's ``plot`` it is recorded for the report.
    """
    plt = require("matplotlib.pyplot", extra="plot")

    from ._io import atomic_savefig

    if caption:
        record_caption(name, caption)

    if tight:
        fig.tight_layout()
    path = atomic_savefig(fig, Path(outdir) / name, dpi=dpi)
    plt.close(fig)
    return path


def style(key: str) -> dict[str, Any]:
    """Plot style of an estimator key (falls back to a plain labelled line)."""
    base = key.split("-")[0] if key not in ESTIMATOR_STYLE else key
    st = dict(ESTIMATOR_STYLE.get(base, {"lw": 1.0}))
    st["label"] = st.get("label", key) if key in ESTIMATOR_STYLE else key
    return st


def plot_rmse_over_time(
    ax, estimators: dict[str, dict[str, Any]], component: int, *, title: str = "", log: bool = False
) -> None:
    """Per-step RMSE of one state component for each estimator."""
    for key, summ in estimators.items():
        r = np.asarray(summ["rmse"])[:, component]
        ax.plot(np.arange(1, r.size + 1), r, **style(key))
    ax.set_xlabel("k")
    ax.set_ylabel(f"RMSE of x{component + 1}")
    if log:
        ax.set_yscale("log")
    if title:
        ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
