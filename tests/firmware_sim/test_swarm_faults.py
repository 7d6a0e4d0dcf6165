"""The swarm-level fault matrix (issue #7; table and numbers in docs/operations.md "Fault matrix").

One 3-drone flight with a fault schedule, the drones in network namespaces: a hostile host attacks
every map server throughout; drone 1's coopd is killed -9 mid-flight and restarted; drone 2's FC
cable is cut for 10 s and later its radio during a (slowed) transfer; drone 3's camera stalls and
its disk fills up when checkpointing. Then the swarm flies its route once more, fault-free, and
must converge. A cheaper grounded test has one drone with a wrong swarm key (it also runs on
loopback, without namespaces).
After each fault: no daemon crashed or hung, the right counters moved, nothing partial or
unauthenticated entered a global map, RSS stayed within memory_mb, and once the faults cleared the
swarm converged within 0.3 m / 3 deg of the truth. Recovery times are printed.
"""

import json
import re
import signal
import time

import pytest

from coopd.sharing.wire import decode_map
from firmware_sim.netns import netns_unavailable_reason
from firmware_sim.swarm import Swarm, SwarmSettings
from tests.ports import process_slot

REASON = netns_unavailable_reason()
pytestmark = pytest.mark.slow
needs_netns = pytest.mark.skipif(REASON is not None, reason=f"cutting links, a hostile host and a small disk "
                                 f"need network namespaces and root: {REASON}")
PORTS = 22000 + process_slot(40) * 20  # MAVLink from here, map servers on PORTS + 10 (22000-22799)
NET = 100 + process_slot(100)
KEY = b"swarm-fault-test-key-0123456789ab"
MEMORY_MB = 768
STATUS_S = 10.0  # a daemon that does not answer status within this is hung


def settings(drones: int, port_offset: int, **kw) -> SwarmSettings:
    return SwarmSettings(drones=drones, mavlink_base=PORTS + port_offset,
                         sharing_port=PORTS + 10 + port_offset,
                         subnet=f"10.214.{NET}", fc_subnet=f"10.215.{NET}", memory_mb=MEMORY_MB,
                         merge_period_s=5.0, speed=1.0, **kw)


def answering(swarm: Swarm) -> list[dict]:
    """Every daemon's status, each within STATUS_S: none crashed, none hung."""
    swarm.check_alive()
    statuses = [d.status(timeout_s=STATUS_S) for d in swarm.daemons]
    hung = [d.vehicle_id for d, s in zip(swarm.daemons, statuses, strict=True) if s is None]
    assert not hung, f"daemons of drones {hung} do not answer status; logs in {swarm.workdir}"
    return statuses


def within_budget(statuses: list[dict]) -> list[float]:
    """Peak RSS of every daemon in MiB, each asserted within its memory budget."""
    peaks = []
    for s in statuses:
        mem = s["memory"]
        assert mem["peak_rss_bytes"] <= mem["budget_bytes"], (s["vehicle_id"], mem)
        peaks.append(round(mem["peak_rss_bytes"] / 2**20))
    return peaks


class Versions:
    """The highest map version each vehicle was seen publishing (a received map may not exceed it)."""

    def __init__(self):
        self.highest: dict[int, int] = {}

    def see(self, statuses: list[dict]) -> list[dict]:
        for s in statuses:
            self._saw(s["vehicle_id"], s["sharing"]["published_version"] or 0)
        return statuses

    def see_sent(self, vehicle_id: int, log_text: str) -> None:
        """The versions a daemon's log says it sent (a daemon killed -9 may have published more
        since the last status we sampled)."""
        for v in re.findall(rf"\bmap of vehicle {vehicle_id} v(\d+) sent to vehicle", log_text):
            self._saw(vehicle_id, int(v))

    def _saw(self, vehicle_id: int, version: int) -> None:
        self.highest[vehicle_id] = max(version, self.highest.get(vehicle_id, 0))


