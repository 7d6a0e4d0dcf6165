"""A hostile host on the swarm network, for fault tests: against every map server it is given, it
sends garbage, oversized MTP announcements (start frames and a hello claiming a vehicle id), and
keeps slowloris connections that trickle a byte at a time. Bounded in connections and seconds;
prints one JSON summary line on exit.

    python -m firmware_sim.attacker --target 10.214.1.1:17400 --target ... --seconds 60
"""

from __future__ import annotations

import argparse
import json
import os
import random
import socket
import sys
import time

from coopd.sharing import mtp

MAX_SECONDS = 600.0
MAX_CONNECTIONS = 2000
SLOWLORIS_PER_TARGET = 3
TRICKLE_PERIOD_S = 0.5
HANGUP_S = 5.0
"""A one-shot connection the server has not closed this long after our bytes counts as left open."""


class Attacker:
    """Rounds over the targets: one garbage, one oversized-announcement and one hello-then-oversized
    connection each, while up to SLOWLORIS_PER_TARGET trickling connections per target stay open
    (reopened when the server cuts them). Counts what the servers did to it."""

    def __init__(self, targets: list[tuple[str, int]], block_size: int, seconds: float,
                 max_connections: int, claim_vid: int = 250, seed: int = 7):
        self.targets = targets
        self.claim_vid = claim_vid
        """Vehicle id its hellos claim (one outside the swarm, so its failures are not charged to a drone)."""
        self.block_size = mtp.check_block_size(block_size)
        self.seconds = min(seconds, MAX_SECONDS)
        self.max_connections = min(max_connections, MAX_CONNECTIONS)
        self.rng = random.Random(seed)
        self.connections = 0
        self.refused = 0
        self.closed_by_server = 0
        self.left_open = 0
        self.sent_bytes = 0
        self.slowloris: dict[socket.socket, tuple[tuple[str, int], float]] = {}
        self.slowloris_cut_after_s: list[float] = []

    def _connect(self, target) -> socket.socket | None:
        if self.connections >= self.max_connections:
            return None
        self.connections += 1
        try:
            return socket.create_connection(target, timeout=HANGUP_S)
        except OSError:
            self.refused += 1
            return None

    def _one_shot(self, target, payload: bytes) -> None:
        """Send payload on a fresh connection and see whether the server hangs up within HANGUP_S."""
        s = self._connect(target)
        if s is None:
            return
        try:
            s.sendall(payload)
            self.sent_bytes += len(payload)
            deadline = time.monotonic() + HANGUP_S
            while time.monotonic() < deadline:
                if s.recv(65536) == b"":
                    self.closed_by_server += 1
                    return
            self.left_open += 1
        except TimeoutError:
            self.left_open += 1
        except OSError:  # reset because our bytes were unread: closed too
            self.closed_by_server += 1
        finally:
            s.close()

    def _garbage(self) -> bytes:
        junk = bytearray(self.rng.randbytes(self.rng.randint(100, 3 * self.block_size)))
        if junk[0] == mtp.MARK:
            junk[0] = 0x01
        return bytes(junk)

    def _hello_then_oversized(self) -> bytes:
        hello = mtp.Hello(self.block_size, self.claim_vid, os.urandom(16), keyed=False)
        return mtp.hello_frame(hello) + mtp.start_frame(2**31 - 1, self.block_size)

    def _trickle(self, now: float) -> None:
        """Keep SLOWLORIS_PER_TARGET connections per target open, each sending one byte per period."""
        for s, (_target, opened) in list(self.slowloris.items()):
            try:
                s.send(b"\x01")
                self.sent_bytes += 1
            except OSError:
                self.slowloris_cut_after_s.append(round(now - opened, 2))
                del self.slowloris[s]
                s.close()
        for target in self.targets:
            while sum(1 for t, _ in self.slowloris.values() if t == target) < SLOWLORIS_PER_TARGET:
                s = self._connect(target)
                if s is None:
                    return
                try:
                    s.send(mtp.start_frame(4, self.block_size)[:8])  # a start frame, slowly
                except OSError:
                    s.close()
                    break
                s.setblocking(False)
                self.slowloris[s] = (target, now)

    def run(self) -> dict:
        t0 = time.monotonic()
        rounds = 0
        while time.monotonic() - t0 < self.seconds and self.connections < self.max_connections:
            for target in self.targets:
                self._one_shot(target, self._garbage())
                self._one_shot(target, mtp.start_frame(2**31 - 1, self.block_size))
                self._one_shot(target, self._hello_then_oversized())
            self._trickle(time.monotonic())
            rounds += 1
            time.sleep(TRICKLE_PERIOD_S)
        for s in self.slowloris:
            s.close()
        cut = self.slowloris_cut_after_s
        return {"rounds": rounds, "seconds": round(time.monotonic() - t0, 1), "connections": self.connections,
                "refused": self.refused, "closed_by_server": self.closed_by_server,
                "left_open": self.left_open, "sent_bytes": self.sent_bytes,
                "slowloris_cut": len(cut), "slowloris_longest_s": max(cut, default=None)}


def parse_target(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--target", action="append", type=parse_target, required=True,
                    help="host:port, repeatable")
    ap.add_argument("--seconds", type=float, default=30.0, help=f"how long (at most {MAX_SECONDS:.0f})")
    ap.add_argument("--max-connections", type=int, default=500, help=f"at most {MAX_CONNECTIONS}")
    ap.add_argument("--block-size", type=int, default=mtp.DEFAULT_BLOCK_SIZE)
    ap.add_argument("--claim-vid", type=int, default=250, help="vehicle id its hellos claim")
    args = ap.parse_args(argv)
    summary = Attacker(args.target, args.block_size, args.seconds, args.max_connections, args.claim_vid).run()
    print(json.dumps(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
