"""Zenoh configuration and sessions for every toptag process: endpoints, mode, multicast scouting, a
JSON5 file, the environment and the command line, with one precedence order.

Facts this module relies on (eclipse-zenoh 1.10, Python):
- Client mode without a reachable router fails at open (immediately); peer mode opens and keeps
  retrying its connect endpoints in the background.
- Zenoh's runtime threads are set by the ZENOH_RUNTIME environment variable (RON, zenoh-runtime's
  syntax), read once, when the process first opens a session; the rx, tx, ... threads start with its
  first link. By default a process runs two rx workers, a tx and a net thread (plus acc and app), and a
  message passes between them: in the bus agent (`toptag bench bus`, 100 Hz IMU, 40 fixes/s, 50 Hz
  output) they took ~700 context switches a second and ~2 % of a core.
"""
from __future__ import annotations

import argparse
import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Literal

import zenoh
from pydantic import BaseModel, ConfigDict

from toptag.errors import SetupError

MODES = ("peer", "client", "router")
ENV_MODE = "TOPTAG_ZENOH_MODE"
ENV_CONNECT = "TOPTAG_ZENOH_CONNECT"
ENV_LISTEN = "TOPTAG_ZENOH_LISTEN"
ENV_CONFIG = "TOPTAG_ZENOH_CONFIG"
ENV_MULTICAST = "TOPTAG_ZENOH_MULTICAST"
ENV_RUNTIME = "ZENOH_RUNTIME"
# Every runtime's work handed over to the app runtime's single worker: one Zenoh thread, no hand-off between
# Zenoh's own threads. For a process whose Python takes its messages from channels (the bus agent): its
# context switches 14 100 -> 5 800 per 20 s, Zenoh's threads 0.46 -> 0.31 s of CPU (docs/real-time.md).
# Not for every process: that thread then carries all of a process's Zenoh I/O, and with it in every process
# of `toptag bench demo` the simulator sent frames up to 2.5 s late and the RSUs skipped 11-13 % of their
# frames for being busy (0.0-0.2 % with it in the bus agents only, as without it).
ONE_ZENOH_THREAD = "(rx: (handover: app), tx: (handover: app), net: (handover: app), acc: (handover: app))"
# PoseFix goes at INTERACTIVE_HIGH, express, with CongestionControl.DROP (publishing.QOS), each fix a batch of its
# own, and an RSU sends its buses' fixes of a frame back to back. Zenoh keeps 2 batches per priority and drops a
# message that waited 1 ms for room: a sender starved of CPU (6 busy loops in its group on the 2 cores) lost
# 20, 22 and 34 of ~786 fixes sent in bursts of 4; with 8 batches none of 2364 (docs/real-time.md). A config
# file that sets this queue to another size keeps it.
FIX_QUEUE_PATH = "transport/link/tx/queue/size/interactive_high"
FIX_QUEUE_BATCHES = 8


class ZenohSetupError(SetupError):
    """A zenoh config or session cannot be made. str(e) is one line."""


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    # zenoh errors end with " at /root/.cargo/...rs:NN." - keep the message, drop the source location.
    cut = text.find(" at /")
    return text[:cut] if cut > 0 else text


def _check_endpoints(what: str, endpoints: Iterable[str]) -> list[str]:
    out = []
    for ep in endpoints:
        ep = str(ep).strip()
        if not ep:
            continue
        proto, sep, addr = ep.partition("/")
        if not sep or not proto or not addr:
            raise ZenohSetupError(f"{what}: endpoint {ep!r} is not of the form <protocol>/<address>, "
                                  f"e.g. tcp/127.0.0.1:7447")
        out.append(ep)
    return out


def split_endpoints(text: str | None) -> list[str]:
    """'tcp/a:1, tcp/b:2' -> ['tcp/a:1', 'tcp/b:2'] (env variables and repeated CLI options)."""
    if not text:
        return []
    return [p.strip() for p in text.replace(";", ",").split(",") if p.strip()]


