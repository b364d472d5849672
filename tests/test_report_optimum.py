"""The report's "RMSE / optimum" column: shown for estimator blocks that carry ratio_to_optimum, absent otherwise."""

from __future__ import annotations

import json

from tobitkf.report import collect_results, write_report


def _write(folder, exp_id, estimators):
    (folder / exp_id).mkdir(parents=True)
    (folder / exp_id / "metrics.json").write_text(
        json.dumps({"id": exp_id, "title": exp_id, "source": "test", "estimators": estimators}), encoding="utf-8"
    )


def test_ratio_column_in_html_and_markdown(tmp_path):
    _write(
        tmp_path,
        "with-optimum",
        {
            "tkf": {"rmse_time_avg": [0.44, 0.61], "ratio_to_optimum": [1.0941, 1.0617]},
            "adf": {"rmse_time_avg": [0.41, 0.574], "ratio_to_optimum": [1.0003, 1.0006]},
            "pf": {"rmse_time_avg": [0.409, 0.5736], "ratio_to_optimum": [1.0, 1.0]},
        },
    )
    _write(tmp_path, "without", {"kf": {"rmse_time_avg": [0.5]}})
    reports = {r.id: r for r in collect_results(tmp_path)[0]}
    t = reports["with-optimum"].rmse_tables[0]
    assert t.has_ratio and t.ratio_text("tkf") == "1.094 / 1.062" and t.ratio_text("pf") == "1 / 1"
    assert not reports["without"].rmse_tables[0].has_ratio
    index, md = write_report(tmp_path)
    html = index.read_text(encoding="utf-8")
    assert html.count("RMSE / optimum</th>") == 1 and "1.094 / 1.062" in html
    text = md.read_text(encoding="utf-8")
    assert "| RMSE / optimum |" in text and "1 / 1" in text
    section = text.split("without")[-1]
    assert "RMSE / optimum" not in section.split("####")[-1]
