"""The layers point one way, and the pure core stays pure.

    toptag (core)  <-  protocol (wire + transport)  <-  sim (world, renderer, studies)  <-  services

The import graph is read from the code (every import statement, inside functions too); a module may
import its own layer and the layers left of it, never one to its right. The CLI dispatches by module
name (strings), which is not an import."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("toptag", "protocol", "sim", "services")
RANK = {name: i for i, name in enumerate(LAYERS)}

pytestmark = pytest.mark.unit

# Plain functions and small classes: no network, no processes, no Zenoh, no wire contract.
PURE = ["toptag/camera.py", "toptag/vehicle.py", "toptag/geometry.py", "toptag/detection.py", "toptag/fix.py",
        "toptag/units.py", "toptag/limits.py", "toptag/errors.py",
        "toptag/solvers", "toptag/rsu", "toptag/fusion", "sim/render.py", "sim/render_kernels.py", "sim/motion.py",
        "sim/world.py", "sim/scenario.py"]
IMPURE_MODULES = {"zenoh", "protocol", "socket", "subprocess"}


def imported_modules(tree: ast.AST, module: str) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in a module's syntax tree, nested ones included."""
    package = module.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the importing module's package
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.append((node.lineno, name))
    return found


def module_name(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def layer_violations(root: Path) -> list[str]:
    """Every import, in every layer's code under ``root``, of a layer to its right."""
    out = []
    for layer in LAYERS:
        for path in sorted((root / layer).rglob("*.py")):
            module = module_name(root, path)
            for line, name in imported_modules(ast.parse(path.read_text(), str(path)), module):
                target = name.split(".")[0]
                if target in RANK and RANK[target] > RANK[layer]:
                    out.append(f"{path.relative_to(root)}:{line}: {layer} imports {name} "
                               f"(layer {target} is above {layer})")
    return out


def test_layers_import_only_downward():
    assert layer_violations(ROOT) == []


def test_layer_check_catches_a_planted_violation(tmp_path):
    """The check is not vacuous: a solver importing the simulator inside a function is caught."""
    for layer in LAYERS:
        (tmp_path / layer).mkdir()
        (tmp_path / layer / "__init__.py").write_text("")
    (tmp_path / "toptag" / "solvers").mkdir()
    (tmp_path / "toptag" / "solvers" / "bad.py").write_text(
        "import numpy\n\ndef f():\n    from sim.render import render\n    return render\n")
    (tmp_path / "protocol" / "ok.py").write_text("from toptag.camera import Camera\n")
    (tmp_path / "sim" / "rel.py").write_text("from .render import x\nfrom services import demo\n")
    found = sorted(layer_violations(tmp_path))
    assert len(found) == 2, found
    assert found[0].startswith("sim/rel.py:2: sim imports services")
    assert found[1].startswith("toptag/solvers/bad.py:4: toptag imports sim.render")


def test_every_layer_exists():
    for layer in LAYERS:
        assert (ROOT / layer / "__init__.py").exists(), f"{layer}/ is not a package"


def _python_files(rel):
    p = ROOT / rel
    return sorted(p.rglob("*.py")) if p.is_dir() else [p]


@pytest.mark.parametrize("rel", PURE)
def test_core_module_does_no_network_or_process_io(rel):
    files = _python_files(rel)
    assert files and all(f.exists() for f in files), f"{rel} is missing"
    for f in files:
        for line, name in imported_modules(ast.parse(f.read_text()), module_name(ROOT, f)):
            assert name.split(".")[0] not in IMPURE_MODULES, f"{f.relative_to(ROOT)}:{line} imports {name}"
