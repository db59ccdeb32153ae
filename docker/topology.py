"""The toptag deployment topology, read from docker/compose.yaml: one description for containers and for
bare hosts.

    python docker/topology.py [--router-host HOST]    # print every service's bare-host command

docker/compose.yaml is read with PyYAML (the test extra; merge keys `<<` resolved as compose resolves
them). For each service this module yields the toptag argv and the environment compose gives it
(``environment`` over ``env_file``, as compose does), and maps the paths it names inside the image to the
repository: /site/... is toptag/data/demo/... (the Dockerfile's COPY lines say so), a bind-mounted file is
its file next to the compose file. The router, an eclipse/zenoh container running ``zenohd -c FILE``,
becomes ``toptag router --zenoh-config FILE`` with the same file.

tests/test_deployment.py checks the compose file with this module and runs exactly these commands and
environments, each service in its own network namespace.
"""
from __future__ import annotations

import argparse
import re
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

DOCKER_DIR = Path(__file__).resolve().parent
REPO = DOCKER_DIR.parent
COMPOSE = DOCKER_DIR / "compose.yaml"
DOCKERFILE = DOCKER_DIR / "Dockerfile"
ROUTER_HOST = "router"  # the router's compose service name, i.e. its host name on the compose network
ZENOH_PORT = 7447


class TopologyError(ValueError):
    """The compose file (or a file it names) is not what this module understands. One line."""


@dataclass
class Service:
    name: str
    image: str
    command: list[str]
    env: dict[str, str]
    volumes: dict[str, Path] = field(default_factory=dict)  # path in the container -> host path
    named_volumes: dict[str, str] = field(default_factory=dict)  # path in the container -> volume name
    build: dict | None = None  # on the one service that builds the image
    is_toptag: bool = False  # runs the image built from docker/Dockerfile: its command is a toptag command line


# ---- reading the files -------------------------------------------------------------------------

def load_compose(path: str | Path = COMPOSE) -> dict:
    try:
        import yaml
    except ImportError:
        raise TopologyError("reading a compose file needs PyYAML: pip install pyyaml") from None
    text = Path(path).read_text()
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        raise TopologyError(f"{path}: not YAML ({where}{getattr(e, 'problem', None) or e})") from None
    if not isinstance(data, dict) or not isinstance(data.get("services"), dict) or not data["services"]:
        raise TopologyError(f"{path}: no services")
    unknown = set(data) - {"name", "services", "networks", "volumes"} - {k for k in data if k.startswith("x-")}
    if unknown:
        raise TopologyError(f"{path}: top-level keys not understood here: {sorted(unknown)}")
    return data


def read_env_file(path: str | Path) -> dict[str, str]:
    """A compose env file, strictly: KEY=VALUE lines, # comments, blank lines; no quotes, no expansion."""
    env: dict[str, str] = {}
    for n, raw in enumerate(Path(path).read_text().splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        m = re.fullmatch(r"([A-Za-z_][A-Za-z0-9_]*)=([^\s'\"#$]*)", line)
        if not m:
            raise TopologyError(f"{path}:{n}: not a plain KEY=VALUE line: {raw!r}")
        env[m.group(1)] = m.group(2)
    return env


def image_layout(dockerfile: str | Path = DOCKERFILE) -> dict[str, Path]:
    """Absolute paths in the image that hold repository files: {"/site/": REPO/"toptag/data/demo"}.
    From the Dockerfile's COPY lines whose destination is absolute (build context = repository root)."""
    layout: dict[str, Path] = {}
    for line in Path(dockerfile).read_text().splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0].upper() == "COPY" and parts[2].startswith("/"):
            src, dst = parts[1], parts[2]
            layout[dst.rstrip("/") + ("/" if src.endswith("/") else "")] = (REPO / src).resolve()
    return layout


def _volumes(svc_name: str, spec: dict, base: Path) -> tuple[dict[str, Path], dict[str, str]]:
    """(bind mounts {container path: host path}, named volumes {container path: volume name})."""
    binds, named = {}, {}
    for v in spec.get("volumes", []):
        if not isinstance(v, str) or v.count(":") not in (1, 2):
            raise TopologyError(f"service {svc_name}: volume {v!r} is not HOST:CONTAINER[:MODE]")
        host, target = v.split(":")[:2]
        if host.startswith((".", "/")):
            binds[target] = (base / host).resolve()
        else:
            named[target] = host  # a named volume: no host file
    return binds, named


def _merge(base: dict, override: dict) -> dict:
    """One service's spec with an override file's (docker compose's rules for what is used here):
    environment merged by name, volumes by container path, env_file and ports appended, the rest
    replaced."""
    out = dict(base)
    for k, v in override.items():
        if k == "environment":
            env = dict(_env_dict(base.get(k, {})))
            env.update(_env_dict(v))
            out[k] = env
        elif k == "volumes":
            by_target = {vol.split(":")[1]: vol for vol in base.get(k, [])}
            by_target.update({vol.split(":")[1]: vol for vol in v})
            out[k] = list(by_target.values())
        elif k in ("env_file", "ports"):
            out[k] = list(dict.fromkeys([*base.get(k, []), *([v] if isinstance(v, str) else v)]))
        else:
            out[k] = v
    return out


def _env_dict(env) -> dict:
    if isinstance(env, list):
        return dict(item.split("=", 1) for item in env)
    return dict(env or {})


