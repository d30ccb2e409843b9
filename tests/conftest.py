"""Shared test configuration.

Hypothesis profiles (chosen with ``HYPOTHESIS_PROFILE``):

* ``default`` (the README's test command and CI): derandomised and without an example database,
  so every run of a checkout draws the same examples; a property that fails does so on every
  run and every machine, and a pass is never one lucky seed. Nothing is written to
  ``.hypothesis/``, so a failure found once cannot make later runs of that checkout fail.
* ``explore`` (a developer hunting for new counter-examples): random examples on every run and
  the example database in ``.hypothesis/`` so a failure found is replayed until fixed.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("default", derandomize=True, database=None, print_blob=True)
settings.register_profile("ci", parent=settings.get_profile("default"))
settings.register_profile("explore", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))
