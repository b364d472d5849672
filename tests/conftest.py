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