def services(*paths: str | Path) -> list[Service]:
    """Every service of the compose file (default docker/compose.yaml), in file order, with its final
    environment. Further files are overrides, as with `docker compose -f A -f B` (paths in all of them are
    relative to the first file's directory, as compose has it)."""
    paths = [Path(p) for p in (paths or (COMPOSE,))]
    specs: dict[str, dict] = {}
    for path in paths:
        for name, spec in load_compose(path)["services"].items():
            specs[name] = _merge(specs.get(name, {}), spec)
    base = paths[0].parent
    built = {str(spec.get("image", "")) for spec in specs.values() if spec.get("build") is not None}
    out = []
    for name, spec in specs.items():
        command = spec.get("command", [])
        if not isinstance(command, list) or not all(isinstance(a, str) for a in command):
            raise TopologyError(f"service {name}: command must be a list of strings (exec form)")
        env: dict[str, str] = {}
        files = spec.get("env_file", [])
        for f in [files] if isinstance(files, str) else files:
            env.update(read_env_file(base / f))
        env.update({k: str(v) for k, v in _env_dict(spec.get("environment", {})).items()})
        binds, named = _volumes(name, spec, base)
        out.append(Service(name=name, image=str(spec.get("image", "")), command=list(command), env=env,
                           volumes=binds, named_volumes=named, build=spec.get("build"),
                           is_toptag=str(spec.get("image", "")) in built))
    return out


# ---- from the container to a bare host ---------------------------------------------------------

def host_path(container_path: str, service: Service, layout: dict[str, Path] | None = None) -> Path | None:
    """Where the file a container sees at ``container_path`` comes from: a bind mount of the service, or
    the repository files the Dockerfile copied there. None if neither (the file is not ours)."""
    for target, host in service.volumes.items():  # a mounted file, or a file in a mounted directory
        if container_path == target:
            return host
        if container_path.startswith(target.rstrip("/") + "/"):
            return host / container_path[len(target.rstrip("/")) + 1:]
    layout = image_layout() if layout is None else layout
    best = None
    for dst, src in layout.items():
        if dst.endswith("/") and container_path.startswith(dst):
            if best is None or len(dst) > len(best[0]):
                best = (dst, src / container_path[len(dst):])
        elif container_path == dst:
            best = (dst, src)
    return None if best is None else best[1]


def container_paths(args: list[str]) -> list[str]:
    """The arguments of a command line that are absolute paths."""
    return [a for a in args if a.startswith("/")]


def bare_argv(service: Service, layout: dict[str, Path] | None = None) -> list[str]:
    """The service's toptag argv (without the `toptag` word) for a bare host: paths mapped to the
    repository. The router (zenohd -c FILE) becomes `router --zenoh-config FILE`."""
    layout = image_layout() if layout is None else layout

    def mapped(a: str) -> str:
        if not a.startswith("/"):
            return a
        p = host_path(a, service, layout)
        if p is None:
            raise TopologyError(f"service {service.name}: {a} is neither mounted nor copied into the image")
        return str(p)

    if service.is_toptag:
        return [mapped(a) for a in service.command]
    if service.image.split(":")[0] == "eclipse/zenoh":
        cmd = service.command
        for flag in ("-c", "--config"):
            if flag in cmd and cmd.index(flag) + 1 < len(cmd):
                rest = [a for i, a in enumerate(cmd) if i not in (cmd.index(flag), cmd.index(flag) + 1)]
                if rest:
                    raise TopologyError(f"service {service.name}: zenohd options besides {flag} FILE: {rest}")
                return ["router", "--zenoh-config", mapped(cmd[cmd.index(flag) + 1])]
        raise TopologyError(f"service {service.name}: zenohd without a config file (-c FILE)")
    raise TopologyError(f"service {service.name}: image {service.image} is neither toptag's nor eclipse/zenoh")


def bare_env(service: Service, router_host: str | None = None,
             layout: dict[str, Path] | None = None) -> dict[str, str]:
    """The service's environment, file paths mapped like bare_argv's; with ``router_host``, the compose host
    name `router` in endpoints replaced by it (or keep `router` and name it in /etc/hosts)."""
    env = dict(service.env)
    for k, v in env.items():
        if v.startswith("/"):
            p = host_path(v, service, layout)
            if p is None:
                raise TopologyError(f"service {service.name}: {k}={v} is neither mounted nor in the image")
            env[k] = str(p)
    if router_host is not None:
        for k, v in env.items():
            if k in ("TOPTAG_ZENOH_CONNECT", "TOPTAG_ZENOH_LISTEN"):
                env[k] = re.sub(rf"(?<=/){re.escape(ROUTER_HOST)}(?=:)", router_host, v)
    return env


def _short(arg: str) -> str:
    """A path under the current directory, relative to it (for printing)."""
    if arg.startswith("/"):
        try:
            return str(Path(arg).relative_to(Path.cwd()))
        except ValueError:
            pass
    return arg


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python docker/topology.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--compose", action="append", default=None, metavar="FILE",
                   help="compose file, repeatable for overrides (default docker/compose.yaml)")
    p.add_argument("--router-host", default=None,
                   help="the router's address, replacing the host name `router` (default: keep it)")
    args = p.parse_args(argv)
    try:
        layout = image_layout()
        for svc in services(*(args.compose or [COMPOSE])):
            env = bare_env(svc, args.router_host, layout) if svc.is_toptag else {}
            words = [f"{k}={shlex.quote(_short(v))}" for k, v in env.items()]
            words += ["toptag"] + [shlex.quote(_short(a)) for a in bare_argv(svc, layout)]
            print(f"# {svc.name}\n" + " ".join(words))
    except BrokenPipeError:  # `... | head`
        sys.stdout = None
    except (TopologyError, OSError) as e:
        print(f"topology: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
