"""Map sharing benchmark: end-to-end time (encode/compress + MTP transfer + receive, check and
decode/decompress on the receiver) for building-like maps of the thesis' sizes (Table 4:
≈6.25 M, 25 M, 110.25 M cells), on loopback and over a 54 Mbit/s tc-tbf shaped veth between two
network namespaces, with compression (the default encoding) and without (raw).

The receiver is a real SharingService in its own process (inspect + full decode before the ack),
the sender a PeerLink: the time is taken from encode start to the receiver's ack, so it covers
exactly what a peer waits for. Prints JSON and writes out/bench/share.json.
Usage: scripts/bench share [--sizes 6M,25M,110M] [--repeat 3] [--no-shaped] [--rate-mbit 54]

--delta: bytes on the wire per drone per minute of an exploration flight, full maps against deltas.
firmware_sim drones fly their routes in a world (in-process, mapped with coopd's Mapper; flown once and
cached in out/bench/); every simulated second each drone's map, cropped to its known box as the daemon
publishes it (once a second when it changed), goes from a real SharingService to another on loopback,
once with deltas off and once on, each version acknowledged before the next. Reported per drone: MTP
bytes sent (frames and data blocks; acks and TCP/IP headers not counted) per minute of flight, over the
whole flight and in steady exploration (after the first --steady-after-s seconds), and the ratio; the
receiver's last map is checked to be the sender's byte for byte. Writes out/bench/share_delta.json.
With --transport zenoh (or mtp,zenoh) the same recording also goes over Zenoh (two Zenoh-only services
on loopback TCP, shared memory off as always): the envelopes the drone put (counted once per publication,
however many subscribers) and the TCP payload bytes its session sent on the link (the kernel's count,
read with ss: Zenoh's framing, declarations and keep-alives included), and the link's idle upkeep.
Usage: scripts/bench share --delta [--world hospital] [--drones 3] [--block-sizes 4096,1024]
       [--transport mtp,zenoh]
"""

import argparse
import json
import os
import platform
import queue
import shutil
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from coopd.grid import OccupancyGrid  # noqa: E402
from coopd.sharing import wire  # noqa: E402
from coopd.sharing.service import SharingConfig, SharingService, wire_inspect, wire_verifier  # noqa: E402
from coopd.sharing.transport import PeerLink, TransportSettings  # noqa: E402
from coopd.sharing.wire_options import DEFAULT_BRICK_EDGE  # noqa: E402
from tests.sharing.realistic_maps import building_map  # noqa: E402

SIZES = {"6M": (250, 250, 100), "25M": (500, 500, 100), "110M": (1050, 1050, 100)}
"""Thesis Table 4 shapes: bookstore (6.25 M), hospital UAV 1 (25 M), racetrack UAV 1 (110.25 M)."""
EXPLORED = {"6M": 0.25, "25M": 0.15, "110M": 0.06}
ENCODINGS = ("default", "raw")
"""Compressed (the wire default) and uncompressed; --encodings adds e.g. 'thesis' (the thesis codec)."""
THESIS_ANCHOR = {"share_110M_compressed_s": 1.75, "share_110M_uncompressed_s": 200.0,
                 "source": "thesis §10.2, i7-4510U, C++, transfer only"}
GOAL_110M_LOOPBACK_S = 0.5
SETTINGS = TransportSettings(max_bytes=256 << 20, max_cells=200_000_000, max_inflight_bytes=512 << 20,
                             read_timeout=30.0, transfer_base_s=120.0)
BENCH_KEY = b"coopd share bench swarm key 0123"
"""--key: both ends use this swarm key, so transfers are authenticated and encrypted as in a keyed swarm."""


def key_args() -> list[str]:
    """The --key flag for the bench's own subprocesses when this run is keyed."""
    return ["--key"] if SETTINGS.swarm_key is not None else []


# --------------------------------------------------------------------------------- receiver
def serve(host: str, port: int) -> None:
    """Receiver process: a SharingService that fully decodes every map before acknowledging it."""
    cfg = SharingConfig(vehicle_id=2, listen_host=host, port=port, transport=SETTINGS)
    verify_inner = wire_verifier(SETTINGS.max_cells, SETTINGS.max_bytes)
    out_lock = threading.Lock()

    def verify(message: bytes) -> None:
        t = time.perf_counter()
        verify_inner(message)
        line = json.dumps({"decode_s": time.perf_counter() - t, "bytes": len(message)})
        with out_lock:
            print(line, flush=True)

    warm_up()
    svc = SharingService(cfg, inspect=wire_inspect, verify=verify).start()
    print("ready", flush=True)
    sys.stdin.read()  # until the orchestrator closes our stdin
    svc.stop()


