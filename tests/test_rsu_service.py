"""The RSU service's own process-wide settings, on a real Zenoh session."""
import gc

import pytest

from services.rsu.service import RsuService
from sim.scene import rsu_camera

pytestmark = pytest.mark.integration


def test_the_rsus_start_up_objects_are_left_out_of_full_collections(zenoh_session, free_port):
    session = zenoh_session("peer", listen=[f"tcp/127.0.0.1:{free_port()}"])
    gc.unfreeze()
    svc = RsuService(session, rsu_camera("sw", 960, 720), "demo")
    try:
        assert any(o is svc.pipeline for o in gc.get_objects())
        svc.run(duration=0.2)
        # made before the frame loop began: never scanned again by a full collection (125-520 ms each in
        # the demo's RSUs, a frame's processing held up meanwhile)
        assert not any(o is svc.pipeline for o in gc.get_objects())
        assert gc.get_freeze_count() > 10_000
    finally:
        svc.close()
        gc.unfreeze()
