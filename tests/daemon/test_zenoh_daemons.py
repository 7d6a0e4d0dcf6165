"""Two coopd daemons sharing over Zenoh only (sharing.transport = "zenoh", swarm key on): each maps
what its camera sees on the ground, receives the other's map through Zenoh (loopback endpoints,
multicast scouting off), and merges it. In this process, against firmware_sim in real time."""


import pytest
from daemon_harness import in_process_memory_mb, run_in_threads, stop_all, wait_until, workdir

from coopd.daemon.config import from_dict
from coopd.daemon.service import Daemon
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world
from tests.loopback_fc import free_port
from tests.ports import zenoh_port

pytest.importorskip("zenoh")
pytestmark = pytest.mark.slow


def test_two_daemons_share_and_merge_over_zenoh():
    wd = workdir("coopd-zenoh-")
    mav_port = free_port()
    zenoh_ports = [zenoh_port(), zenoh_port()]
    key_file = wd / "swarm.key"
    key_file.write_bytes(b"z" * 32)
    key_file.chmod(0o600)
    sim = Simulation(build_world("small_house", 0), 2, seed=0, noise="none", mavlink_base_port=mav_port,
                     camera_dir=str(wd / "cam"))
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
        print({f"vehicle {i + 1}": {k: s["zenoh"].get(k) for k in ("accepted_map", "published", "bytes_in",
                                                                    "bytes_out", "fetched")}
               for i, s in enumerate(status)})
    finally:
        stop_all(sim, daemons, runners, wd)