# --------------------------------------------------------------------------------- sender
def warm_up() -> None:
    """Compile the codec kernels (numba JIT) before anything is timed."""
    grid = OccupancyGrid(building_map((60, 60, 20), 0.5, 0), 0.1)
    for enc in wire.ENCODINGS:
        wire.decode_map(wire.encode_map(grid, wire.MapMeta(0, 1), enc))


def make_grid(size: str, seed: int = 1) -> OccupancyGrid:
    return OccupancyGrid(building_map(SIZES[size], EXPLORED[size], seed), 0.1)


def send_runs(host: str, port: int, size: str, encoding: str, repeat: int, version0: int) -> dict:
    """Encode + send `repeat` times (new version each time); best and all end-to-end times."""
    warm_up()
    grid = make_grid(size)
    link = PeerLink.connect(host, port, SETTINGS, 1)
    runs = []
    try:
        for r in range(repeat):
            t0 = time.perf_counter()
            msg = wire.encode_map(grid, wire.MapMeta(1, version0 + r, time.time()), encoding)
            t1 = time.perf_counter()
            status, ack_s = link.send_map(msg)
            t2 = time.perf_counter()
            if status != 0:
                raise RuntimeError(f"receiver refused the map (ack status {status})")
            runs.append({"encode_s": t1 - t0, "send_to_ack_s": t2 - t1, "end_to_end_s": t2 - t0,
                         "message_bytes": len(msg)})
    finally:
        link.close()
    best = min(runs, key=lambda x: x["end_to_end_s"])
    return {"cells": grid.size, "encoding": wire.DEFAULT_ENCODING if encoding == "default" else encoding,
            **best, "runs_end_to_end_s": [round(x["end_to_end_s"], 4) for x in runs]}


# --------------------------------------------------------------------------------- deltas
DELTA_GOAL_RATIO = 10.0
"""Steady exploration should cost at most a tenth of the bytes with deltas."""


def flight_recording(world: str, seed: int, drones: int) -> list[list[tuple[float, bytes]]]:
    """Per drone, (simulated time, full map message) of every second its map changed: what its daemon
    publishes (the map cropped to its known box plus the snapshot pad). Cached in out/bench/."""
    import numpy as np

    path = ROOT / "out" / "bench" / f"share_flight_{world}_s{seed}_n{drones}.npz"
    if path.exists():
        with np.load(path) as z:
            out = []
            for i in range(drones):
                data = z[f"d{i}_data"]
                out.append([(float(t), data[int(a):int(b)].tobytes()) for t, a, b in z[f"d{i}_index"]])
            return out
    from coopd.daemon.service import SNAPSHOT_PAD_CELLS
    from firmware_sim import simset

    seen = [0] * drones
    out: list[list[tuple[float, bytes]]] = [[] for _ in range(drones)]

    def each_second(t, mappers):
        for i, m in enumerate(mappers):
            if m.version > seen[i]:
                seen[i] = m.version
                grid = m.grid.shrunk(pad=SNAPSHOT_PAD_CELLS)
                out[i].append((t, wire.encode_map(grid, wire.MapMeta(i + 1, m.version, t))))

    print(f"flying {drones} drones in {world} (seed {seed}) once, to record their maps ...", file=sys.stderr)
    simset.fly(world, seed, drones, each_second=each_second)
    arrays = {}
    for i, seq in enumerate(out):
        ends = np.cumsum([len(m) for _, m in seq])
        arrays[f"d{i}_data"] = np.frombuffer(b"".join(m for _, m in seq), dtype=np.uint8)
        arrays[f"d{i}_index"] = np.array([(t, e - len(m), e) for (t, m), e in zip(seq, ends, strict=True)],
                                         dtype=np.float64)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return out


RX_VID = 200
"""The receiving vehicle of a replay."""
IDLE_SAMPLE_S = 5.0
"""--transport zenoh: seconds the link is watched idle before a replay, for its upkeep in bytes per minute."""


