"""Every service process leaves its start-up's objects out of the garbage collector's full collections:
run_service (the runner all of them share) on a real Zenoh session, with the RSU as the service."""
import argparse
import gc

import pytest

from protocol.transport.runner import add_service_arguments, run_service
from services.rsu.service import RsuService
from sim.scene import rsu_camera

pytestmark = pytest.mark.integration


def test_a_services_start_up_objects_are_left_out_of_full_collections(free_port):
    p = argparse.ArgumentParser()
    add_service_arguments(p)
    args = p.parse_args(["--listen", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting", "--duration", "0.2"])
    seen = {}

    def build(session, camera):
        svc = RsuService(session, camera, "demo")
        run = svc.run

        def run_and_look(duration):
            # made before the frame loop began: never scanned again by a full collection (125-520 ms each
            # in the demo's RSUs, a frame's processing held up meanwhile)
            seen["pipeline tracked"] = any(o is svc.pipeline for o in gc.get_objects())
            seen["frozen"] = gc.get_freeze_count()
            run(duration)

        svc.run = run_and_look
        return svc

    gc.unfreeze()
    try:
        code = run_service("rsu", args, lambda: rsu_camera("sw", 960, 720), build, lambda camera: camera.id)
    finally:
        gc.unfreeze()
    assert code == 0
    assert seen == {"pipeline tracked": False, "frozen": seen["frozen"]} and seen["frozen"] > 10_000, seen
