"""Tests of the atomic result writers (``tobitkf._io``)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from tobitkf import ValidationError
from tobitkf._io import atomic_savefig, atomic_write_json, atomic_write_text, safe_child


def test_write_json_roundtrip_and_no_leftovers(tmp_path):
    path = atomic_write_json(tmp_path / "sub" / "metrics.json", {"rmse": np.array([0.5, np.inf]), "n": np.int32(3)})
    assert json.loads(path.read_text()) == {"rmse": [0.5, "inf"], "n": 3}
    assert os.listdir(path.parent) == ["metrics.json"]  # the temporary file was renamed, not left behind


def test_failed_write_keeps_previous_file(tmp_path):
    path = atomic_write_text(tmp_path / "a.txt", "old")

    class Boom:
        def __str__(self):
            raise RuntimeError("boom")

    with pytest.raises(TypeError):
        atomic_write_text(path, Boom())  # not a str: the write fails
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["a.txt"]


def test_savefig(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    path = atomic_savefig(fig, tmp_path / "f.png")
    plt.close(fig)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert os.listdir(tmp_path) == ["f.png"]


def test_safe_child(tmp_path):
    assert safe_child(tmp_path, "exp1") == (tmp_path / "exp1").resolve()
    with pytest.raises(ValidationError, match="output path: '../x' would leave the output directory"):
        safe_child(tmp_path, "../x")
    with pytest.raises(ValidationError, match="output path"):
        safe_child(tmp_path, "/etc")
