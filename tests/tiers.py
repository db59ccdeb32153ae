"""Test tiers: every test carries exactly one of the markers unit, integration, system.

- unit: pure code in this process, no network, no child process (seconds);
- integration: real Zenoh sessions, routers or child processes, one part of the system at a time;
- system: the whole system as a user runs it (the demo, the deployment in network namespaces).

The markers are registered in pyproject.toml (--strict-markers); `make test-unit` runs the unit tier
only, `make test` runs all. tests/conftest.py loads this hook; a test without a tier fails collection."""
from __future__ import annotations

import pytest

TIERS = ("unit", "integration", "system")


def pytest_collection_modifyitems(config, items):
    wrong = []
    for item in items:
        tiers = sorted({m.name for m in item.iter_markers() if m.name in TIERS})
        if len(tiers) != 1:
            wrong.append(f"{item.nodeid} ({'tiers ' + ', '.join(tiers) if tiers else 'no tier'})")
    if wrong:
        raise pytest.UsageError(
            f"every test needs exactly one tier marker ({', '.join('@pytest.mark.' + t for t in TIERS)}; "
            f"a module may set pytestmark): {'; '.join(wrong)}")