class MtpPair:
    """A sender and a receiver SharingService over MTP on loopback: the receiver acknowledges each
    version. Counts what the sender's MTP link to the receiver sent: map/delta messages, and on the wire
    hello, frames and data blocks (acks and TCP/IP headers not counted)."""

    transport = "mtp"

    def __init__(self, vid: int, deltas: bool, block_size: int, brick_edge: int):
        settings = replace(SETTINGS, block_size=block_size, read_timeout=5.0, transfer_base_s=10.0)
        verify = wire_verifier(settings.max_cells, settings.max_bytes)
        self.vid = vid
        self.rx = SharingService(SharingConfig(vehicle_id=RX_VID, listen_host="127.0.0.1", port=0,
                                               deltas=deltas, transport=settings),
                                 inspect=wire_inspect, verify=verify).start()
        self.tx = SharingService(SharingConfig(vehicle_id=vid, listen_host="127.0.0.2", port=0, deltas=deltas,
                                               delta_brick_edge=brick_edge, scan_period=0.1,
                                               transport=settings, peers=(f"127.0.0.1:{self.rx.address[1]}",))
                                 ).start()

    def publish(self, message: bytes, version: int, grid) -> None:
        self.tx.publish(message, version, grid)

    def delivered(self, version: int) -> bool:
        return self.tx.peers.has_version(RX_VID, self.vid) == version  # stored, acknowledged and counted

    def counters(self) -> dict:
        p = peer(self.tx, RX_VID)
        return {"message_bytes": p["bytes_sent"], "wire_bytes": p["wire_bytes_sent"],
                "maps_sent": p["maps_sent"], "deltas_sent": p["deltas_sent"],
                "delta_fallbacks": p["delta_fallbacks"]}

    def stop(self) -> None:
        self.tx.stop()
        self.rx.stop()


class ZenohPair:
    """A sender and a receiver SharingService over Zenoh on loopback (TCP endpoints on 127.0.0.1, multicast
    scouting off; the receiver connects to the sender). Nothing is acknowledged: a version is delivered when
    the receiver holds it and the sender counted its put. Counts the envelopes the sender put or replied
    with (Zenoh's bytes_out: once per publication, whatever the number of subscribers) and on the wire
    the TCP payload bytes the sender's session sent on its link, as the kernel counts them (ss):
    Zenoh's framing, declarations and keep-alives included, TCP/IP headers not."""

    transport = "zenoh"

    def __init__(self, vid: int, deltas: bool, brick_edge: int, idle_sample_s: float = IDLE_SAMPLE_S):
        from coopd.sharing.zenoh_link import ZenohSettings
        from tests.ports import zenoh_port

        verify = wire_verifier(SETTINGS.max_cells, SETTINGS.max_bytes)
        self.vid, self.ports, self.puts = vid, (zenoh_port(), zenoh_port()), 0

        def zenoh(listen: int, connect=()):
            return ZenohSettings(swarm="bench", listen=(f"tcp/127.0.0.1:{listen}",),
                                 connect=tuple(f"tcp/127.0.0.1:{p}" for p in connect),
                                 multicast_scouting=False)

        self.tx = SharingService(SharingConfig(vehicle_id=vid, mtp=False, deltas=deltas,
                                               delta_brick_edge=brick_edge, zenoh=zenoh(self.ports[0]),
                                               transport=SETTINGS)).start()
        self.rx = SharingService(SharingConfig(vehicle_id=RX_VID, mtp=False, deltas=deltas,
                                               zenoh=zenoh(self.ports[1], [self.ports[0]]),
                                               transport=SETTINGS),
                                 inspect=wire_inspect, verify=verify).start()
        try:
            deadline = time.monotonic() + 15.0
            while not self.tx.stats()["zenoh"]["peers"]:
                if time.monotonic() > deadline:
                    raise RuntimeError("the Zenoh sessions did not connect within 15 s")
                time.sleep(0.01)
            before = self.link_bytes_sent()
            time.sleep(idle_sample_s)
            self.idle_bytes_per_min = round((self.link_bytes_sent() - before) * 60 / idle_sample_s)
        except BaseException:
            self.stop()
            raise

    def link_bytes_sent(self) -> int:
        """TCP payload bytes sent so far by the sender's sockets of the link: those on its listening port,
        and any it opened to the receiver's."""
        out = subprocess.run(["ss", "-tinH", "state", "established",
                              f"( sport = :{self.ports[0]} or dport = :{self.ports[1]} )"],
                             check=True, capture_output=True, text=True, timeout=10).stdout
        counts = [int(w.split(":", 1)[1]) for w in out.split() if w.startswith("bytes_sent:")]
        if not counts:
            raise RuntimeError(f"ss shows no bytes_sent for the Zenoh link (kernel >= 4.19 needed): {out!r}")
        return sum(counts)

    def publish(self, message: bytes, version: int, grid) -> None:
        self.tx.publish(message, version, grid)
        self.puts += 1

    def delivered(self, version: int) -> bool:
        z = self.tx.stats()["zenoh"]
        return (self.rx.received.version(self.vid) == version
                and z.get("published", 0) + z.get("published_delta", 0) == self.puts)

    def counters(self) -> dict:
        z = self.tx.stats()["zenoh"]
        return {"message_bytes": z.get("bytes_out", 0), "wire_bytes": self.link_bytes_sent(),
                "maps_sent": z.get("published", 0), "deltas_sent": z.get("published_delta", 0),
                "delta_fallbacks": self.rx.stats()["zenoh"].get("delta_refetch", 0)}

    def stop(self) -> None:
        self.rx.stop()
        self.tx.stop()


