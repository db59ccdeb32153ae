"""The pure core stays pure: no network, no Zenoh in geometry, detection, solvers, filter, pipeline."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PURE = ["toptag/camera.py", "toptag/vehicle.py", "toptag/geometry.py", "toptag/detection.py",
        "toptag/solvers", "services/rsu/pipeline.py", "services/rsu/regions.py", "services/rsu/tracking.py",
        "services/bus/filter.py", "services/bus/presence.py", "sim/render.py", "sim/motion.py", "sim/world.py",
        "sim/scenario.py"]


def _python_files(rel):
    p = ROOT / rel
    return sorted(p.rglob("*.py")) if p.is_dir() else [p]


@pytest.mark.parametrize("rel", PURE)
def test_core_module_does_not_import_zenoh(rel):
    files = _python_files(rel)
    assert files and all(f.exists() for f in files), f"{rel} is missing"
    for f in files:
        for node in ast.walk(ast.parse(f.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            assert not any(n.split(".")[0] in ("zenoh", "protocol", "socket") for n in names), f"{f} imports {names}"
