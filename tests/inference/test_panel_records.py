"""``tk.Panel.from_records``: a panel read from a long table (``read_censored_panel``) as the filters take it."""

import doctest

import numpy as np
import pytest

import tobitkf as tk
from tobitkf import ValidationError
from tobitkf.data import read_censored, read_censored_panel
from tobitkf.inference import panel as panel_module

TABLE = "id,day,v,z\na,0,1.5,0.1\na,7,<0.5,0.2\nb,3,>4,0.3\nb,9,2.0,0.4\nb,12,,0.5\n"


def test_a_read_panel_is_the_panel_built_by_hand(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text(TABLE)
    p = tk.Panel.from_records(read_censored_panel(path, id="id", time="day", y="v", covariates=["z"]),
                              regressors=["z"], intercept=True)  # fmt: skip
    hand = tk.Panel(
        [[0.0, 7.0], [3.0, 9.0, 12.0]],
        [[1.5, 0.5], [4.0, 2.0, np.nan]],
        lower=[[-np.inf, 0.5], [-np.inf] * 3],
        upper=[[np.inf, np.inf], [4.0, np.inf, np.inf]],
        censored=[[False, True], [True, False, False]],
        u=[[[1.0, 0.1], [1.0, 0.2]], [[1.0, 0.3], [1.0, 0.4], [1.0, 0.5]]],
        ids=["a", "b"],
    )
    assert p.ids == hand.ids
    for name in ("times", "y", "lower", "upper", "censored", "u"):
        for got, want in zip(getattr(p, name), getattr(hand, name)):
            np.testing.assert_array_equal(np.asarray(got, dtype=float), np.asarray(want, dtype=float))
    # one series read with times is a panel of one subject; without inputs u is None
    one = tk.Panel.from_records([read_censored({"t": [0, 2], "v": ["1.0", "<0.5"]}, y="v", time="t")])
    assert one.n_subjects == 1 and one.u == [None] and one.censored[0][:, 0].tolist() == [False, True]


def test_refusals_name_the_line_and_column(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text(TABLE.replace("b,9,2.0,0.4", "b,9,2.0,"))
    recs = read_censored_panel(path, id="id", time="day", y="v", covariates=["z"])
    with pytest.raises(ValidationError, match=r"p.csv line 5, column 'z': a blank regressor"):
        tk.Panel.from_records(recs, regressors=["z"])
    with pytest.raises(ValidationError, match=r"regressors: .* has no covariate 'q'"):
        tk.Panel.from_records(recs, regressors=["q"])
    untimed = read_censored({"v": ["1.0", "<0.5"]}, y="v")
    with pytest.raises(ValidationError, match=r"records\[0\]: .* has no sample times"):
        tk.Panel.from_records([untimed])


def test_the_docstring_example():
    finder = doctest.DocTestFinder()
    (test,) = [t for t in finder.find(panel_module.Panel.from_records, "from_records") if t.examples]
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    runner.run(test)
    assert runner.failures == 0 and runner.tries > 0
