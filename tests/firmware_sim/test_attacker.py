"""The hostile-host attacker of the swarm fault tests, against one real map server on loopback: it
is cut off (garbage, oversized announcements, slowloris), stays within its bounds, and the server
keeps nothing from it."""

import time

from coopd.sharing.service import SharingConfig, SharingService
from coopd.sharing.transport import TransportSettings
from firmware_sim.attacker import HANGUP_S, Attacker, main


def test_attacker_is_cut_off_and_bounded():
    transport = TransportSettings(handshake_timeout=1.0, read_timeout=1.0, transfer_base_s=2.0,
                                  block_size=256)
    config = SharingConfig(vehicle_id=1, listen_host="127.0.0.1", port=0, transport=transport)
    svc = SharingService(config).start()
    try:
        t0 = time.monotonic()
        summary = Attacker([svc.address], block_size=256, seconds=4.0, max_connections=60).run()
        took = time.monotonic() - t0
        stats = svc.stats()
    finally:
        svc.stop()
    assert summary["connections"] <= 60 and took < 4.0 + 3 * HANGUP_S + 2.0  # bounded in count and time
    assert summary["rounds"] >= 1 and summary["closed_by_server"] >= 3 and summary["left_open"] == 0, summary
    assert summary["slowloris_cut"] >= 1, summary  # trickling connections are cut, not kept
    assert stats["received_maps"] == {} and stats["inflight_bytes"] == 0
    failures = sum(sum(c.values()) for c in stats["unidentified_failures"].values())
    failures += sum(sum(p["failures"].values()) for p in stats["peers"])
    assert failures >= summary["closed_by_server"], stats


def test_attacker_cli_prints_a_summary_for_an_absent_target(capsys):
    assert main(["--target", "127.0.0.1:9", "--seconds", "0.2", "--max-connections", "3"]) == 0
    out = capsys.readouterr().out
    assert '"connections": 3' in out and '"refused": 3' in out
