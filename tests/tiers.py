"""Test tiers: every test carries exactly one of the markers unit, integration, system.

- unit: pure code in this process, no network, no child process (seconds);
- integration: real Zenoh sessions, routers or child processes, one part of the system at a time;
- system: the whole system as a user runs it (the demo, the deployment in network namespaces).

The markers are registered in pyproject.toml (--strict-markers); `make test-unit` runs the unit tier
only, `make test` runs all. tests/conftest.py loads this hook; a test without a tier fails collection.

`make test` spreads the tests over pytest-xdist workers (`--dist loadgroup`); every system test is in
one group, so they run one after another on one worker: each starts the whole system (a demo takes
about 1.5 cores), and two at once would starve each other."""
from __future__ import annotations

import pytest

TIERS = ("unit", "integration", "system")


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook reads the xdist_group markers
def pytest_collection_modifyitems(config, items):
    wrong = []
    for item in items:
        tiers = sorted({m.name for m in item.iter_markers() if m.name in TIERS})
        if len(tiers) != 1:
            wrong.append(f"{item.nodeid} ({'tiers ' + ', '.join(tiers) if tiers else 'no tier'})")
        elif tiers == ["system"]:
            item.add_marker(pytest.mark.xdist_group("system"))
    if wrong:
        raise pytest.UsageError(
            f"every test needs exactly one tier marker ({', '.join('@pytest.mark.' + t for t in TIERS)}; "
            f"a module may set pytestmark): {'; '.join(wrong)}")
