"""scripts/benchmarks/swarm.py: its pure parts (convergence checks, offsets against the truth, TOML)."""

import importlib.util
import math
import os
import tomllib
from pathlib import Path

import numpy as np

from coopd.daemon.merger import offset_summary
from coopd.geometry import rigid, rotation_z

ROOT = Path(__file__).resolve().parents[2]
spec = importlib.util.spec_from_file_location("bench_swarm", ROOT / "scripts" / "benchmarks" / "swarm.py")
swarm = importlib.util.module_from_spec(spec)
spec.loader.exec_module(swarm)


def status(vid, held=(), accepted=(), refused=(), transforms=None, provisional=()):
    """A daemon status reduced to what the checks read."""
    transforms = transforms or {}
    offsets = {str(v): {"accepted": True, "provisional": v in provisional,
                        **offset_summary(transforms.get(v, np.eye(4)))} for v in accepted}
    offsets |= {str(v): {"accepted": False, **offset_summary(np.eye(4))} for v in refused}
    peers = [{"vehicle_id": v, "map_version": 1} for v in held] + [{"vehicle_id": 99, "map_version": None}]
    return {"vehicle_id": vid, "peers": peers, "merges": {"offsets": offsets}}


def test_holds_all_maps_needs_every_other_vehicle():
    ids = [1, 2, 3]
    assert swarm.holds_all_maps(status(1, held=[2, 3]), ids)
    assert not swarm.holds_all_maps(status(1, held=[2]), ids)
    assert swarm.holds_all_maps(status(2, held=[1, 3, 7]), ids)


def test_a_daemon_holding_every_map_and_the_global_map_is_not_polled_again():
    last = {1: status(1, held=[2, 3], accepted=[2, 3]), 2: status(2, held=[1], accepted=[1, 3]),
            3: status(3, held=[1, 2], accepted=[1, 2])}
    # 1: done; 2: the global map once but a map missing; 3: every map, global map not seen yet
    assert swarm.still_waiting([1, 2, 3], {1: 5.0, 2: 6.0}, last) == [2, 3]
    assert swarm.still_waiting([1, 2, 3], {}, {}) == [1, 2, 3]


def test_holds_global_counts_only_accepted_offsets():
    ids = [1, 2, 3]
    assert swarm.holds_global(status(1, accepted=[2, 3]), ids)
    assert not swarm.holds_global(status(1, accepted=[2], refused=[3]), ids)
    assert swarm.accepted_offsets(status(3, accepted=[1], refused=[2])) == {1}
    assert not swarm.holds_global(status(1, accepted=[2, 3], provisional=[3]), ids)  # held out of it


def test_judge_offsets_tells_correct_from_wrong_merges():
    truth2 = rigid(rotation_z(math.radians(30)), [2.0, -1.0, 0.5])
    truth3 = rigid(rotation_z(math.radians(-90)), [0.0, 4.0, 0.0])
    near = rigid(rotation_z(math.radians(31)), [2.1, -1.0, 0.5])  # 0.1 m, 1 deg off: correct
    flipped = rigid(rotation_z(math.radians(90)), [0.0, 4.0, 0.0])  # 180 deg off: wrong
    st = status(1, accepted=[2, 3], refused=[4], transforms={2: near, 3: flipped})
    j = swarm.judge_offsets(st["merges"]["offsets"], {2: truth2, 3: truth3, 4: np.eye(4)}, 0.3, 3.0)
    assert j["accepted"] == [2, 3] and j["correct"] == [2] and j["wrong"] == [3] and list(j["refused"]) == [4]
    te, re = j["errors"][2]
    assert abs(te - 0.1) < 1e-3 and abs(re - 1.0) < 0.01
    assert abs(j["errors"][3][1] - 180.0) < 0.01
    held = status(1, accepted=[2], provisional=[2])["merges"]["offsets"]
    j = swarm.judge_offsets(held, {2: truth2}, 0.3, 3.0)
    assert j["accepted"] == [] and j["refused"][2].startswith("provisional")


def test_displacement_is_the_mean_shift_of_the_maps_points():
    truth = rigid(rotation_z(math.radians(30)), [2.0, -1.0, 0.5])
    points = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    shifted = rigid(None, [0.1, 0.0, 0.0]) @ truth
    assert abs(swarm.displacement_m(offset_summary(shifted)["transform"], truth, points) - 0.1) < 1e-4
    turned = truth @ rigid(rotation_z(math.radians(1)))  # 1 deg about the map origin: 0 and 0.175 m
    assert abs(swarm.displacement_m(turned, truth, points) - 10 * math.radians(1) / 2) < 1e-3
    st = status(1, accepted=[2], transforms={2: shifted})
    j = swarm.judge_offsets(st["merges"]["offsets"], {2: truth}, 0.3, 3.0, {2: points})
    assert abs(j["errors"][2][2] - 0.1) < 1e-3