def stored_maps_complete(swarm: Swarm, i: int, legit: set[int]) -> dict[int, int]:
    """Drone i's received maps: only from legit vehicles, each complete (decodes, CRC checked);
    {vehicle id: version}."""
    s = swarm.daemons[i].status(timeout_s=STATUS_S)
    received = {int(k): v for k, v in s["sharing"]["received_maps"].items()}
    assert set(received) <= legit - {i + 1}, received
    out = {}
    for vid, version in received.items():
        reply, blob = swarm.daemons[i].request("dump-map", {"map": "peer", "vehicle_id": vid}, timeout_s=60,
                                               max_blob_bytes=256 << 20)
        _, meta = decode_map(blob)
        assert meta.vehicle_id == vid and meta.version == reply["version"] >= version
        out[vid] = meta.version
    return out


def check_maps(swarm: Swarm, legit: set[int], versions: Versions) -> None:
    """Every stored peer map complete and at a version its origin really published."""
    stored = [stored_maps_complete(swarm, i, legit) for i in range(len(swarm.daemons))]
    versions.see(answering(swarm))
    for held in stored:
        for vid, version in held.items():
            assert version <= versions.highest[vid], (vid, version, versions.highest)


def merged_only(swarm: Swarm, statuses: list[dict], legit: set[int]) -> None:
    for i, s in enumerate(statuses):
        assert set(swarm.merged_vehicles(s)) <= legit - {i + 1}, s["merges"]


def failures_from(status: dict, address: str) -> dict:
    """Failure counts by cause a daemon charged to a remote address (before it identified itself)."""
    return (status["sharing"]["unidentified_failures"] or {}).get(address, {})


def failures_about(statuses: list[dict], vid: int) -> int:
    """Failures other daemons charged to vehicle vid, plus vid's own failures towards them."""
    total = 0
    for s in statuses:
        for p in s["peers"]:
            if p["vehicle_id"] == vid or s["vehicle_id"] == vid:
                total += sum(p["failures"].values())
    return total


def transfer_through(swarm: Swarm, vid: int, min_left: int) -> dict | None:
    """A map transfer under way over vehicle vid's radio (to it or from it) with at least min_left
    bytes still to come, as the receiving daemon's status shows it; None if there is none."""
    for i, d in enumerate(swarm.daemons):
        s = d.status(timeout_s=STATUS_S) or {}
        for r in s.get("sharing", {}).get("receiving", []):
            if vid in (i + 1, r["vehicle_id"]) and r["announced_bytes"] - r["received_bytes"] >= min_left:
                return {"receiver": i + 1, **r}
    return None


