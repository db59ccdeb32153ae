"""Bad input gets one clear line naming what is wrong: the error type and helpers shared by every loader."""
from __future__ import annotations

import json
from pathlib import Path
from typing import TypeVar

from pydantic import BaseModel, ValidationError

from toptag.errors import InputError

__all__ = ["InputError", "describe_validation_error", "read_json", "read_model", "validate_model"]

M = TypeVar("M", bound=BaseModel)


def describe_validation_error(e: ValidationError) -> str:
    """The first problem pydantic found, as 'field.path: message' on one line."""
    parts = []
    for err in e.errors()[:3]:
        loc = ".".join(str(x) for x in err.get("loc", ())) or "(top level)"
        msg = err.get("msg", "invalid").removeprefix("Value error, ")
        parts.append(f"{loc}: {msg}")
    more = f" (+{e.error_count() - 3} more)" if e.error_count() > 3 else ""
    return "; ".join(parts) + more


def read_json(path: str | Path, what: str):
    """Parse a JSON file, or raise InputError naming the file and the problem."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise InputError(f"{what} {p}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{what} {p}: is a directory") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{what} {p}: cannot read ({e})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"{what} {p}: not valid JSON (line {e.lineno}: {e.msg})") from None


def validate_model(model: type[M], data, source: str) -> M:
    """``model`` validated from ``data``, or InputError 'source: field.path: message'."""
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise InputError(f"{source}: {describe_validation_error(e)}") from None


def read_model(model: type[M], path: str | Path, what: str) -> M:
    """A JSON file validated as ``model``, or InputError naming the file (as '<what> <path>') and the problem."""
    return validate_model(model, read_json(path, what), f"{what} {path}")
