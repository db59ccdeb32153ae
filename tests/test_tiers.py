"""Every test carries exactly one tier (tests/tiers.py): a test without one, or with two, stops the
collection with a message naming it."""
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

TESTS = Path(__file__).resolve().parent


def collect(tmp_path, source: str) -> subprocess.CompletedProcess:
    (tmp_path / "test_planted.py").write_text(source)
    return subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "tiers", "-p",
                           "no:cacheprovider", str(tmp_path)], cwd=tmp_path, capture_output=True, text=True,
                          env={"PYTHONPATH": str(TESTS), "PATH": "/usr/bin:/bin"}, timeout=120)


def test_a_test_without_a_tier_fails_collection(tmp_path):
    r = collect(tmp_path, "import pytest\n\ndef test_untiered():\n    pass\n\n"
                          "@pytest.mark.unit\ndef test_tiered():\n    pass\n")
    assert r.returncode != 0
    assert "every test needs exactly one tier marker" in r.stderr + r.stdout
    assert "test_planted.py::test_untiered (no tier)" in r.stderr + r.stdout, r.stderr + r.stdout
    error = next(line for line in (r.stderr + r.stdout).splitlines() if "exactly one tier" in line)
    assert "test_tiered" not in error


def test_two_tiers_fail_and_one_passes(tmp_path):
    r = collect(tmp_path, "import pytest\n\n@pytest.mark.unit\n@pytest.mark.system\ndef test_both():\n    pass\n")
    assert r.returncode != 0 and "test_both (tiers system, unit)" in r.stderr + r.stdout
    r = collect(tmp_path, "import pytest\n\npytestmark = pytest.mark.integration\n\ndef test_one():\n    pass\n")
    assert r.returncode == 0, r.stderr + r.stdout
