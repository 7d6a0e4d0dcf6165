"""Two coopd daemons sharing over Zenoh only (sharing.transport = "zenoh", swarm key on): each maps
what its camera sees on the ground, receives the other's map through Zenoh (loopback endpoints,
multicast scouting off), and merges it where the simulation says it belongs. In this process, against
firmware_sim in real time."""


import pytest
from daemon_harness import (
    in_process_memory_mb,
    offset_error,
    run_in_threads,
    stop_all,
    true_offset,
    wait_until,
    workdir,
)

from coopd.daemon.config import from_dict
from coopd.daemon.service import Daemon
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world
from tests.loopback_fc import free_port
from tests.ports import zenoh_port

pytest.importorskip("zenoh")
pytestmark = pytest.mark.slow

OVERLAPPING_STARTS = [(3.0, 2.5, 0.0, 0.0476), (3.5, 4.0, 0.0, -0.3)]
"""Both drones in small_house's living room facing its east wall and the door to the kitchen, 1.6 m
apart: their views overlap, so their maps decide how they fit. From the world's own start poses (one
in the living room, one in the bedroom, each facing a wall with a door) the grounded views share
nothing: merging can only refuse them or be wrong (there a fit 180 degrees and 7.8 m off validates
on 2 090 agreeing samples, a second 4.5 m off on 1 892, the truth on 48)."""


def test_two_daemons_share_and_merge_over_zenoh():
    wd = workdir("coopd-zenoh-")
    mav_port = free_port()
    zenoh_ports = [zenoh_port(), zenoh_port()]
    key_file = wd / "swarm.key"
    key_file.write_bytes(b"z" * 32)
    key_file.chmod(0o600)
    sim = Simulation(build_world("small_house", 0), 2, seed=0, noise="none", mavlink_base_port=mav_port,
                     camera_dir=str(wd / "cam"), start_poses=OVERLAPPING_STARTS)
    daemons, runners = [], []
    try:
        for i in range(2):
            daemons.append(Daemon(from_dict({
                "vehicle": {"id": i + 1, "mavlink": f"udpin:127.0.0.1:{mav_port + i}"},
                "camera": {"source": f"socket:{sim.vehicle(i).camera_path}"},
                "sharing": {"transport": "zenoh", "swarm_key_file": str(key_file),
                            "zenoh": {"swarm": "test", "listen": [f"tcp/127.0.0.1:{zenoh_ports[i]}"],
                                      "connect": [f"tcp/127.0.0.1:{zenoh_ports[0]}"] if i else [],
                                      "multicast_scouting": False}},
                "merging": {"period_s": 2.0, "confirm_before_fusing": False},
                "daemon": {"state_dir": str(wd / f"state{i}"), "control_socket": str(wd / f"control{i}.sock"),
                           "memory_mb": in_process_memory_mb(), "checkpoint_period_s": 0.0},
            })))
        runners = run_in_threads(daemons)
        sim.start()

        def received():
            return all(d.sharing.received.get(2 - i) is not None for i, d in enumerate(daemons))

        assert wait_until(received, 60, 0.5), [d.handle_status({})["sharing"] for d in daemons]
        status = [d.handle_status({})["sharing"] for d in daemons]
        for s in status:
            assert s["transports"] == ["zenoh"] and s["listen"] is None
            assert s["zenoh"]["peers"] and s["zenoh"].get("accepted_map", 0) >= 1, s["zenoh"]
            assert not any(k.startswith("dropped_") for k in s["zenoh"]), s["zenoh"]
        merged = wait_until(lambda: all(d.merger.offsets.get(2 - i, {}).get("accepted")
                                        for i, d in enumerate(daemons)), 60, 0.5)
        assert merged, [d.handle_status({})["merges"] for d in daemons]
        origins = [d.handle_status({})["link"]["map_origin_fc_enu"] for d in daemons]
        errors = []
        starts = [v.true_start_pose for v in sim.vehicles]
        for i, d in enumerate(daemons):
            truth = true_offset(starts[i], origins[i], starts[1 - i], origins[1 - i])
            errors.append(offset_error(d.merger.offsets[2 - i]["transform"], truth))
        print({f"vehicle {i + 1}": {**{k: s["zenoh"].get(k) for k in ("accepted_map", "published", "bytes_in",
                                                                      "bytes_out", "fetched")},
                                    "offset error vs truth (m, deg)": [round(e, 3) for e in errors[i]]}
               for i, s in enumerate(status)})
        assert all(metres < 0.15 and degrees < 2.0 for metres, degrees in errors), (errors, [
            d.merger.offsets for d in daemons])
    finally:
        stop_all(sim, daemons, runners, wd)
