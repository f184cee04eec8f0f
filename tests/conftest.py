"""Shared test settings.

Under CI (CI=true) hypothesis runs derandomized, so a CI verdict is reproducible and does not
depend on which examples a fresh database happens to draw; local runs keep exploring new
examples (and remember failing ones in .hypothesis/).
"""

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
