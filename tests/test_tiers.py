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


def test_system_tests_run_one_after_another_on_one_xdist_worker(tmp_path):
    """`make test` runs with `-n auto --dist loadgroup`: two whole systems at once would starve each other."""
    runs = tmp_path / "runs"
    runs.mkdir()
    source = ("import os, time\nimport pytest\n\n"
              + "".join(f"@pytest.mark.system\ndef test_system_{i}():\n"
                        f"    t0 = time.time(); time.sleep(0.3)\n"
                        f"    open(r'{runs}/{i}', 'w').write(f\"{{os.environ['PYTEST_XDIST_WORKER']}} {{t0}} {{time.time()}}\")\n\n"
                        for i in range(4))
              + "".join(f"@pytest.mark.unit\ndef test_unit_{i}():\n    time.sleep(0.1)\n\n" for i in range(8)))
    (tmp_path / "test_planted.py").write_text(source)
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "tiers", "-p", "no:cacheprovider", "-n", "2",
                        "--dist", "loadgroup", str(tmp_path)], cwd=tmp_path, capture_output=True, text=True,
                       env={"PYTHONPATH": str(TESTS), "PATH": "/usr/bin:/bin"}, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    seen = sorted((p.read_text().split() for p in runs.iterdir()), key=lambda w: float(w[1]))
    assert len(seen) == 4 and len({w[0] for w in seen}) == 1, seen
    assert all(float(b[1]) >= float(a[2]) for a, b in zip(seen, seen[1:])), seen  # never two at once
