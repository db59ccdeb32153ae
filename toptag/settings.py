"""Settings files: `--config FILE` of the services, in TOML (or YAML with the `yaml` extra), validated by
a pydantic model that refuses unknown keys.

A file has one table per part of the service, e.g. for `toptag rsu`::

    [zenoh]
    mode = "client"
    connect = ["tcp/192.0.2.1:7447"]

    [pipeline]
    method = "level"

Bad files are one-line InputErrors naming the file and the key (exit 2). Options given on the command
line override the file."""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import TypeVar

from pydantic import BaseModel, ValidationError

from toptag.errors import InputError

M = TypeVar("M", bound=BaseModel)
SUFFIXES = (".toml", ".yaml", ".yml")


def read_settings(path: str | Path) -> dict:
    """The table of a TOML (or YAML) settings file, or an InputError naming the file and the problem."""
    p = Path(path)
    if p.suffix not in SUFFIXES:
        raise InputError(f"settings {p}: unknown format (use {', '.join(SUFFIXES)})")
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise InputError(f"settings {p}: no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"settings {p}: cannot read ({e})") from None
    if p.suffix == ".toml":
        try:
            return tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise InputError(f"settings {p}: not valid TOML ({e})") from None
    try:
        import yaml
    except ImportError:
        raise InputError(f"settings {p}: YAML needs PyYAML (pip install 'toptag[yaml]'), or use TOML") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise InputError(f"settings {p}: not valid YAML ({' '.join(str(e).split())})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"settings {p}: the top level must be a mapping of tables")
    return data


def describe_settings_error(e: ValidationError) -> str:
    """The first problems as 'key.path: message', with unknown keys called what they are."""
    parts = []
    for err in e.errors()[:3]:
        key = ".".join(str(x) for x in err.get("loc", ())) or "(top level)"
        msg = "unknown key" if err.get("type") == "extra_forbidden" else err.get("msg", "invalid").removeprefix(
            "Value error, ")
        parts.append(f"{key}: {msg}")
    more = f" (+{e.error_count() - 3} more)" if e.error_count() > 3 else ""
    return "; ".join(parts) + more


def load_settings(path: str | Path, model: type[M]) -> M:
    """A settings file validated by ``model`` (which must forbid extra keys)."""
    data = read_settings(path)
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise InputError(f"settings {path}: {describe_settings_error(e)}") from None
