"""Shared test configuration.

Hypothesis runs derandomised in CI (``CI`` set), so a CI result is reproducible; on a developer's
machine it explores new examples on every run.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