def test_offset_errors_reads_the_status_transform_row_major():
    t = rigid(rotation_z(0.2), [1.0, 2.0, 3.0])
    assert max(swarm.offset_errors(offset_summary(t)["transform"], t)) < 1e-4
    te, _ = swarm.offset_errors(offset_summary(t)["transform"], t.T)  # transposed: translation lost
    assert te > 1.0


def test_daemon_configs_round_trip_with_the_zenoh_table():
    bench = swarm.Swarm([], {}, Path("/tmp"), transport="zenoh")
    table = {"vehicle": {"id": 3, "mavlink": "udpin:127.0.0.1:18503"},
             "sharing": {"port": 18003, "peers": ["127.0.0.1:18001", "127.0.0.1:18002"],
                         **bench.zenoh_sharing(3)},
             "merging": {"distributed": True, "period_s": 10.0}}
    assert tomllib.loads(swarm.render_config(table)) == table
    assert table["sharing"]["zenoh"]["connect"] == [f"tcp/127.0.0.11:{swarm.ZENOH_BASE + 1}"]
    assert swarm.Swarm([], {}, Path("/tmp")).zenoh_sharing(3) == {}  # MTP: nothing added


def test_comparisons_are_distributed_over_central():
    rows = [{"drones": 4, "mode": "central", "merge_cpu_s": None, "merging_thread_cpu_s": 40.0,
             "t_global_s": 20.0},
            {"drones": 4, "mode": "distributed", "merge_cpu_s": None, "merging_thread_cpu_s": 10.0,
             "t_global_s": 8.0}]
    assert swarm.comparisons(rows) == [{"drones": 4, "cpu": "merging_thread_cpu_s", "merge_cpu_ratio": 0.25,
                                        "t_global_ratio": 0.4}]


def test_cpu_s_reads_this_process_and_its_threads():
    import threading

    busy = sum(i * i for i in range(300_000))  # some CPU of our own
    assert busy > 0
    whole = swarm.cpu_s(f"/proc/{os.getpid()}/stat")
    main = swarm.cpu_s(f"/proc/{os.getpid()}/task/{threading.get_native_id()}/stat")
    assert whole is not None and main is not None and 0 < main <= whole + 0.02
    assert swarm.cpu_s("/proc/0/stat") is None


def test_gave_up_needs_all_maps_idle_no_new_merge_and_an_unchanged_skip():
    ids = [1, 2, 3]

    def st(done, unchanged, state="idle", held=(2, 3)):
        s = status(1, held=held, accepted=[2])
        s["merges"] |= {"done": done, "unchanged": unchanged, "state": state}
        return s

    assert swarm.gave_up(st(1, 0), st(1, 1), ids)
    assert not swarm.gave_up(st(1, 1), st(1, 1), ids)  # no skip seen yet
    assert not swarm.gave_up(st(1, 0), st(2, 1), ids)  # merged again: may still converge
    assert not swarm.gave_up(st(1, 0), st(1, 1, state="merging"), ids)
    assert not swarm.gave_up(st(1, 0, held=[2]), st(1, 1, held=[2]), ids)  # a map still to come
    assert not swarm.gave_up({"merges": {}}, {"vehicle_id": 1, "peers": [], "merges": {}}, ids)  # old daemon


def test_sharing_failures_add_up_every_peer_and_unidentified_sender():
    sharing = {"peers": [{"vehicle_id": 2, "failures": {"busy": 2, "auth": 1}}, {"vehicle_id": 3},
                         {"vehicle_id": 4, "failures": {"busy": 1}}],
               "unidentified_failures": {"127.0.0.9": {"auth": 4}}}
    assert swarm.sharing_failures(sharing) == {"busy": 3, "auth": 5}
    assert swarm.sharing_failures({}) == {}


def test_flight_description_says_a_reduced_camera_rate():
    default = swarm.simset.camera().rate_hz
    assert "reduced" not in swarm.flight_description("bookstore", 1, 30, default)
    said = swarm.flight_description("bookstore", 1, 30, default / 2)
    assert f"{default / 2:g} Hz (reduced from the emulator's {default:g} Hz)" in said and "30 drones" in said


def test_the_polled_status_sections_exist_and_hold_what_the_checks_read():
    from coopd.daemon.status import SECTIONS, check_sections

    assert check_sections(swarm.POLLED_SECTIONS) <= SECTIONS.keys()
    assert {"peers", "merges"} <= set(swarm.POLLED_SECTIONS)  # holds_all_maps, holds_global, gave_up