def zenoh_config(mode: str | None = "peer", connect: Sequence[str] | None = None,
                 listen: Sequence[str] | None = None, multicast_scouting: bool | None = False,
                 config_file: str | os.PathLike | None = None,
                 extra: dict[str, Any] | None = None) -> zenoh.Config:
    """A zenoh.Config: start from ``config_file`` (JSON5) if given, then set every argument that is not
    None (``extra`` maps config paths such as "transport/link/tx/lease" to JSON-able values).

    Defaults suit toptag: peer mode, multicast scouting off (explicit endpoints only), FIX_QUEUE_BATCHES."""
    if config_file is not None:
        try:
            conf = zenoh.Config.from_file(str(config_file))
        except Exception as e:  # zenoh raises ZError (or others) with a long message
            raise ZenohSetupError(f"zenoh config file {config_file}: {_one_line(e)}") from None
    else:
        conf = zenoh.Config()

    def put(path: str, value: Any) -> None:
        try:
            conf.insert_json5(path, json.dumps(value))
        except Exception as e:
            raise ZenohSetupError(f"zenoh config {path}={value!r}: {_one_line(e)}") from None

    if mode is not None:
        if mode not in MODES:
            raise ZenohSetupError(f"zenoh mode {mode!r} is not one of {', '.join(MODES)}")
        put("mode", mode)
    if connect is not None:
        put("connect/endpoints", _check_endpoints("connect", connect))
    if listen is not None:
        put("listen/endpoints", _check_endpoints("listen", listen))
    if multicast_scouting is not None:
        put("scouting/multicast/enabled", bool(multicast_scouting))
    if conf.get_json(FIX_QUEUE_PATH) == zenoh.Config().get_json(FIX_QUEUE_PATH):  # Zenoh's default: not the file's
        put(FIX_QUEUE_PATH, FIX_QUEUE_BATCHES)
    for path, value in (extra or {}).items():
        put(path, value)
    return conf


def config_summary(conf: zenoh.Config) -> str:
    """'mode=peer listen=[...] connect=[...]' for logs."""
    def get(path):
        try:
            return json.loads(conf.get_json(path))
        except Exception:
            return None
    mode = get("mode") or "peer"
    listen = get("listen/endpoints")
    if isinstance(listen, dict):
        listen = listen.get(mode, [])
    return f"mode={mode} listen={listen or []} connect={get('connect/endpoints') or []}"


def open_session(conf: zenoh.Config | None = None, *, runtime: str | None = None, **config_kwargs) -> zenoh.Session:
    """Open a zenoh session from ``conf`` or from zenoh_config(**config_kwargs). Raises
    ZenohSetupError (one line) if zenoh refuses (port in use, bad endpoint, no router in client mode).

    ``runtime``: Zenoh's runtime threads for this process (a ZENOH_RUNTIME value, e.g. ONE_ZENOH_THREAD),
    taken only by the process's first session and only when the environment sets no ZENOH_RUNTIME (an
    operator's choice wins). It is not left in the environment: processes started later choose their own."""
    if conf is None:
        conf = zenoh_config(**config_kwargs)
    elif config_kwargs:
        raise TypeError("pass either a zenoh.Config or zenoh_config() keyword arguments, not both")
    own = runtime is not None and ENV_RUNTIME not in os.environ
    if own:
        os.environ[ENV_RUNTIME] = runtime
    try:
        return zenoh.open(conf)
    except Exception as e:
        raise ZenohSetupError(f"cannot open zenoh session ({config_summary(conf)}): {_one_line(e)}") from None
    except BaseException as e:  # zenoh-runtime panics on a ZENOH_RUNTIME it cannot parse (pyo3's PanicException)
        if type(e).__name__ != "PanicException":
            raise
        raise ZenohSetupError(f"cannot open zenoh session: {ENV_RUNTIME}={os.environ.get(ENV_RUNTIME)!r}: "
                              f"{_one_line(e)}") from None
    finally:
        if own:
            del os.environ[ENV_RUNTIME]


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, default_mode: str = "peer") -> None:
    """Add --zenoh-mode/--connect/--listen/--zenoh-config/--multicast-scouting to a service's CLI.
    Resolve them with zenoh_config_from_args()."""
    g = parser.add_argument_group("zenoh")
    g.add_argument("--zenoh-mode", choices=MODES, default=None,
                   help=f"zenoh mode (env {ENV_MODE}; default {default_mode})")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to connect to, e.g. tcp/10.0.0.1:7447; repeatable or comma-separated "
                        f"(env {ENV_CONNECT})")
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to listen on; repeatable or comma-separated (env {ENV_LISTEN})")
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help=f"zenoh JSON5 config file to start from (env {ENV_CONFIG}); options above override it")
    g.add_argument("--multicast-scouting", action=argparse.BooleanOptionalAction, default=None,
                   help=f"zenoh multicast scouting (env {ENV_MULTICAST}=1/0; default off)")
    parser.set_defaults(_zenoh_default_mode=default_mode)


