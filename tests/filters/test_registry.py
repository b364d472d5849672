"""The estimator registry (``tobitkf.filters.registry``): every option it lists is one its estimator
takes, every linear entry builds with each listed value, and ``tobitkf estimators`` lists them all."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from typer.testing import CliRunner

import tobitkf as tk
from tobitkf.channels.fading import RiceFading
from tobitkf.channels.protocol import LAMBDA_BASE, ProtocolChannel
from tobitkf.cli import app
from tobitkf.filters.registry import ENTRIES, get, names

SAMPLE = {float: 0.7, int: 2, object: 3}  # a valid value per option type (xi in (0, 1), a count, a seed)


def _system(m=1):
    C = np.eye(2)[:m]
    return tk.LinearSystem(
        A=[[0.95, 0.1], [0.0, 0.9]], C=C, Q=0.01 * np.eye(2), R=0.05 * np.eye(m), x0=[1.0, 0.0], P0=0.5 * np.eye(2)
    )


def _parts():
    return {
        "censoring": tk.Censoring(lower=0.2),
        "fading": RiceFading.gaussian(1, [0.9, 0.4], [0.01, 0.02]),
        "protocol": ProtocolChannel(2, window=2, failures=LAMBDA_BASE, threshold=0.0),
        "saturation": tk.RandomSaturation([0.3], [0.8]),
    }


def _built(entry, options):
    m = 2 if "protocol" in entry.needs else 1
    # the particle filter takes any channel: none here (the censored linear reading, which has every proposal
    # it lists but the Rao-Blackwellised one), the protocol channel for that one
    parts = {} if entry.name == "ParticleFilter" else _parts()
    if "channel" in entry.needs:  # the generic filters of any channel: one without a named form
        parts = {"quantizer": tk.Quantizer(0.5)}
    if entry.name == "ParticleFilter" and options.get("proposal") == "rao_blackwellised":
        parts, m = {"protocol": _parts()["protocol"]}, 2
    return entry.build(_system(m), parts, options)


LINEAR = names("linear")


def test_the_linear_entries_include_the_assumed_density_filters():
    assert {"AssumedDensityTobitFilter", "FadingAssumedDensityFilter", "ProtocolAssumedDensityFilter"} <= set(LINEAR)


@pytest.mark.parametrize("name", LINEAR)
def test_every_listed_value_of_every_option_builds(name):
    """Each option value the registry lists is accepted by the estimator (a listed option the class
    refuses, or a value it refuses, raises here)."""
    entry = get(name)
    base = {k: SAMPLE[entry.options[k]] for k in entry.required}
    est = _built(entry, base)
    assert est is not None
    for key, allowed in entry.options.items():
        if key in entry.required:
            continue
        values = allowed if isinstance(allowed, tuple) else (SAMPLE.get(allowed),)
        for v in values:
            if v is None:
                continue
            if key == "backend" and v == "numba":
                pytest.importorskip("numba")
            built = _built(entry, {**base, key: v})
            if (name, key, v) == ("ParticleFilter", "proposal", "auto"):
                assert built.proposal == "optimal"  # "auto" resolves to the closed form the model has
            elif hasattr(built, key):  # the estimator keeps the option it was given
                assert getattr(built, key) == v, (key, v)


@pytest.mark.parametrize("name", sorted(ENTRIES))
def test_listed_options_are_parameters_of_the_estimator(name):
    entry = get(name)
    if name in ("RegionalHinfFilter", "ProtocolBaselineTobitKalmanFilter", "ControlledLimitTobitKalmanFilter"):
        pytest.skip("built through a factory of its own (gains, the baseline, a pass-through of the TKF's options)")
    import tobitkf.filters as filters

    est_cls = getattr(tk, name, None) or getattr(filters, name)
    params = inspect.signature(est_cls.__init__).parameters
    assert set(entry.options) <= set(params), sorted(set(entry.options) - set(params))


@pytest.mark.parametrize(
    "name, direct",
    [
        ("AssumedDensityTobitFilter", lambda s, p: tk.AssumedDensityTobitFilter(s, p["censoring"])),
        ("FadingAssumedDensityFilter", lambda s, p: tk.FadingAssumedDensityFilter(s, p["fading"], p["censoring"])),
    ],
)
def test_a_registry_build_filters_as_the_class_does(name, direct):
    sys_, parts = _system(), _parts()
    d = tk.simulate(sys_, 15, 4, censoring=parts["censoring"], seed=3)
    a = get(name).build(sys_, parts).filter(d.y)
    b = direct(sys_, parts).filter(d.y)
    np.testing.assert_array_equal(a.mean, b.mean)


def test_the_command_line_lists_every_estimator():
    res = CliRunner().invoke(app, ["estimators"])
    assert res.exit_code == 0, res.output
    for name in ENTRIES:
        assert name in res.output
