"""The docstring examples of tobitkf.inference and tobitkf.data run and hold."""

import doctest
import importlib

import pytest

MODULES = [
    "tobitkf.data",
    "tobitkf.inference.adf",
    "tobitkf.inference.smoothing",
    "tobitkf.inference.likelihood",
    "tobitkf.inference.censored_ar",
    "tobitkf.inference.fitting",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert res.failed == 0
