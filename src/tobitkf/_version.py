"""The package version, in one place: ``pyproject.toml`` reads it from here (setuptools' dynamic
version), ``tobitkf.__version__``, ``tobitkf --version``, ``metrics.json`` and the sweep stores
record it. When it changes: CONTRIBUTING.md, "Versions and the changelog"."""

__version__ = "0.2.0.dev2"
