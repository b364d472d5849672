"""A fake ``tobitkf reproduce`` output folder for the report tests (not collected by pytest).

Three experiments, written the way ``cli.run_experiment`` writes them (``atomic_write_json``
of numpy arrays, figures drawn with matplotlib): ``fake-alpha`` (top-level estimators,
claims that hold, fail and are unchecked, a ``<script>`` claim, all three provenances),
``fake-beta`` (estimators nested under ``scenarios``; alpha also has claims of the package itself:
held, failed with a stated limitation citing deviation IDs, failed with no reason) and ``fake-gamma`` (same source as
alpha, nothing but an id). ``build_fake_results`` returns what it wrote, so tests compare
the report with the input rather than with the report's own output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tobitkf._io import atomic_write_json

SOURCE_A = "Alpha & Beta 2020, Ch. <1>"
SOURCE_B = "Zeta 2019"
SCRIPT_CLAIM = "<script>alert('x')</script> the TKF is unbiased"
# deviation IDs in a package claim's explanation: three with an entry in docs/sources, one without
LIMITATION = "a stated limitation of the option (MB-09 to MB-11, LD-E3); MA-99 has no entry"
LINKED_IDS = ("MB-09", "MB-11", "LD-E3")
CAPTION_A1 = "Fig 3.1: one run of the three filters on censored readings & their mean over runs"

CLAIMS_ALPHA = [
    {
        "claim": "TKF RMSE below KF RMSE",
        "quantity": "time-averaged RMSE",
        "measured": "TKF 0.5 < KF 0.9",
        "test": "KF - TKF > tol",
        "tolerance": "3 standard errors = 0.02",
        "holds": True,
    },
    {
        "claim": "the IKF converges to the truth",
        "quantity": "final bias",
        "measured": "IKF bias 0.13 after 1000 steps",
        "test": "|bias| <= tol",
        "tolerance": "3 standard errors = 0.01",
        "holds": False,
        "explanation": "the source's Fig 3.1 shows the dropping filter's limit, not the truth",
    },
    {
        "claim": "Fig 3.7 matches",
        "quantity": "none (not measurable)",
        "measured": "not measurable: the figure has no axis scale",
        "test": "none",
        "tolerance": "none",
        "holds": None,
        "note": "no numbers in the source",
        "not_measurable": "the figure has no axis scale",
    },
    {
        "claim": SCRIPT_CLAIM,
        "quantity": "bias",
        "measured": "bias 0.2 | 4 s.e. = 0.01",
        "test": "|bias| <= tol",
        "tolerance": "0.01",
        "holds": False,
    },
    {
        "claim": "(not in the source) the ADF is within 1.02x of the optimum",
        "quantity": "RMSE / optimum",
        "measured": "1.004",
        "test": "ratio <= 1.02",
        "tolerance": "none beyond the target",
        "holds": True,
    },
    {
        "claim": "(not in the source) the total-variance TKF stays finite",
        "quantity": "largest RMSE",
        "measured": "RMSE 3e3",
        "test": "finite and below 10",
        "tolerance": "none",
        "holds": False,
        "explanation": LIMITATION,
    },
    {
        "claim": "(not in the source) the fit converges",
        "quantity": "optimiser status",
        "measured": "not converged",
        "test": "converged",
        "tolerance": "none",
        "holds": False,
    },
]
CLAIMS_BETA = [
    {
        "claim": "low limit: TKF best",
        "quantity": "RMSE",
        "measured": "0.1 < 0.3",
        "test": "b - a > tol",
        "tolerance": "0.05",
        "holds": True,
    },
    {
        "claim": "high limit: all filters agree",
        "quantity": "max difference",
        "measured": "max difference 1e-3",
        "test": "difference <= tol",
        "tolerance": "1e-2",
        "holds": True,
    },
]


def _png(path: Path, seed: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tobitkf._io import atomic_savefig

    fig, ax = plt.subplots(figsize=(7.0, 2.2))
    ax.plot(np.random.default_rng(seed).standard_normal(30).cumsum())
    ax.set_title(path.name, fontsize=9)
    atomic_savefig(fig, path, dpi=80)
    plt.close(fig)


def _summary(rng: np.random.Generator, steps: int, n: int, scale: float) -> dict:
    rmse = scale * (1.0 + rng.random((steps, n)))
    return {
        "rmse": rmse,
        "rmse_time_avg": rmse.mean(axis=0),
        "bias": rmse / 3,
        "bias_time_avg": (rmse / 3).mean(axis=0),
        "nees": np.full(steps, n + 0.25),
        "nees_time_avg": n + 0.25,
    }


def build_fake_results(root: Path) -> dict:
    """Write the fake folder under ``root``; return ``{id: metrics dict as written}``."""
    rng = np.random.default_rng(7)
    written: dict[str, dict] = {}

    alpha_figs = ["fig_a1.png", "fig+a2 (censored).png"]
    alpha = {
        "id": "fake-alpha",
        "title": "Alpha example: constant & oscillator",
        "source": SOURCE_A,
        "runs": 20,
        "seed": 3,
        "package_version": "0.1.0",
        "elapsed_seconds": 1.25,
        "settings": {
            "A": {"value": [[1.0, 0.1], [0.0, 1.0]], "provenance": "source", "note": ""},
            "sigma": {"value": 0.05, "provenance": "reconstructed", "note": "garbled in (3.45); spec A-3.6"},
            "steps": {"value": 400, "provenance": "default", "note": "horizon not stated"},
            "x0": {"value": 0.1, "provenance": "default", "note": ""},
        },
        "claims": CLAIMS_ALPHA,
        "figures": alpha_figs,
        "estimators": {"kf": _summary(rng, 12, 2, 1.0), "tkf": _summary(rng, 12, 2, 0.5)},
        "censored_fraction": 0.4,
        "figure_captions": {"fig_a1.png": CAPTION_A1},
        "report_tables": [
            {
                "title": "Table 9: printed and ours",
                "columns": ["row", "t = 1", "t = 2"],
                "rows": [["printed", 0.2156, 0.075], ["ours", 0.00933612, 0.0208]],
                "note": "not expected to agree",
            }
        ],
    }
    beta = {
        "id": "fake-beta",
        "title": "Beta example",
        "source": SOURCE_B,
        "runs": 10,
        "seed": 0,
        "settings": {"limit": {"value": [0.0, 1.5], "provenance": "source", "note": "two limits"}},
        "claims": CLAIMS_BETA,
        "figures": ["beta.png"],
        "scenarios": {
            "low": {
                "estimators": {
                    "kf": _summary(rng, 8, 1, 0.3),
                    "ikf": _summary(rng, 8, 1, 0.2),
                    "tkf": _summary(rng, 8, 1, 0.1),
                }
            },
            "high": {"estimators": {"kf": _summary(rng, 8, 1, 0.4), "tkf": _summary(rng, 8, 1, 0.45)}},
        },
    }
    gamma = {"id": "fake-gamma", "title": "Gamma (nothing measured)", "source": SOURCE_A}
    for metrics in (alpha, beta, gamma):
        outdir = root / metrics["id"]
        outdir.mkdir(parents=True, exist_ok=True)
        for i, name in enumerate(metrics.get("figures", [])):
            _png(outdir / name, i)
        atomic_write_json(outdir / "metrics.json", metrics)
        written[metrics["id"]] = metrics
    return written