@needs_netns
def test_fault_schedule_during_one_flight():
    # full maps only: the radio is cut while a transfer is under way, which needs transfers longer than
    # the few kB of a map delta (a truncated delta is refused like a truncated map: tests/sharing)
    swarm = Swarm(settings(3, 0, swarm_key=KEY, checkpoint_period_s=3.0,
                           config={"sharing": {"deltas": False}}), say=print)
    legit = {1, 2, 3}
    versions = Versions()
    record: dict = {}
    try:
        swarm.small_disk(2, "32m")
        swarm.start()
        attacker = swarm.start_hostile(seconds=120, max_connections=1200)
        hostile_addr = swarm.lab.address(200)
        t_attack = time.monotonic()
        swarm.wait_for(lambda: all(len(s["sharing"]["received_maps"]) == 2
                                   for s in versions.see(answering(swarm))),
                       180, "every drone has both others' maps while under attack")
        record["maps shared under attack after s"] = round(time.monotonic() - t_attack)

        # ---- just after take-off, at once: drone 1 killed -9, drone 2's FC cable cut, drone 3's camera
        # stalled and its disk full
        before = versions.see(answering(swarm))
        swarm.fly()
        time.sleep(3)
        assert not swarm.landed()
        t0 = time.monotonic()
        assert swarm.kill_daemon(0) == -signal.SIGKILL
        versions.see_sent(1, swarm.daemons[0].log_tail(1 << 24))
        swarm.fc_link(1, up=False)
        swarm.sim.stall_camera(2, 10.0)
        record["disk filled bytes"] = swarm.fill_disk(2)
        failed0 = before[2]["checkpoint"]["failed"]

        def status(i: int) -> dict:
            return swarm.daemons[i].status(timeout_s=STATUS_S) or {}

        swarm.wait_for(lambda: (s := status(1)) and s["link"]["odometry_stale"]
                       and s["mapping"]["state"].startswith("paused"), 30, "drone 2 sees its FC link lost")
        record["FC loss noticed after s"] = round(time.monotonic() - t0, 1)
        b = status(1)
        assert any(p["connected"] for p in b["peers"]), b["peers"]  # its radio still works
        swarm.wait_for(lambda: (s := status(2)) and s["mapping"]["state"] != "mapping", 30,
                       "drone 3 sees its camera stall")
        record["camera stall noticed after s"] = round(time.monotonic() - t0, 1)
        swarm.wait_for(lambda: (s := status(2)) and s["checkpoint"]["failed"] > failed0, 60,
                       "drone 3 counts a failed checkpoint on the full disk")
        c = status(2)
        record["checkpoint error"] = c["checkpoint"]["last_error"]
        record["airborne during the faults"] = not swarm.landed()
        time.sleep(max(0.0, 10.0 - (time.monotonic() - t0)))
        swarm.fc_link(1, up=True)
        swarm.free_disk(2)
        swarm.start_daemon(0)
        t_clear = time.monotonic()
        swarm.wait_mapping([1], "drone 2's FC link restored")
        record["FC link recovery s"] = round(time.monotonic() - t_clear, 1)
        swarm.wait_mapping([2], "drone 3's camera back")
        record["camera recovery s (after the 10 s stall)"] = round(time.monotonic() - t0 - 10.0, 1)
        saved = status(2)["checkpoint"]["saved"]
        swarm.wait_for(lambda: status(2).get("checkpoint", {}).get("saved", 0) > saved, 60,
                       "drone 3 checkpoints again")
        record["checkpoint recovery s (disk freed)"] = round(time.monotonic() - t_clear, 1)
        swarm.wait_mapping([0], "drone 1 restarted")
        swarm.wait_for(lambda: len(status(0).get("sharing", {}).get("received_maps", {})) == 2, 120,
                       "restarted drone 1 has the others' maps again")
        record["kill -9 recovery s (restart to maps back)"] = round(time.monotonic() - t_clear, 1)
        statuses = versions.see(answering(swarm))
        assert statuses[2]["camera"]["stalls"] >= 1 or statuses[2]["camera"]["reconnects"] >= 1, statuses[2]
        check_maps(swarm, legit, versions)

        # ---- drone 2's radio cut during a transfer (slowed so that one is under way), then restored
        swarm.lab.shape(2, "300kbit")
        fail0 = failures_about(statuses, 2)
        deadline = time.monotonic() + 60
        while not (mid := transfer_through(swarm, 2, 16 << 10)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert mid, "no map transfer over drone 2's radio within 60 s"
        swarm.radio(1, up=False)
        t_cut = time.monotonic()
        time.sleep(8)
        answering(swarm)
        swarm.radio(1, up=True)
        swarm.lab.unshape(2)
        v2 = status(1)["sharing"]["published_version"]
        swarm.wait_for(lambda: all((status(i).get("sharing", {}).get("received_maps", {}).get("2") or 0) >= v2
                                   for i in (0, 2)), 120, "drone 2's newest map reaches both others")
        record["radio cut mid-transfer"] = mid
        record["radio recovery s (restore to newest map everywhere)"] = round(time.monotonic() - t_cut - 8, 1)
        statuses = versions.see(answering(swarm))
        record["failures about drone 2 (before, after the cut)"] = (fail0, failures_about(statuses, 2))
        assert failures_about(statuses, 2) > fail0  # the cut connection was noticed, not hung on
        check_maps(swarm, legit, versions)

        # ---- landing, the end of the attack; a second flight once every fault cleared (the first lost
        # too much of drones 2's and 3's maps to overlap), then convergence
        swarm.wait_for(swarm.landed, 400, "every drone landed")
        out, _ = attacker.communicate(timeout=200)
        t_second = time.monotonic()
        swarm.fly()
        swarm.wait_for(swarm.landed, 400, "every drone landed after the second flight")
        record["second flight s"] = round(time.monotonic() - t_second)
        attack = json.loads(out.strip().splitlines()[-1])
        record["attack"] = attack
        t_merge = time.monotonic()
        assert swarm.merge_until_converged(limit_s=240), [status(i).get("merges") for i in range(3)]
        record["converged after landing s"] = round(time.monotonic() - t_merge, 1)
        statuses = versions.see(answering(swarm))
        merged_only(swarm, statuses, legit)
        check_maps(swarm, legit, versions)
        errors, wrong = {}, {}
        for i in range(3):
            for vid, e in swarm.offset_errors(i, statuses).items():
                errors[f"{i + 1}<-{vid}"] = (round(e["error_m"], 3), round(e["error_deg"], 2))
                if not (e["error_m"] < 0.3 and e["error_deg"] < 3.0):
                    wrong[f"{i + 1}<-{vid}"] = e
            charged = failures_from(statuses[i], hostile_addr)
            claimed = sum(sum(p["failures"].values()) for p in statuses[i]["peers"]
                          if p["vehicle_id"] == 250)
            assert sum(charged.values()) + claimed > 0, statuses[i]["sharing"]
            record[f"drone {i + 1} refused from hostile host"] = {**charged, "as vehicle 250": claimed}
        assert attack["connections"] > 0 and attack["closed_by_server"] > 0, attack
        # left open = not closed within 5 s: only a daemon still starting up may be that slow
        assert attack["left_open"] <= attack["connections"] // 100 and attack["slowloris_cut"] > 0, attack
        record["offset errors (m, deg)"] = errors
        record[f"peak RSS MiB (budget {MEMORY_MB})"] = within_budget(statuses)
        assert [d.starts for d in swarm.daemons] == [2, 1, 1]
        assert not wrong, f"merged off the truth (> 0.3 m or 3 deg): {wrong}"
    except BaseException:
        keep = True  # the daemons' logs, for whoever reads the failure
        raise
    else:
        keep = False
    finally:
        print("fault matrix record:", json.dumps(record, indent=1, default=str))
        merges = [(swarm.status(i) or {}).get("merges", {}).get("offsets") for i in range(3)]
        swarm.stop(keep_files=keep)
        if keep:
            print(f"merges: {merges}\nlogs kept in {swarm.workdir}")


def test_wrong_swarm_key_is_refused_until_fixed():
    swarm = Swarm(settings(2, 5, swarm_key=KEY, drone_keys={1: b"the-wrong-key-for-this-swarm-0000"}),
                  say=print)
    record: dict = {}
    try:
        swarm.start()
        t0 = time.monotonic()

        def auth_failures(s: dict) -> int:
            per_peer = sum(p["failures"].get("auth", 0) for p in s["peers"])
            anonymous = sum(c.get("auth", 0) for c in s["sharing"]["unidentified_failures"].values())
            return per_peer + anonymous

        swarm.wait_for(lambda: all(auth_failures(s) > 0 for s in answering(swarm)), 90,
                       "both drones count authentication failures")
        record["auth failures seen after s"] = round(time.monotonic() - t0, 1)
        time.sleep(10)  # several scan periods: still nothing exchanged
        statuses = answering(swarm)
        for s in statuses:
            assert s["sharing"]["received_maps"] == {}, s["sharing"]
            assert swarm.merged_vehicles(s) == {}
        record["auth failures"] = [auth_failures(s) for s in statuses]
        within_budget(statuses)

        # the operator installs the right key and restarts the drone: the two share at once
        swarm.kill_daemon(1, signal.SIGTERM)
        swarm.key_file(1).write_bytes(KEY)
        swarm.start_daemon(1)
        t_fix = time.monotonic()
        swarm.wait_mapping([1], "drone 2 restarted with the right key")
        swarm.wait_for(lambda: all(len(s["sharing"]["received_maps"]) == 1 for s in answering(swarm)), 120,
                       "maps exchanged once the key is right")
        record["shared after key fixed s"] = round(time.monotonic() - t_fix, 1)
        within_budget(answering(swarm))
    finally:
        print("wrong key record:", json.dumps(record, indent=1))
        swarm.stop()
