"""Studies behind `toptag eval ...`: each module has run(...) -> dict and main(argv) -> int."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

from toptag.errors import SetupError

STUDIES_EXTRA = "toptag[studies]"


def require_plotting() -> None:
    """SetupError naming what to install when matplotlib, which the studies plot with and the services do
    not need, is missing: the runtime image and a plain `pip install toptag` leave it out. Checked before a
    study runs, not after minutes of work."""
    if importlib.util.find_spec("matplotlib") is None:
        raise SetupError(f"the studies plot with matplotlib, which is not installed: pip install "
                         f"'{STUDIES_EXTRA}' (or pip install -e '.[studies]' in a checkout)")


def write_results(out: Path, doc: dict) -> Path:
    """A study's machine-readable results: out/results.json (out made if missing); its path."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path
