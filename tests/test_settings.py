"""Settings files (`--config FILE`): the shipped examples load, unknown keys are refused with the key
named, the command line overrides the file, and a service started with a file uses it."""
from __future__ import annotations

import argparse
import subprocess
import sys

import pytest
from conftest import REPO, clean_env

from protocol.transport.config import zenoh_config_from_args
from protocol.transport.runner import ServiceSettings, add_service_arguments, load_service_settings
from services.bus.agent import BusSettings
from services.bus.agent import build_parser as bus_parser
from services.rsu.service import RsuSettings
from services.rsu.service import build_parser as rsu_parser
from toptag.errors import InputError
from toptag.fusion.filter import FilterConfig
from toptag.rsu.pipeline import PipelineSettings

EXAMPLES = REPO / "examples" / "config"
CAMERA = REPO / "toptag" / "data" / "demo" / "rsu-sw.json"


def _args(parser: argparse.ArgumentParser, *argv: str) -> argparse.Namespace:
    return parser.parse_args(list(argv))


def _service_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    add_service_arguments(p)
    return p


@pytest.mark.unit
@pytest.mark.parametrize("name, model", [("rsu.toml", RsuSettings), ("bus.toml", BusSettings),
                                         ("bus.yaml", BusSettings), ("router.toml", ServiceSettings)])
def test_every_shipped_example_loads(name, model):
    args = _args(_service_parser(), "--config", str(EXAMPLES / name))
    settings = load_service_settings(args, model)
    assert isinstance(settings, model)
    if model is RsuSettings:
        assert settings.pipeline.method == "level" and settings.pipeline.detector.max_hamming == 0
        assert args.zenoh_mode == "client" and args.connect == ["tcp/127.0.0.1:7447"]
    if model is BusSettings:
        assert settings.filter.gate_probability == 0.999 and settings.filter == FilterConfig()
    if model is ServiceSettings:
        assert args.listen == ["tcp/0.0.0.0:7447"] and args.multicast_scouting is False


@pytest.mark.unit
def test_examples_cover_every_file_in_the_folder():
    assert sorted(p.name for p in EXAMPLES.iterdir()) == ["bus.toml", "bus.yaml", "router.toml", "rsu.toml"]


@pytest.mark.unit
@pytest.mark.parametrize("text, model, key", [
    ("[pipeline]\nmethd = 'bas'\n", RsuSettings, "pipeline.methd: unknown key"),
    ("[pipeline.detector]\nmax_haming = 1\n", RsuSettings, "pipeline.detector.max_haming: unknown key"),
    ("[filter]\ngate_prob = 0.9\n", BusSettings, "filter.gate_prob: unknown key"),
    ("[filter]\nbuffer_s = 0.5\n", BusSettings, "filter.buffer_s: Input should be greater than or equal to 1"),
    ("[zenoh]\nmode = 'server'\n", ServiceSettings, "zenoh.mode: Input should be"),
    ("[zenoh]\nconect = ['tcp/1.2.3.4:7447']\n", BusSettings, "zenoh.conect: unknown key"),
    ("[filter]\nbuffer_s = 2.0\n", RsuSettings, "filter: unknown key"),  # the bus's table given to an RSU
    ("[pipeline]\nmethod = 'fast'\n", RsuSettings, "pipeline.method: unknown solver 'fast'"),
    ("[pipeline\n", RsuSettings, "not valid TOML"),
])
def test_bad_settings_are_one_line_naming_the_key(tmp_path, text, model, key):
    path = tmp_path / "s.toml"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        load_service_settings(_args(_service_parser(), "--config", str(path)), model)
    assert key in str(e.value) and str(path) in str(e.value) and "\n" not in str(e.value)


@pytest.mark.unit
def test_yaml_and_missing_files(tmp_path):
    (tmp_path / "s.yaml").write_text("filter:\n  lost_after_s: 5.0\n  gate_probabilty: 0.9\n")
    with pytest.raises(InputError, match="filter.gate_probabilty: unknown key"):
        load_service_settings(_args(_service_parser(), "--config", str(tmp_path / "s.yaml")), BusSettings)
    with pytest.raises(InputError, match="no such file"):
        load_service_settings(_args(_service_parser(), "--config", str(tmp_path / "none.toml")), BusSettings)
    (tmp_path / "s.json").write_text("{}")
    with pytest.raises(InputError, match="unknown format"):
        load_service_settings(_args(_service_parser(), "--config", str(tmp_path / "s.json")), BusSettings)


@pytest.mark.unit
def test_the_command_line_overrides_the_file(tmp_path, monkeypatch):
    monkeypatch.delenv("TOPTAG_ZENOH_CONNECT", raising=False)
    path = tmp_path / "rsu.toml"
    path.write_text("[zenoh]\nmode = 'client'\nconnect = ['tcp/10.0.0.1:7447']\nconfig_file = 'z.json5'\n"
                    "[pipeline]\nmethod = 'sopt'\nacquire_period_s = 0.25\n")
    (tmp_path / "z.json5").write_text("{}\n")
    args = _args(rsu_parser(), "--camera", "c.json", "--intersection", "x1", "--config", str(path),
                 "--connect", "tcp/10.0.0.2:7447")
    settings = load_service_settings(args, RsuSettings)
    assert args.connect == ["tcp/10.0.0.2:7447"] and args.zenoh_mode == "client"
    assert args.zenoh_config == str(tmp_path / "z.json5")  # relative to the settings file
    assert settings.pipeline.method == "sopt" and settings.pipeline.acquire_period_s == 0.25
    conf = zenoh_config_from_args(args)
    assert "10.0.0.2" in conf.get_json("connect/endpoints") and "10.0.0.1" not in conf.get_json("connect/endpoints")
    # the file fills what the command line leaves unset, the environment comes last
    monkeypatch.setenv("TOPTAG_ZENOH_CONNECT", "tcp/10.0.0.3:7447")
    args = _args(bus_parser(), "--vehicle", "v.json", "--map", "m.json", "--config", str(path.with_name("b.toml")))
    path.with_name("b.toml").write_text("[zenoh]\nconnect = ['tcp/10.0.0.1:7447']\n")
    load_service_settings(args, BusSettings)
    assert "10.0.0.1" in zenoh_config_from_args(args).get_json("connect/endpoints")
    assert PipelineSettings().method == "level"  # defaults untouched


@pytest.mark.integration
def test_rsu_with_a_bad_settings_file_exits_2_naming_the_key(tmp_path):
    path = tmp_path / "rsu.toml"
    path.write_text("[pipeline]\nacquire_perod_s = 1.0\n")
    r = subprocess.run([sys.executable, "-m", "toptag", "rsu", "--camera", str(CAMERA), "--intersection", "x1",
                        "--config", str(path)], cwd=REPO, env=clean_env(), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0] == f"toptag rsu: settings {path}: pipeline.acquire_perod_s: unknown key", \
        r.stderr


@pytest.mark.integration
def test_rsu_runs_with_the_example_settings_and_command_line_method(tmp_path, launch, free_port):
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = launch(["-m", "toptag", "router", "--listen", ep], ready="router listening on")
    rsu = launch(["-m", "toptag", "rsu", "--camera", str(CAMERA), "--intersection", "x1",
                  "--config", str(EXAMPLES / "rsu.toml"), "--connect", ep, "--method", "bas"], ready="ready")
    out = rsu.output()
    assert "(960x720, bas solver)" in out and ep in out, out  # the command line's method and endpoint
    assert rsu.stop() == 0 and router.stop() == 0