def replay(sequence, pair, steady_after_s: float) -> dict:
    """One drone's recorded maps from pair.tx to pair.rx, each version delivered before the next; what
    the sender sent (pair.counters()), over the flight and after steady_after_s."""
    steady_from = None
    publish_s = []
    try:
        for t, message in sequence:
            grid, meta = wire.decode_map(message)
            if steady_from is None and t >= steady_after_s:
                steady_from = pair.counters()
            t0 = time.perf_counter()
            pair.publish(message, meta.version, grid)
            publish_s.append(time.perf_counter() - t0)
            deadline = time.monotonic() + 30.0
            while not pair.delivered(meta.version):
                if time.monotonic() > deadline:
                    raise RuntimeError(f"vehicle {pair.vid} v{meta.version} did not arrive within 30 s")
                time.sleep(0.002)
        identical = bytes(pair.rx.received.get(pair.vid).data) == sequence[-1][1]
        last = pair.counters()
    finally:
        pair.stop()
    flight_s = sequence[-1][0]
    steady_from = steady_from or last
    steady_s = max(flight_s - steady_after_s, 1e-9)

    def steady_per_min(key: str) -> int:
        return round((last[key] - steady_from[key]) * 60 / steady_s)

    return {"versions": len(sequence), "flight_s": round(flight_s, 1), "identical": identical,
            **{k: last[k] for k in ("maps_sent", "deltas_sent", "delta_fallbacks", "message_bytes",
                                    "wire_bytes")},
            "wire_bytes_per_min": round(last["wire_bytes"] * 60 / flight_s),
            "steady_wire_bytes_per_min": steady_per_min("wire_bytes"),
            "steady_message_bytes_per_min": steady_per_min("message_bytes"),
            "publish_ms_mean": round(1000 * sum(publish_s) / len(publish_s), 2),
            **({"idle_link_bytes_per_min": pair.idle_bytes_per_min} if pair.transport == "zenoh" else {})}


def delta_costs(size: str = "25M") -> dict:
    """Seconds of each step of a delta on a building map of `size` with a 10x10x10 patch changed: the
    ledger's hashing (per published map), making the delta, and the receiver's rebuild and encode;
    next to the full encode the daemon does for every published map anyway."""
    from coopd.sharing import delta

    grid = make_grid(size)
    first = wire.encode_map(grid, wire.MapMeta(1, 1, 0.0))
    ledger = delta.BrickLedger(DEFAULT_BRICK_EDGE)
    ledger.record(grid, 1, first)
    changed = grid.copy()
    changed.cells[100:110, 100:110, 10:20] = 100
    t0 = time.perf_counter()
    second = wire.encode_map(changed, wire.MapMeta(1, 2, 0.0))
    t1 = time.perf_counter()
    ledger.record(changed, 2, second)
    t2 = time.perf_counter()
    data = ledger.delta_for(1)
    t3 = time.perf_counter()
    base = wire.decode_map(first)
    t4 = time.perf_counter()
    rebuilt, meta = delta.apply_delta(*base, data)
    t5 = time.perf_counter()
    again = wire.encode_map(rebuilt, meta)
    t6 = time.perf_counter()
    if again != second:
        raise RuntimeError("the rebuilt map is not the sender's")
    return {"cells": grid.size, "full_message_bytes": len(second), "delta_bytes": len(data),
            "full_encode_s": round(t1 - t0, 4), "ledger_record_s": round(t2 - t1, 4),
            "make_delta_s": round(t3 - t2, 4), "receiver_decode_base_s": round(t4 - t3, 4),
            "receiver_apply_s": round(t5 - t4, 4), "receiver_encode_s": round(t6 - t5, 4)}