def zenoh_config_from_args(args: argparse.Namespace, *, mode: str | None = None,
                           default_listen: Sequence[str] | None = None,
                           default_connect: Sequence[str] | None = None,
                           environ: dict[str, str] | None = None) -> zenoh.Config:
    """Config from add_zenoh_arguments() options. Precedence: command line > environment > config
    file > defaults (``mode`` forces the mode, e.g. "router")."""
    env = os.environ if environ is None else environ

    def endpoints(cli, env_name):
        if cli:
            return [e for item in cli for e in split_endpoints(item)]
        if env.get(env_name):
            return split_endpoints(env[env_name])
        return None

    config_file = args.zenoh_config or env.get(ENV_CONFIG) or None
    listen = endpoints(args.listen, ENV_LISTEN)
    connect = endpoints(args.connect, ENV_CONNECT)
    the_mode = mode or args.zenoh_mode or env.get(ENV_MODE) or None
    multicast = args.multicast_scouting
    if multicast is None and env.get(ENV_MULTICAST):
        multicast = env[ENV_MULTICAST].strip().lower() in ("1", "true", "yes", "on")
    if config_file is None:
        the_mode = the_mode or getattr(args, "_zenoh_default_mode", "peer")
        listen = listen if listen is not None else (list(default_listen) if default_listen else None)
        connect = connect if connect is not None else (list(default_connect) if default_connect else None)
        multicast = False if multicast is None else multicast
    else:
        # Only fill defaults the file does not set.
        base = zenoh_config(mode=None, multicast_scouting=None, config_file=config_file)
        unset = zenoh.Config()
        if listen is None and default_listen and base.get_json("listen/endpoints") == unset.get_json(
                "listen/endpoints"):
            listen = list(default_listen)
        if connect is None and default_connect and base.get_json("connect/endpoints") == unset.get_json(
                "connect/endpoints"):
            connect = list(default_connect)
        if multicast is None and json.loads(base.get_json("scouting/multicast/enabled")) is None:
            multicast = False  # toptag default, unless the file turns it on
    return zenoh_config(mode=the_mode, connect=connect, listen=listen, multicast_scouting=multicast,
                        config_file=config_file)


class ZenohSettings(BaseModel):
    """The [zenoh] table of a service's settings file: the same options as the command line's
    (--zenoh-mode, --connect, --listen, --multicast-scouting, --zenoh-config). A relative config_file
    is relative to the settings file."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    mode: Literal["peer", "client", "router"] | None = None
    connect: list[str] | None = None
    listen: list[str] | None = None
    multicast_scouting: bool | None = None
    config_file: str | None = None


def apply_zenoh_settings(args: argparse.Namespace, zs: ZenohSettings, base_dir: Path | None = None) -> None:
    """Fill the Zenoh options the command line left unset from a settings file's [zenoh] table: the
    command line overrides the file, the file overrides the environment."""
    if args.zenoh_mode is None and zs.mode is not None:
        args.zenoh_mode = zs.mode
    if args.connect is None and zs.connect is not None:
        args.connect = list(zs.connect)
    if args.listen is None and zs.listen is not None:
        args.listen = list(zs.listen)
    if args.multicast_scouting is None and zs.multicast_scouting is not None:
        args.multicast_scouting = zs.multicast_scouting
    if args.zenoh_config is None and zs.config_file is not None:
        f = Path(zs.config_file)
        args.zenoh_config = str(f if f.is_absolute() or base_dir is None else base_dir / f)
