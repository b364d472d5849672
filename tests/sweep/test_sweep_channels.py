"""Sweep files name any registered channel by its section: the quantizer's table, its estimators, its errors."""

import numpy as np
import pytest

import tobitkf as tk
from tobitkf.filters.registry import channel_of, make, parts_of
from tobitkf.sweep import SweepFileError, load_result, parse_sweep, run_sweep

QUANTIZED = """
[sweep]
runs = 20
steps = 12
seed = 5
block_runs = 10

[model]
A = [[0.95]]
C = [[1.0]]
Q = [[0.04]]
R = [[0.01]]
x0 = [0.0]
P0 = [[0.2]]

[quantizer]
width = 0.25
lower = -0.5

[estimators.adf]
type = "AssumedDensityFilter"

[estimators.slf]
type = "TobitFilter"

[grid]
"quantizer.width" = [0.25, 0.5]
"""


def test_a_sweep_file_names_the_quantizer_by_its_table(tmp_path):
    spec = parse_sweep(QUANTIZED, name="q")
    ds = load_result(run_sweep(spec, tmp_path))
    sys_ = tk.LinearSystem(A=[[0.95]], C=[[1.0]], Q=[[0.04]], R=[[0.01]], x0=[0.0], P0=[[0.2]])
    for width in (0.25, 0.5):  # independent: the documented block seeds, filtered directly
        q = tk.Quantizer(width, lower=-0.5)
        errs = []
        for b in range(2):
            d = tk.simulate(sys_, 12, 10, channel=q, seed=np.random.SeedSequence(5, spawn_key=(b,)))
            errs.append(tk.AssumedDensityFilter(sys_, q).filter(d.y).mean - d.x[:, 1:])
        e = np.concatenate(errs)
        got = ds["rmse"].sel({"quantizer.width": width, "estimator": "adf"}).values
        np.testing.assert_allclose(got, np.sqrt((e**2).mean(axis=0)), rtol=1e-12)


@pytest.mark.parametrize(
    "old, new, match",
    [
        ("lower = -0.5", "lower = -0.5\nstep = 2", "quantizer.step.*unknown key"),
        ("[quantizer]", "[censoring]\nlower = 0.0\n\n[quantizer]", "carries its own limits; drop \\[censoring\\]"),
        ("width = 0.25", "width = -1.0", "width: expected a step > 0"),
    ],
)
def test_quantizer_table_errors(old, new, match):
    with pytest.raises(SweepFileError, match=match):
        parse_sweep(QUANTIZED.replace(old, new, 1), name="q")


def test_the_registry_builds_the_generic_filters_of_any_registered_channel():
    sys_ = tk.LinearSystem(A=[[0.9]], C=[[1.0]], Q=[[0.1]], R=[[0.5]], x0=[0.0], P0=[[1.0]])
    q = tk.Quantizer(0.5)
    assert parts_of(q) == {"quantizer": q} and channel_of({"censoring": tk.Censoring(), "quantizer": q}) is q
    assert type(make("AssumedDensityFilter", sys_, quantizer=q)) is tk.AssumedDensityFilter
    assert type(make("AssumedDensityFilter", sys_, censoring=tk.Censoring(lower=0.0))) is tk.AssumedDensityTobitFilter
    assert make("ParticleFilter", sys_, quantizer=q, seed=0).model.channel is q
    with pytest.raises(tk.ValidationError, match="channel: AssumedDensityFilter needs a channel piece"):
        make("AssumedDensityFilter", sys_)
