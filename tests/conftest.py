"""Test-suite configuration: hypothesis profiles.

``ci`` (the default) keeps every property test to a bounded example count so the suite
stays fast; ``long`` is for a run by hand::

    HYPOTHESIS_PROFILE=long python -m pytest tests/reliability -q

Tests that pass their own ``@settings(max_examples=...)`` keep it (explicit settings win).
"""

import os

from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci", max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
)
settings.register_profile(
    "long", max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


# The heavy tests: whole experiments, the docs site with every tutorial executed, Monte Carlo recovery.
# They take most of the suite's time, so the default run (the README's test command) leaves them out
# and .ci/run runs them as a second step (`python -m pytest -n 2 -q -m heavy`); run one by hand with
# `-m heavy` (or `-m ""` for everything).
HEAVY = (
    "tests/docs/test_docs.py::test_docs_site_builds_strict",
    "tests/docs/test_docs.py::test_tutorial_code_runs",
    "tests/experiments/test_claims_rule.py::test_every_experiment_follows_the_claims_rule_and_captions_its_figures",
    "tests/experiments/test_verdicts.py::",
    "tests/inference/test_fit.py::test_recovery_of_a_censored_ar1_regression",
    "tests/control/test_closed_loop.py::test_t15_unstable_plant_moving_limit_is_only_locally_stable",
    "tests/reliability/test_fuzz_readers.py::test_randomly_damaged_stores",
    "tests/experiments/test_yardstick.py::test_figures_and_cli",
)


def pytest_collection_modifyitems(config, items):
    import pytest

    for item in items:
        if item.nodeid.startswith(HEAVY):
            item.add_marker(pytest.mark.heavy)