def _ratio(full: float, delta: float) -> float | None:
    return round(full / delta, 2) if delta > 0 else None


def peer(svc: SharingService, vid: int) -> dict:
    return next(p for p in svc.stats()["peers"] if p["vehicle_id"] == vid)


WHAT = {
    "mtp": "MTP bytes one drone sends one peer (wire: hello, frames and data blocks; acks and TCP/IP headers "
           "not counted)",
    "zenoh": "Zenoh bytes one drone sends (message: envelopes put or replied, counted once per publication "
             "whatever the number of subscribers; wire: TCP payload its session sent on its one link, Zenoh "
             "framing, declarations and keep-alives included, TCP/IP headers not; with more peers each link "
             "carries it again)",
}


def run_delta(world: str, seed: int, drones: int, block_sizes, steady_after_s: float, brick_edge: int,
              transports=("mtp",)) -> dict:
    warm_up()
    recording = flight_recording(world, seed, drones)
    setups = [("mtp", bs) for bs in block_sizes if "mtp" in transports]
    setups += [("zenoh", None)] * ("zenoh" in transports)  # Zenoh has no block size
    rows = []
    for transport, bs in setups:
        for deltas in (False, True):
            per_drone = []
            for seq in recording:
                vid = wire.peek(seq[0][1]).vehicle_id
                pair = (MtpPair(vid, deltas, bs, brick_edge) if transport == "mtp"
                        else ZenohPair(vid, deltas, brick_edge))
                per_drone.append(replay(seq, pair, steady_after_s))
            keys = ("wire_bytes_per_min", "steady_wire_bytes_per_min", "steady_message_bytes_per_min")
            mean = {k: round(sum(d[k] for d in per_drone) / len(per_drone)) for k in keys}
            rows.append({"transport": transport, "block_size": bs, "deltas": deltas, **mean,
                         "per_drone": per_drone})
            print(f"{transport} block {bs} deltas {deltas}: {mean}", file=sys.stderr)
    ratios = []
    for transport, bs in setups:
        full, dlt = (next(r for r in rows if (r["transport"], r["block_size"], r["deltas"]) == setup)
                     for setup in ((transport, bs, False), (transport, bs, True)))
        ratios.append({"transport": transport, "block_size": bs,
                       **{f"{k}ratio": _ratio(full[f"{k}bytes_per_min"], dlt[f"{k}bytes_per_min"])
                          for k in ("wire_", "steady_wire_", "steady_message_")}})
    judged = {t: next(r for r in ratios if r["transport"] == t) for t in transports}  # first block size
    return {"benchmark": "share --delta", "host": platform.node(), "cpus": os.cpu_count(), "world": world,
            "seed": seed, "drones": drones, "brick_edge": brick_edge, "steady_after_s": steady_after_s,
            "what": {t: WHAT[t] + " per minute of flight, its map published every second it changed, full "
                     "maps vs deltas; steady = after steady_after_s" for t in transports},
            "ratios": ratios, "goal_steady_ratio": DELTA_GOAL_RATIO,
            "goal_met": {t: (r["steady_wire_ratio"] or 0) >= DELTA_GOAL_RATIO for t, r in judged.items()},
            "all_identical": all(d["identical"] for r in rows for d in r["per_drone"]),
            "costs_25M": delta_costs(), "runs": rows}


