"""`make test` runs the suite on two workers with `--dist loadgroup` (Makefile): each module whole on one worker,
the timing-sensitive modules one after another (tests/conftest.py). Under pytest 9.2 with pytest-xdist 3.8 the
groups were silently ignored, every test scheduled on its own; this checks they reach the scheduler."""

from __future__ import annotations

import pytest

from .conftest import TIMING_SENSITIVE_MODULES


def test_each_test_carries_its_module_group_to_the_scheduler(request):
    if not request.config.getvalue("loadgroup"):
        pytest.skip("not under `pytest -n N --dist loadgroup` (make test)")
    assert request.node.nodeid.endswith("@test_suite_groups"), request.node.nodeid
    assert "test_suite_groups" not in TIMING_SENSITIVE_MODULES
