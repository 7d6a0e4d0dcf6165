"""A live coopd (the real process, default 512 MiB budget, a swarm key) attacked as in the field:
32 key holders send a decompression bomb at once, keyless hosts announce huge transfers, key
holders announce 64 MiB and stall. Its peak RSS stays far under memory_mb, every attack is
counted, and merges are not deferred by anything it was sent."""

import os
import socket
import threading
import time

import pytest
from daemon_harness import Coopd, port_block, swarm_key_file, workdir

from coopd.sharing import mtp, swarmkey
from coopd.sharing.transport import PeerLink, TransportSettings
from tests.sharing.hostile_maps import bomb

pytestmark = pytest.mark.slow

MIB = 1 << 20


def vm_kb(pid: int, field: str) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise KeyError(field)


def test_a_live_daemon_holds_its_budget_under_bombs_and_announcements():
    wd = workdir("coopd-attack-")
    mav_port, share_port = port_block(3)
    d = Coopd(wd, "a", ["--vehicle-id", "1", "--mavlink", f"udpin:127.0.0.1:{mav_port}",
                        "--camera", f"socket:{wd}/no-camera.sock", "--sharing-port", str(share_port),
                        "--memory-mb", "512"]).start()
    socks = []
    try:
        d.wait_running()
        base_kb = vm_kb(d.proc.pid, "VmHWM")
        insider = TransportSettings(swarm_key=swarmkey.read_key_file(swarm_key_file(wd)))
        results = []

        def send_bomb(k: int) -> None:
            link = PeerLink.connect("127.0.0.1", share_port, insider, 10 + k, source=f"127.0.4.{10 + k}")
            try:
                results.append(link.send_map(bomb(10 + k, 1))[0])
            finally:
                link.close()

        threads = [threading.Thread(target=send_bomb, args=(k,)) for k in range(32)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert results == [mtp.ACK_REJECTED] * 32  # 100 M cells each: refused before decoding
        print(f"after the bombs: +{(vm_kb(d.proc.pid, 'VmHWM') - base_kb) / 1024:.0f} MiB")

        for k in range(8):  # keyless hosts: a keyed-looking hello, then a 64 MiB start frame
            s = socket.create_connection(("127.0.0.1", share_port), timeout=5,
                                         source_address=(f"127.0.5.{k + 1}", 0))
            s.sendall(mtp.hello_frame(mtp.Hello(4096, 200 + k, os.urandom(16), True)))
            s.sendall(mtp.start_frame((64 * MIB) // 4096, 4096))
            socks.append(s)
        for k in range(16):  # key holders: 64 MiB announced, 1 MiB sent, then silence
            link = PeerLink.connect("127.0.0.1", share_port, insider, 60 + k, source=f"127.0.6.{k + 1}")
            link.sock.sendall(mtp.start_frame((64 * MIB) // 4096, 4096) + bytes(MIB))
            socks.append(link.sock)
        time.sleep(2.0)
        status = d.status()
        grown_mib = (vm_kb(d.proc.pid, "VmHWM") - base_kb) / 1024
        memory, inflight = status["memory"], status["sharing"]["inflight_bytes"]
        print(f"peak RSS grew by {grown_mib:.0f} MiB; RSS {memory['rss_bytes'] >> 20} MiB of "
              f"{memory['budget_bytes'] >> 20} MiB; in flight {inflight} B")
        # before: 32 bombs took 2.3-2.6 GB, and every announcement +64 MiB; now what was sent (16 MiB)
        assert grown_mib < 48, grown_mib
        assert status["memory"]["rss_bytes"] < status["memory"]["budget_bytes"]
        assert inflight <= 16 * (MIB + mtp.RESERVE_STEP), inflight
        failures = {}
        for p in status["sharing"]["peers"]:
            for cause, n in p["failures"].items():
                failures[cause] = failures.get(cause, 0) + n
        for counts in status["sharing"]["unidentified_failures"].values():
            for cause, n in counts.items():
                failures[cause] = failures.get(cause, 0) + n
        assert failures.get("oversize") == 32 and failures.get("auth", 0) >= 8, failures
        assert status["sharing"]["received_maps"] == {}
        merge, _ = d.request("merge-now")
        assert merge["outcome"] != "deferred", merge
    finally:
        for s in socks:
            s.close()
        d.stop()