# --------------------------------------------------------------------------------- orchestration
class Receiver:
    def __init__(self, argv_prefix: list[str], host: str, port: int):
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        self.proc = subprocess.Popen([*argv_prefix, sys.executable, __file__, *key_args(), "--serve", host,
                                      str(port)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        self.lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [self.lines.put(x) for x in self.proc.stdout], daemon=True).start()
        if self.lines.get(timeout=60).strip() != "ready":
            raise RuntimeError("receiver did not start")

    def decode_times(self) -> list[float]:
        out = []
        while True:
            try:
                out.append(json.loads(self.lines.get_nowait())["decode_s"])
            except queue.Empty:
                return out

    def stop(self) -> None:
        self.proc.stdin.close()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_loopback(sizes, repeat, encodings) -> list[dict]:
    port = free_port()
    rx = Receiver([], "127.0.0.1", port)
    results = []
    try:
        version = 1
        for size in sizes:
            for enc in encodings:
                r = send_runs("127.0.0.1", port, size, enc, repeat, version)
                version += repeat
                decodes = rx.decode_times()
                r.update(size=size, link="loopback",
                         receiver_decode_s=round(min(decodes), 4) if decodes else None)
                results.append(r)
                print(f"loopback {size} {r['encoding']}: {r['end_to_end_s']:.3f} s", file=sys.stderr)
    finally:
        rx.stop()
    return results


def _send_one(barrier, link, message, times, i) -> None:
    barrier.wait()
    times[i] = link.send_map(message)[1]


def run_fan_in(counts, size: str = "25M") -> list[dict]:
    """N senders at once into one receiver (thread per connection): wall time for all N maps."""
    port = free_port()
    rx = Receiver([], "127.0.0.1", port)
    warm_up()
    grid = make_grid(size)
    results = []
    version = 1
    try:
        for n in counts:
            msgs = [wire.encode_map(grid, wire.MapMeta(100 + i, version, 0.0)) for i in range(n)]
            version += 1
            links = [PeerLink.connect("127.0.0.1", port, SETTINGS, 100 + i, source=f"127.0.3.{10 + i}")
                     for i in range(n)]  # one address per drone, as in a swarm
            times = [0.0] * n
            barrier = threading.Barrier(n)
            t0 = time.perf_counter()
            threads = [threading.Thread(target=_send_one, args=(barrier, links[i], msgs[i], times, i))
                       for i in range(n)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            wall = time.perf_counter() - t0
            for link in links:
                link.close()
            rx.decode_times()
            results.append({"senders": n, "size": size, "message_bytes": len(msgs[0]),
                            "wall_s": round(wall, 4), "slowest_transfer_s": round(max(times), 4),
                            "maps_per_s": round(n / wall, 1)})
            print(f"fan-in {n} x {size}: {wall:.3f} s", file=sys.stderr)
    finally:
        rx.stop()
    return results


def run_shaped(sizes, rate_mbit: float, encodings) -> tuple[list[dict], str | None]:
    """One run per size and encoding over a veth between two namespaces, tbf on the sender side."""
    if os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("tc") is None:
        return [], "needs root, ip and tc"
    tag = f"coopdb-{os.getpid()}"
    a, b = f"{tag}-a", f"{tag}-b"

    def sh(*cmd):
        subprocess.run(cmd, check=True, capture_output=True, timeout=20)

    results = []
    try:
        sh("ip", "netns", "add", a)
        sh("ip", "netns", "add", b)
        sh("ip", "-n", a, "link", "add", "eth0", "type", "veth", "peer", "name", "eth0", "netns", b)
        for ns, addr in ((a, "10.213.9.1/24"), (b, "10.213.9.2/24")):
            sh("ip", "-n", ns, "addr", "add", addr, "dev", "eth0")
            sh("ip", "-n", ns, "link", "set", "eth0", "up")
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        sh("ip", "netns", "exec", a, "tc", "qdisc", "replace", "dev", "eth0", "root", "tbf",
           "rate", f"{rate_mbit}mbit", "burst", "64kb", "latency", "100ms")
        rx = Receiver(["ip", "netns", "exec", b], "10.213.9.2", 7400)
        try:
            version = 1
            for size in sizes:
                for enc in encodings:
                    out = subprocess.run(
                        ["ip", "netns", "exec", a, sys.executable, __file__, *key_args(), "--send",
                         "10.213.9.2", "7400", size, enc, "1", str(version)],
                        check=True, capture_output=True, text=True, timeout=900,
                        env=dict(os.environ, PYTHONPATH=str(ROOT)))
                    version += 1
                    r = json.loads(out.stdout.strip().splitlines()[-1])
                    decodes = rx.decode_times()
                    ideal = r["message_bytes"] * 8 / (rate_mbit * 1e6)
                    decode = min(decodes) if decodes else 0.0
                    r.update(size=size, link=f"tbf {rate_mbit} Mbit/s", receiver_decode_s=round(decode, 4),
                             ideal_transfer_s=round(ideal, 4),
                             transfer_overhead_ratio=round((r["send_to_ack_s"] - decode) / ideal, 4))
                    results.append(r)
                    print(f"shaped {size} {r['encoding']}: {r['end_to_end_s']:.3f} s", file=sys.stderr)
        finally:
            rx.stop()
    finally:
        for ns in (a, b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=20)
    return results, None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="6M,25M,110M")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-shaped", action="store_true")
    ap.add_argument("--rate-mbit", type=float, default=54.0)
    ap.add_argument("--encodings", default=",".join(ENCODINGS), help="e.g. default,raw,thesis")
    ap.add_argument("--fan-in", default="1,4,16", help="concurrent senders into one receiver ('' to skip)")
    ap.add_argument("--serve", nargs=2, metavar=("HOST", "PORT"))
    ap.add_argument("--send", nargs=6, metavar=("HOST", "PORT", "SIZE", "ENCODING", "REPEAT", "VERSION"))
    ap.add_argument("--delta", action="store_true", help="bytes per drone per minute, full maps vs deltas")
    ap.add_argument("--world", default="hospital", help="--delta: the firmware_sim world flown")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--drones", type=int, default=3)
    ap.add_argument("--block-sizes", default="4096,1024",
                    help="--delta: MTP block sizes (the first one is the one judged against the goal)")
    ap.add_argument("--steady-after-s", type=float, default=30.0)
    ap.add_argument("--transport", default="mtp",
                    help="--delta: mtp, zenoh or mtp,zenoh (the same recorded flight over each)")
    ap.add_argument("--brick-edge", type=int, default=DEFAULT_BRICK_EDGE)
    ap.add_argument("--key", action="store_true",
                    help="both ends hold a swarm key: transfers authenticated (HMAC) and encrypted (AEAD)")
    args = ap.parse_args()
    global SETTINGS
    if args.key:
        SETTINGS = replace(SETTINGS, swarm_key=BENCH_KEY)
    if args.serve:
        serve(args.serve[0], int(args.serve[1]))
        return
    if args.send:
        host, port, size, enc, repeat, version = args.send
        print(json.dumps(send_runs(host, int(port), size, enc, int(repeat), int(version))))
        return
    if args.delta:
        transports = [t for t in args.transport.split(",") if t]
        if not transports or not set(transports) <= {"mtp", "zenoh"}:
            ap.error("--transport: mtp and/or zenoh, comma-separated")
        report = run_delta(args.world, args.seed, args.drones, [int(b) for b in args.block_sizes.split(",")],
                           args.steady_after_s, args.brick_edge, transports)
        text = json.dumps(report, indent=2)
        print(text)
        (ROOT / "out" / "bench").mkdir(parents=True, exist_ok=True)
        (ROOT / "out" / "bench" / "share_delta.json").write_text(text + "\n")
        return
    sizes = [s for s in args.sizes.split(",") if s]
    for s in sizes:
        if s not in SIZES:
            ap.error(f"unknown size {s}; known: {', '.join(SIZES)}")
    encodings = [e for e in args.encodings.split(",") if e]
    loop = run_loopback(sizes, args.repeat, encodings)
    fan_in = run_fan_in([int(n) for n in args.fan_in.split(",") if n])
    shaped, why = (([], "disabled by --no-shaped") if args.no_shaped
                   else run_shaped(sizes, args.rate_mbit, encodings))
    big = [r for r in loop if r["size"] == "110M" and r["encoding"] == wire.DEFAULT_ENCODING]
    report = {
        "benchmark": "share", "host": platform.node(), "python": platform.python_version(),
        "cpus": os.cpu_count(), "block_size": SETTINGS.block_size, "keyed": SETTINGS.swarm_key is not None,
        "what": "end_to_end_s = encode (compress) + MTP transfer + receiver inspect/decode (decompress) "
                "until its ack; best of --repeat on loopback, one run shaped",
        "loopback": loop, "fan_in_loopback": fan_in, "shaped": shaped, "shaped_skipped": why,
        "thesis_anchor": THESIS_ANCHOR,
        "goal_110M_loopback_s": GOAL_110M_LOOPBACK_S,
        "goal_met": (big[0]["end_to_end_s"] <= GOAL_110M_LOOPBACK_S) if big else None,
    }
    text = json.dumps(report, indent=2)
    print(text)
    out = ROOT / "out" / "bench"
    out.mkdir(parents=True, exist_ok=True)
    (out / "share.json").write_text(text + "\n")


if __name__ == "__main__":
    main()
