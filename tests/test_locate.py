"""`toptag locate` as a user runs it: a real process on rendered images it was never tuned to."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim.examples import write_examples

pytestmark = pytest.mark.integration

TOPTAG = [sys.executable, "-c", "from toptag.cli import main; main()"]


def locate(*args, timeout=120):
    p = subprocess.run(TOPTAG + ["locate", *map(str, args)], capture_output=True, text=True, timeout=timeout)
    return p.returncode, [json.loads(line) for line in p.stdout.splitlines()], p.stderr


@pytest.fixture(scope="module")
def low_res(tmp_path_factory):
    out = tmp_path_factory.mktemp("low")
    return out, write_examples(out, count=12, seed=101)


@pytest.fixture(scope="module")
def high_res(tmp_path_factory):
    out = tmp_path_factory.mktemp("high")
    return out, write_examples(out, count=3, width=3200, height=2400, seed=202)


def errors(out: Path, truth, lines):
    assert [Path(r["image"]).name for r in lines] == [t["image"] for t in truth]  # input order
    pos, yaw = [], []
    for r, t in zip(lines, truth):
        assert r["ok"], r
        pos.append(np.hypot(r["x"] - t["x"], r["y"] - t["y"]))
        yaw.append(np.degrees(np.angle(np.exp(1j * (r["yaw"] - t["yaw"])))))
        cov = np.asarray(r["covariance"])
        assert cov.shape == (3, 3) and np.all(np.linalg.eigvalsh(cov) > 0)
    return np.asarray(pos), np.asarray(yaw)


def test_low_resolution_default_solver_within_centimetres(low_res):
    out, truth = low_res
    images = [out / t["image"] for t in truth]
    code, lines, err = locate("--camera", out / "rsu-sw-960x720.json", "--vehicle", out / "bus-17.json", *images)
    assert code == 0, err
    pos, yaw = errors(out, truth, lines)
    # ±10 cm roof bounce, blur, noise, JPEG, lens distortion, a second bus or a truck in many images.
    assert np.sqrt(np.mean(pos ** 2)) < 0.05 and pos.max() < 0.12, pos
    assert np.sqrt(np.mean(yaw ** 2)) < 0.3
    assert {"level"} == {r["method"] for r in lines}


@pytest.mark.parametrize("method, limit", [("sopt", 0.12), ("hopt", 0.45), ("bas", 1.5)])
def test_other_methods(low_res, method, limit):
    out, truth = low_res
    code, lines, err = locate("--camera", out / "rsu-sw-960x720.json", "--vehicle", out / "bus-17.json",
                              "--method", method, *[out / t["image"] for t in truth[:6]])
    assert code == 0, err
    ok = [(r, t) for r, t in zip(lines, truth) if r["ok"]]
    assert len(ok) >= 4 and all(r["method"] == method for r, _ in ok)
    assert max(np.hypot(r["x"] - t["x"], r["y"] - t["y"]) for r, t in ok) < limit


def test_high_resolution(high_res):
    out, truth = high_res
    code, lines, err = locate("--camera", out / "rsu-sw-3200x2400.json", "--vehicle", out / "bus-17.json",
                              *[out / t["image"] for t in truth])
    assert code == 0, err
    pos, _ = errors(out, truth, lines)
    assert pos.max() < 0.04, pos


def test_other_bus_tags_are_never_this_bus(low_res):
    out, truth = low_res
    # The second bus's code bag: only images where it is in view may give a pose, and that pose is its own.
    with_second = [t for t in truth if "second" in t["scene"]]
    assert with_second
    code, lines, _ = locate("--camera", out / "rsu-sw-960x720.json", "--vehicle", out / "bus-42.json",
                            *[out / t["image"] for t in truth])
    assert code == 0
    for r, t in zip(lines, truth):
        if r["ok"]:
            assert "second" in t["scene"] and np.hypot(r["x"] - t["x"], r["y"] - t["y"]) > 2.5
        elif "second" not in t["scene"]:
            assert "no tag of code bag bus-42" in r["error"]


def test_bad_inputs_exit_2_with_one_line(low_res, tmp_path):
    out, truth = low_res
    good = out / truth[0]["image"]
    corrupt = tmp_path / "corrupt.jpg"
    corrupt.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    cam, veh = out / "rsu-sw-960x720.json", out / "bus-17.json"

    code, lines, err = locate("--camera", cam, "--vehicle", veh, good, tmp_path / "missing.jpg", corrupt, good)
    assert code == 2 and "Traceback" not in err
    assert [r["ok"] for r in lines] == [True, False, False, True]  # every image still answered, in order
    assert len(err.strip().splitlines()) == 2 and "missing.jpg: no such file" in err and "corrupt" in err

    bad_cam = tmp_path / "cam.json"
    cam_data = json.loads(cam.read_text())
    cam_data["R_wc"][0][0] = 5.0
    bad_cam.write_text(json.dumps(cam_data))
    code, lines, err = locate("--camera", bad_cam, "--vehicle", veh, good)
    assert code == 2 and lines == [] and "R_wc" in err and len(err.strip().splitlines()) == 1

    code, _, err = locate("--camera", cam, "--vehicle", tmp_path / "none.json", good)
    assert code == 2 and "none.json" in err and "Traceback" not in err
