"""Fuzz targets: per parser, valid seeds and a check(data) that feeds one input and asserts the contract.

Shared by the bounded CI tests (tests/fuzz/test_fuzz_*.py) and the long campaigns (scripts/fuzz).
Every check raises bounds.Finding when the input breaks the contract and returns quietly otherwise.
Socket targets are context managers that start their server on entry and stop it on exit.
"""

import random
import struct
import zlib

import numpy as np

from coopd.grid import OccupancyGrid
from coopd.sharing import codec, mtp, planes, wire

from .bounds import Finding, allocation_limit, expect_only, time_limit

CALL_LIMIT_S = 5.0
"""No single parse may take longer than this (they all work in well under a second)."""


def sample_cells(rng: random.Random, n: int) -> np.ndarray:
    """n flat cells shaped like a real map: long runs of unknown/free/occupied with HIMM noise."""
    out = np.empty(n, dtype=np.int8)
    i = 0
    while i < n:
        run = min(n - i, rng.choice((1, 2, 5, 40, 300)))
        out[i:i + run] = rng.choice((-1, -1, 0, 0, 100, 50, -2, rng.randint(-2, 100)))
        i += run
    return out


def sample_grid(rng: random.Random) -> OccupancyGrid:
    """A small random grid with a random origin."""
    shape = (rng.randint(1, 12), rng.randint(1, 12), rng.choice((1, rng.randint(1, 6))))
    cells = sample_cells(rng, shape[0] * shape[1] * shape[2]).reshape(shape)
    offset = tuple(rng.randint(-50, 50) for _ in range(3))
    return OccupancyGrid(cells, rng.choice((0.05, 0.1, 0.2, 1.0)), offset)


def with_matching_crc(data: bytes, head: int, rng: random.Random) -> bytes:
    """Half the time, the mutant with the CRC-32 at the end of its `head`-byte header made to match
    the payload after it, so the checks behind the CRC are reached too."""
    if len(data) < head or rng.random() < 0.5:
        return data
    out = bytearray(data)
    struct.pack_into("<I", out, head - 4, zlib.crc32(out[head:]))
    return bytes(out)


class Target:
    """One parser under fuzz: seeds() are valid inputs, check(data) feeds one input."""

    name = ""
    max_len = 1 << 16

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        """Stop whatever the target started; check its end-of-run contract (Finding if broken)."""

    def seeds(self) -> list[bytes]:
        raise NotImplementedError

    def warm_up(self) -> None:
        """Run the seeds once unmeasured: numba loads or compiles each kernel specialization on its first
        call (megabytes, once per process), which must not count against an input's allocation bound."""
        measuring = getattr(self, "measure_memory", False)
        self.measure_memory = False
        try:
            for seed in self.seeds():
                try:
                    self.check(seed)
                except Finding:
                    pass  # reported when the campaign feeds the seed, measured
        finally:
            self.measure_memory = measuring

    def post_mutate(self, data: bytes, rng: random.Random) -> bytes:
        """Target-specific repair after a blind mutation (e.g. a valid checksum), or data unchanged."""
        return data

    def check(self, data: bytes) -> None:
        raise NotImplementedError


# ------------------------------------------------------------------------------------------ codec
SIZE_PREFIX = struct.Struct("<I")
MAX_FUZZ_CELLS = 1 << 24
ALLOCATION_SLACK = 1 << 18
"""Interpreter and numba dispatch overhead a call may allocate regardless of its input."""


class CodecTarget(Target):
    """codec.decompress(stream, expected_size): input = uint32 expected size + stream."""

    name = "codec"

    def __init__(self, measure_memory: bool = True):
        self.measure_memory = measure_memory

    def seeds(self) -> list[bytes]:
        rng = random.Random(1)
        out = []
        for n in (0, 1, 7, 8, 9, 130, 1000, 5000):
            cells = sample_cells(rng, n)
            out.append(SIZE_PREFIX.pack(n) + codec.compress(cells).tobytes())
        return out

    def check(self, data: bytes) -> None:
        if len(data) < SIZE_PREFIX.size:
            return
        (n,) = SIZE_PREFIX.unpack_from(data)
        n %= MAX_FUZZ_CELLS  # a valid stream may expand to 127**117 cells: only the announced n is allocated
        stream = data[SIZE_PREFIX.size:]
        cells = None

        def bound():  # the output only if the stream was accepted; nothing proportional to n otherwise
            return (n if cells is not None else 0) + 8 * len(stream) + ALLOCATION_SLACK

        with time_limit(CALL_LIMIT_S, "codec.decompress"), \
                allocation_limit(bound, "codec.decompress", self.measure_memory):
            cells = expect_only(codec.CodecError, "codec.decompress", lambda: codec.decompress(stream, n))
        if cells is None:
            return
        if cells.size != n or (n and (cells.min() < codec.CELL_MIN or cells.max() > codec.CELL_MAX)):
            raise Finding(f"codec.decompress returned {cells.size} cells for {n} or values out of range")
        if not np.array_equal(codec.decompress(codec.compress(cells), n), cells):
            raise Finding("codec: decompress(compress(x)) != x for a decoded stream")


class PlanesTarget(Target):
    """planes.decode(payload, n): input = uint32 cell count + payload."""

    name = "planes"

    def __init__(self, measure_memory: bool = True):
        self.measure_memory = measure_memory

    def seeds(self) -> list[bytes]:
        rng = random.Random(2)
        return [SIZE_PREFIX.pack(n) + planes.encode(sample_cells(rng, n)) for n in (0, 1, 5, 64, 999, 4000)]

    def check(self, data: bytes) -> None:
        if len(data) < SIZE_PREFIX.size:
            return
        (n,) = SIZE_PREFIX.unpack_from(data)
        n %= MAX_FUZZ_CELLS  # the wire layer caps cells long before (DecodeLimits)
        payload = data[SIZE_PREFIX.size:]
        # frames are checked against n before they are inflated: at most the three streams and the output
        bound = 3 * n + 8 * len(payload) + ALLOCATION_SLACK
        with time_limit(CALL_LIMIT_S, "planes.decode"), \
                allocation_limit(bound, "planes.decode", self.measure_memory):
            cells = expect_only(planes.PlanesError, "planes.decode", lambda: planes.decode(payload, n))
        if cells is None:
            return
        if cells.size != n or (n and (cells.min() < codec.CELL_MIN or cells.max() > codec.CELL_MAX)):
            raise Finding(f"planes.decode returned {cells.size} cells for {n} or values out of range")
        if not np.array_equal(planes.decode(planes.encode(cells), n), cells):
            raise Finding("planes: decode(encode(x)) != x for a decoded payload")


# ------------------------------------------------------------------------------------------- wire
FUZZ_LIMITS = wire.DecodeLimits(max_cells=1 << 20, max_bytes=1 << 22)


def _same_map(a: tuple, b: tuple) -> bool:
    (ga, ma), (gb, mb) = a, b
    return (np.array_equal(ga.cells, gb.cells) and tuple(ga.offset) == tuple(gb.offset)
            and ga.resolution == gb.resolution and ma == mb)


class WireTarget(Target):
    """wire.peek + wire.decode_map under small DecodeLimits; decoded maps must re-encode identically."""

    name = "wire"

    def __init__(self, measure_memory: bool = True):
        self.measure_memory = measure_memory

    def seeds(self) -> list[bytes]:
        rng = random.Random(3)
        out = []
        for i, enc in enumerate(wire.ENCODINGS):
            grid = sample_grid(rng)
            meta = wire.MapMeta(rng.randint(0, 2**31 - 1), rng.randint(0, 2**40), 1.7e9 + i)
            out.append(wire.encode_map(grid, meta, enc))
        grid = sample_grid(rng)
        out += [wire.encode_thesis_map(grid, 7, True), wire.encode_thesis_map(grid, 8, False)]
        return out

    def decode(self, data: bytes):
        bound = 8 * FUZZ_LIMITS.max_cells + 4 * len(data) + (1 << 20)
        with time_limit(CALL_LIMIT_S, "wire.decode_map"), \
                allocation_limit(bound, "wire.decode_map", self.measure_memory):
            expect_only(wire.WireError, "wire.peek", lambda: wire.peek(data))
            return expect_only(wire.WireError, "wire.decode_map", lambda: wire.decode_map(data, FUZZ_LIMITS))

    def check(self, data: bytes) -> None:
        decoded = self.decode(data)
        if decoded is None:
            return
        grid, meta = decoded
        info = wire.peek(data)
        encoding = info.encoding if info.message_type == wire.MSG_COOPD_MAP else "thesis"
        again = wire.decode_map(wire.encode_map(grid, meta, encoding), FUZZ_LIMITS)
        if not _same_map(decoded, again):
            raise Finding("wire: decode(encode(decode(x))) differs from decode(x)")


class DeltaTarget(Target):
    """delta.apply_delta on a fixed held map (and the service's inspect on type-4 messages): only WireError
    (DeltaBaseError is one), bounded time and memory; an accepted delta gives a map of valid cells with the
    box its header names, and the held map is never changed."""

    name = "delta"

    def __init__(self, measure_memory: bool = True):
        from coopd.sharing import delta

        self.measure_memory = measure_memory
        rng = random.Random(6)
        base = sample_grid(rng)
        base = OccupancyGrid(base.cells, 0.1, base.offset)
        self.base, self.base_meta = base, wire.MapMeta(9, 1, 1.7e9)
        self.base_cells = base.cells.copy()
        self._seeds = []
        for edge in (4, 8):
            ledger = delta.BrickLedger(edge, full_share=100.0)
            ledger.record(base, 1, wire.encode_map(base, self.base_meta))
            grid = base
            for v in range(2, 5):
                grid = grid.copy()
                keys = np.array([[rng.randint(-60, 60) for _ in range(3)] for _ in range(4)])
                grid.set_keys(keys, sample_cells(rng, 4))
                grid = grid.shrunk(pad=rng.randint(0, 3))
                ledger.record(grid, v, wire.encode_map(grid, wire.MapMeta(9, v, 1.7e9 + v)))
                self._seeds.append(ledger.delta_for(1))

    def seeds(self) -> list[bytes]:
        return list(self._seeds)

    def post_mutate(self, data: bytes, rng: random.Random) -> bytes:
        """Half the mutants get a matching payload CRC, so the index and brick checks behind it run."""
        from coopd.sharing import delta

        return with_matching_crc(data, delta.DELTA_HEADER.size, rng)

    def check(self, data: bytes) -> None:
        from coopd.sharing import delta
        from coopd.sharing.service import wire_inspect

        bound = 8 * FUZZ_LIMITS.max_cells + 4 * len(data) + (1 << 20)
        with time_limit(CALL_LIMIT_S, "delta.apply_delta"), \
                allocation_limit(bound, "delta.apply_delta", self.measure_memory):
            if data[:1] == bytes([delta.MSG_MAP_DELTA]):
                expect_only(wire.WireError, "wire_inspect", lambda: wire_inspect(data))
            out = expect_only(wire.WireError, "delta.apply_delta",
                              lambda: delta.apply_delta(self.base, self.base_meta, data, FUZZ_LIMITS))
        if not np.array_equal(self.base.cells, self.base_cells):
            raise Finding("delta.apply_delta changed the held map")
        if out is None:
            return
        grid, meta = out
        info = delta.peek_delta(data)
        valid = grid.cells.min() >= codec.CELL_MIN and grid.cells.max() <= codec.CELL_MAX
        if grid.shape != info.shape or tuple(int(v) for v in grid.offset) != info.offset \
                or meta.version != info.map_version or not valid:
            raise Finding("delta.apply_delta accepted a delta into a map other than its header names")


class MergeResultTarget(Target):
    """wire.decode_merge_result and the sharing service's inspect on type-2 messages (merge results):
    only WireError; a decoded message re-encodes to one that decodes to the same fields."""

    name = "merge_result"
    max_len = 1 << 14

    def seeds(self) -> list[bytes]:
        from coopd.geometry import euler_to_matrix, rigid

        rng = random.Random(5)
        out = []
        for n in (0, 1, 3, wire.MAX_EDGES):
            edges = tuple(wire.MergeEdge(
                rng.randint(0, 20), 21 + i, rigid(euler_to_matrix(*(rng.uniform(-3, 3) for _ in range(3))),
                                                  [rng.uniform(-50, 50) for _ in range(3)]),
                rng.random(), rng.random(), rng.randint(0, 2**40), rng.randint(0, 2**40), rng.randint(0, 1))
                for i in range(n))
            out.append(wire.encode_merge_result(wire.MergeResultMessage(rng.randint(0, 99), n + 1, 1.7e9,
                                                                        edges)))
        return out

    def post_mutate(self, data: bytes, rng: random.Random) -> bytes:
        """Half the mutants get a matching CRC, so the edge checks behind it are reached."""
        return with_matching_crc(data, wire.RESULT_HEADER.size, rng)

    def check(self, data: bytes) -> None:
        from coopd.sharing.service import wire_inspect

        with time_limit(CALL_LIMIT_S, "wire.decode_merge_result"):
            if data[:1] == bytes([wire.MSG_MERGE_RESULT]):
                expect_only(wire.WireError, "wire_inspect", lambda: wire_inspect(data))
            msg = expect_only(wire.WireError, "wire.decode_merge_result",
                              lambda: wire.decode_merge_result(data))
        if msg is None:
            return
        again = wire.decode_merge_result(wire.encode_merge_result(msg))
        same = (again.vehicle_id, again.version, again.stamp, len(again.edges)) == \
            (msg.vehicle_id, msg.version, msg.stamp, len(msg.edges))
        for e, f in zip(msg.edges, again.edges, strict=True):
            same &= (e.a, e.b, e.score, e.overlap, e.version_a, e.version_b, e.flags) == \
                (f.a, f.b, f.score, f.overlap, f.version_a, f.version_b, f.flags)
            same &= bool(np.array_equal(e.transform, f.transform))
        if not same:
            raise Finding("merge_result: decode(encode(decode(x))) differs from decode(x)")


class CmapTarget(WireTarget):
    """io.cmap.load_cmap on a file holding the input: only WireError, never OSError or others."""

    name = "cmap"

    def __init__(self, directory, measure_memory: bool = False):
        super().__init__(measure_memory)
        from pathlib import Path

        self.path = Path(directory) / "fuzz.cmap"

    def decode(self, data: bytes):
        from coopd.io.cmap import load_cmap

        self.path.write_bytes(data)
        with time_limit(CALL_LIMIT_S, "load_cmap"):
            return expect_only(wire.WireError, "load_cmap", lambda: load_cmap(self.path, FUZZ_LIMITS))

    def check(self, data: bytes) -> None:
        decoded = self.decode(data)
        if decoded is not None and not _same_map(decoded, wire.decode_map(data, FUZZ_LIMITS)):
            raise Finding("load_cmap and decode_map disagree on the same bytes")


class OctomapTarget(Target):
    """io.bt.read_octomap (OctoMap .bt / .ot files from other robots): only ValueError; the grid it
    returns never spans more than the cell limit."""

    name = "octomap"

    def seeds(self) -> list[bytes]:
        from coopd.io.bt import bt_bytes

        rng = random.Random(11)
        ot = b"# Octomap OcTree file\nid OcTree\nsize {n}\nres 0.1\ndata\n"
        root_leaf = ot.replace(b"{n}", b"1") + struct.pack("<fB", 0.5, 0)
        one_child = ot.replace(b"{n}", b"2") + struct.pack("<fB", 0.5, 1) + struct.pack("<fB", -1.0, 0)
        return [bt_bytes(sample_grid(rng)) for _ in range(4)] + [root_leaf, one_child]

    def check(self, data: bytes) -> None:
        from coopd.io.bt import read_octomap

        with time_limit(CALL_LIMIT_S, "read_octomap"):
            grid = expect_only(ValueError, "read_octomap", lambda: read_octomap(data, FUZZ_LIMITS.max_cells))
        if grid is not None and grid.size > FUZZ_LIMITS.max_cells:
            raise Finding(f"read_octomap: a grid of {grid.size} cells, over the limit of "
                          f"{FUZZ_LIMITS.max_cells}")


# -------------------------------------------------------------------------------------------- mtp
MTP_BS = 64
MTP_MAX_BYTES = 1 << 16


class MtpTarget(Target):
    """mtp.Reassembler fed the input in pseudo-random chunks: only MtpError; bounded buffers."""

    name = "mtp"

    def __init__(self, measure_memory: bool = True):
        self.measure_memory = measure_memory

    def seeds(self) -> list[bytes]:
        rng = random.Random(4)
        hello = mtp.hello_frame(mtp.Hello(MTP_BS, 9, bytes(range(16)), False, 77))
        msg = wire.encode_map(sample_grid(rng), wire.MapMeta(9, 3, 1.0))
        plain = b"".join(bytes(b) for b in mtp.encode_transfer(msg, MTP_BS))
        tagged = b"".join(bytes(b) for b in mtp.encode_transfer(msg, MTP_BS, tag=bytes(32)))
        offer = mtp.offer_frame(5, 12, MTP_BS)
        keyed = mtp.hello_frame(mtp.Hello(MTP_BS, 9, bytes(range(16)), True, 77))
        proof = mtp.proof_frame(9, bytes(range(16)), MTP_BS)
        return [hello, hello + plain, hello + tagged + offer + plain, plain, hello + offer,
                keyed + proof + tagged + offer, keyed + tagged, keyed + offer]

    def check(self, data: bytes) -> None:
        chunks = random.Random(zlib.crc32(data))
        events = []

        # a keyed hello puts the reassembler in the keyed server's state: nothing before a proof
        keyed = len(data) > 7 and data[:2] == bytes([mtp.MARK, mtp.HELLO]) and data[7] & mtp.HELLO_FLAG_KEY

        def feed_all():
            r = mtp.Reassembler(MTP_BS, MTP_MAX_BYTES, authorized=not keyed)
            view = memoryview(data)
            try:
                while len(view):
                    n = chunks.choice((1, 3, MTP_BS, 1000, len(view)))
                    for e in r.feed(view[:n]):
                        events.append(e)
                        if isinstance(e, mtp.Proof):
                            r.authorized = True  # what the server does once the tag verified
                    view = view[n:]
            finally:
                r.close()

        with time_limit(CALL_LIMIT_S, "mtp.Reassembler"), \
                allocation_limit(2 * MTP_MAX_BYTES + (1 << 16) + 4 * len(data), "mtp.Reassembler",
                                 self.measure_memory):
            expect_only(mtp.MtpError, "mtp.Reassembler.feed", feed_all)
        for e in events:
            if isinstance(e, mtp.Transfer):
                if len(e.data) != e.blocks * MTP_BS or not 0 < e.blocks * MTP_BS <= MTP_MAX_BYTES:
                    raise Finding(f"mtp: transfer of {e.blocks} blocks holds {len(e.data)} bytes")
            elif isinstance(e, mtp.Hello):
                if e.block_size != MTP_BS or len(e.nonce) != 16:
                    raise Finding(f"mtp: hello {e} accepted with the wrong block size or nonce")
            elif isinstance(e, mtp.Proof):
                if not keyed or len(e.tag) != 16:
                    raise Finding(f"mtp: proof {e} accepted on an unkeyed connection or with a bad tag")
            elif not isinstance(e, mtp.Offer):
                raise Finding(f"mtp: unexpected event {e!r}")


# ---------------------------------------------------------------------------------- camera header
class CameraHeaderTarget(Target):
    """camera.protocol: 4-byte length prefix then a msgpack header; only ProtocolError."""

    name = "camera_header"
    max_payload = 1 << 16

    def seeds(self) -> list[bytes]:
        import msgpack

        base = {"v": 1, "seq": 3, "t_us": 1000, "w": 8, "h": 6, "fx": 5.0, "fy": 5.0, "cx": 3.5,
                "cy": 2.5, "scale": 0.001, "enc": "z16", "n": 96, "min_m": 0.2, "max_m": 5.0}
        variants = [base, {**base, "w": 128, "h": 128, "n": 128 * 128 * 2}, {**base, "fx": 5, "min_m": 0},
                    {**base, "clock": "monotonic"}, {**base, "clock": "fc"}]
        out = []
        for d in variants:
            raw = msgpack.packb(d, use_bin_type=True)
            out.append(struct.pack("<I", len(raw)) + raw)
        return out

    def check(self, data: bytes) -> None:
        from coopd.camera import protocol

        if len(data) < 4:
            return
        with time_limit(CALL_LIMIT_S, "camera.protocol"):
            n = expect_only(protocol.ProtocolError, "header_length", lambda: protocol.header_length(data[:4]))
            header = expect_only(protocol.ProtocolError, "parse_header",
                                 lambda: protocol.parse_header(data[4:], self.max_payload))
        if n is not None and not 1 <= n <= protocol.MAX_HEADER:
            raise Finding(f"header_length accepted {n}")
        if header is not None:
            intr = header.intrinsics
            if header.n != intr.width * intr.height * 2 or header.n > self.max_payload:
                raise Finding(f"parse_header accepted n={header.n} for {intr.width}x{intr.height}")
            if not 0.0 <= header.min_m < header.max_m <= 1000.0 or header.t_us <= 0 or header.seq < 0:
                raise Finding(f"parse_header accepted an out-of-range header {header}")
            if header.clock not in protocol.CLOCKS:
                raise Finding(f"parse_header accepted the time domain {header.clock!r}")


# ----------------------------------------------------------------------------------------- config
def toml_literal(rng: random.Random) -> str:
    """A random TOML value of a random type, aimed at range and type checks."""
    pick = rng.randrange(11)
    if pick == 0:
        return str(rng.choice((0, 1, -1, 255, 256, 65535, 65536, 2**31, 2**63 - 1, -(2**63))))
    if pick == 1:
        return rng.choice(("0.0", "-0.0", "1e-9", "1e308", "nan", "inf", "-inf", "0.5", "-3.5"))
    if pick == 2:
        return rng.choice(("true", "false"))
    if pick == 3:
        s = rng.choice(("", "x", "/", "/tmp/a", "udpin:1.2.3.4:5", "tcp::0", "socket:", "tcp:h:99999",
                        "10.0.0.300", "::1", "[::1]:5", "a" * 300, "/dev/ttyACM0,0", "\u00e9", "debug"))
        return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if pick == 4:
        return "[" + ", ".join(toml_literal(rng) for _ in range(rng.randint(0, 4))) + "]"
    if pick == 5:
        return "{ a = 1 }"
    if pick == 6:
        return "1979-05-27T07:32:00Z"
    if pick == 7:
        return "[" + ", ".join(str(rng.uniform(-20, 20)) for _ in range(rng.randint(0, 4))) + "]"
    if pick == 8:
        return '["' + '", "'.join(rng.choice(("10.0.0.2", "a:b", "h:1-3", "h:0", "1.2.3.4:65535", "x:-"))
                                   for _ in range(rng.randint(1, 3))) + '"]'
    if pick == 9:
        return str(rng.randint(-10, 10**6))
    return repr(rng.uniform(-1e6, 1e6))


class ConfigTarget(Target):
    """daemon.config.load_config on a file holding the input: only ConfigError, naming the key."""

    name = "config"

    def __init__(self, directory):
        from pathlib import Path

        self.path = Path(directory) / "fuzz.toml"
        self.default_text = (Path(__file__).resolve().parents[2] / "etc" / "coopd.toml").read_text()

    def seeds(self) -> list[bytes]:
        rng = random.Random(5)
        return [self.default_text.encode(), b"", b"[vehicle]\nid = 3\n"] + \
            [self.variant(rng).encode() for _ in range(8)]

    def variant(self, rng: random.Random) -> str:
        """The default file with 1-3 `key = value` lines given random values (structure-aware mutation)."""
        lines = self.default_text.splitlines()
        keyed = [i for i, line in enumerate(lines) if " = " in line and not line.startswith("#")]
        for i in rng.sample(keyed, rng.randint(1, 3)):
            key = lines[i].split(" = ", 1)[0]
            lines[i] = f"{key} = {toml_literal(rng)}"
        return "\n".join(lines) + "\n"

    def post_mutate(self, data: bytes, rng: random.Random) -> bytes:
        return self.variant(rng).encode() if rng.random() < 0.5 else data

    def check(self, data: bytes) -> None:
        import tomllib

        from coopd.daemon.config import ConfigError, load_config

        self.path.write_bytes(data)
        try:
            with time_limit(CALL_LIMIT_S, "load_config"):
                load_config(self.path)
            return
        except ConfigError as e:
            error = e
        except Exception as e:
            raise Finding(f"load_config: {type(e).__name__} instead of ConfigError: {e}") from e
        try:
            tomllib.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, tomllib.TOMLDecodeError):
            return  # a file-level error: no key to name
        if not error.key or not str(error).startswith(f"{error.key}: ") or not error.problem.strip():
            raise Finding(f"load_config: error on valid TOML does not name its key: {error!r} (key "
                          f"{error.key!r})")


# --------------------------------------------------------------------------------- MAVLink ingest
def _mavlink_seeds() -> list[bytes]:
    from pymavlink.dialects.v20 import common as mav

    fc = mav.MAVLink(None, 7, 1)
    nan21 = [float("nan")] * 21
    msgs = [
        fc.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, 0, 0, 3, 3),
        fc.odometry_encode(2_000_000, 1, 12, 1.0, 2.0, -1.0, [1.0, 0, 0, 0], 0, 0, 0, 0, 0, 0,
                           nan21, nan21, 0, 0, 100),
        fc.odometry_encode(2_050_000, 1, 12, 1.1, 2.0, -1.0, [0.7071, 0, 0, 0.7071], 0.1, 0, 0, 0, 0, 0,
                           nan21, nan21, 1, 0, 90),
        fc.local_position_ned_encode(2100, 1.0, 2.0, -1.0, 0, 0, 0),
        fc.attitude_quaternion_encode(2100, 1.0, 0, 0, 0, 0, 0, 0, [0, 0, 0, 0]),
        fc.timesync_encode(0, 123456789),
        fc.timesync_encode(5_000_000, 123456789),
        fc.system_time_encode(1_700_000_000_000_000, 2100),
        fc.command_ack_encode(mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0),
    ]
    return [m.pack(fc) for m in msgs]


def fix_mavlink_crc(data: bytes) -> bytes:
    """A MAVLink 2 packet with its checksum recomputed, so payload mutations reach the handlers."""
    from pymavlink.dialects.v20 import common as mav
    from pymavlink.generator.mavcrc import x25crc

    if len(data) < 12 or data[0] != 0xFD:
        return data
    length = data[1]
    msgid = int.from_bytes(data[7:10], "little")
    if msgid not in mav.mavlink_map or len(data) < 10 + length + 2:
        return data
    body = data[1:10 + length]
    crc = x25crc(body)
    crc.accumulate(struct.pack("<B", mav.mavlink_map[msgid].crc_extra))
    return data[:10 + length] + struct.pack("<H", crc.crc) + data[12 + length:]


class _Recorder:
    """A datagram transport that records writes and never reads (the target feeds _ingest directly)."""

    def __init__(self):
        from coopd.vehicle.transport import Endpoint, Transport

        class Recorder(Transport):
            is_open = True

            def open(self):
                pass

            def read(self, timeout):
                return b""

            def write(self, data):
                pass

            def close(self):
                pass

        self.transport = Recorder(Endpoint("udpin", "127.0.0.1", 1))


class MavlinkIngestTarget(Target):
    """VehicleLink._ingest (the whole receive path) with one datagram: nothing may escape it."""

    name = "mavlink"
    max_len = 600

    def __init__(self):
        from coopd.vehicle import LinkConfig, VehicleLink

        self.link = VehicleLink(LinkConfig(connection="udpin:127.0.0.1:1"), _Recorder().transport)
        self.link._ingest(_mavlink_seeds()[0], 0.0)  # lock onto the FC so messages reach the handlers
        self.now = 1.0

    def seeds(self) -> list[bytes]:
        singles = _mavlink_seeds()
        return singles + [singles[1] + singles[3] + singles[0]]

    def post_mutate(self, data: bytes, rng: random.Random) -> bytes:
        return fix_mavlink_crc(data) if rng.random() < 0.7 else data

    def check(self, data: bytes) -> None:
        self.now += 0.01
        before = self.link.counters["rx_bytes"]
        with time_limit(CALL_LIMIT_S, "VehicleLink._ingest"):
            try:
                self.link._ingest(data, self.now)
            except Exception as e:
                raise Finding(f"VehicleLink._ingest: {type(e).__name__} escaped: {e}") from e
        if self.link.counters["rx_bytes"] != before + len(data):
            raise Finding("VehicleLink._ingest did not count the datagram")
        if self.link.target_system == 0:
            raise Finding("VehicleLink lost its FC lock on a datagram")
        latest = self.link.poses.latest()
        if latest is not None and not (np.isfinite(latest.position).all() and np.isfinite(latest.t_fc)
                                       and abs(np.linalg.norm(latest.quaternion) - 1.0) < 1e-3):
            raise Finding(f"VehicleLink buffered a pose that is not finite or not a unit rotation: {latest}")


# -------------------------------------------------------------------------------- socket targets
SOCKET_CASE_S = 5.0
"""A hostile connection must be closed (or answered) by the server within this."""


def wait_for(predicate, timeout: float, step: float = 0.002) -> bool:
    """Poll predicate until true or timeout seconds passed."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(step)
    return bool(predicate())


def send_and_drain(sock, data: bytes, timeout: float) -> tuple[bytes, bool]:
    """Send data, half-close, read until the peer closes; (bytes read, closed within timeout)."""
    import socket
    import time

    sock.settimeout(timeout)
    try:
        sock.sendall(data)
        sock.shutdown(socket.SHUT_WR)
    except OSError:
        pass  # the server may drop us mid-send: that is a close
    got = bytearray()
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            chunk = sock.recv(65536)
        except TimeoutError:
            return bytes(got), False
        except OSError:
            return bytes(got), True
        if not chunk:
            return bytes(got), True
        got += chunk
    return bytes(got), False


TRANSPORT_BS = 256


class TransportTarget(Target):
    """A running SharingService on loopback, one hostile connection per input: dropped, never 'internal'."""

    name = "transport"

    def __init__(self):
        from coopd.sharing.service import SharingConfig, SharingService, wire_verifier
        from coopd.sharing.transport import TransportSettings

        self.settings = TransportSettings(
            block_size=TRANSPORT_BS, connect_timeout=1.0, read_timeout=1.0, handshake_timeout=1.0,
            idle_timeout=5.0, transfer_base_s=2.0, max_bytes=1 << 20, max_inflight_bytes=4 << 20,
            max_cells=1 << 16)
        cfg = SharingConfig(vehicle_id=1, listen_host="127.0.0.1", port=0, transport=self.settings)
        self.service = SharingService(cfg, verify=wire_verifier(1 << 16, 1 << 20)).start()
        self.good_version = 0

    def seeds(self) -> list[bytes]:
        rng = random.Random(6)
        hello = mtp.hello_frame(mtp.Hello(TRANSPORT_BS, 5, bytes(16), False, 1))
        msg = wire.encode_map(sample_grid(rng), wire.MapMeta(5, 1, 1.0))
        transfer = b"".join(bytes(b) for b in mtp.encode_transfer(msg, TRANSPORT_BS))
        offer = mtp.offer_frame(6, 3, TRANSPORT_BS)
        return [hello + transfer, hello + offer + transfer, hello, transfer]

    def internal_failures(self) -> int:
        snap = self.service.peers.snapshot()
        counts = [p["failures"] for p in snap["peers"]] + list(snap["unidentified_failures"].values())
        return sum(c.get("internal", 0) for c in counts)

    def check(self, data: bytes) -> None:
        import socket

        before = self.internal_failures()
        with socket.create_connection(self.service.address, timeout=SOCKET_CASE_S) as s:
            _, closed = send_and_drain(s, data, SOCKET_CASE_S)
        if not closed:
            raise Finding(f"transport: connection still open {SOCKET_CASE_S} s after a hostile stream ended")
        if not wait_for(lambda: self.service.stats()["open_connections"] == 0, SOCKET_CASE_S):
            raise Finding("transport: the server kept serving a connection the peer had closed")
        if self.internal_failures() != before:
            raise Finding("transport: a hostile stream caused an internal error in the server")

    def good_peer_delivers(self) -> None:
        """Finding unless a well-behaved peer can still send a map and get it acknowledged."""
        from coopd.sharing.transport import PeerLink

        self.good_version += 1
        host, port = self.service.address
        msg = wire.encode_map(sample_grid(random.Random(7)), wire.MapMeta(9, self.good_version, 2.0))
        link = PeerLink.connect(host, port, self.settings, 9)
        try:
            status, _ = link.send_map(msg)
        finally:
            link.close()
        if status != mtp.ACK_OK:
            raise Finding(f"transport: a good peer's map got ack status {status} after the fuzzing")

    def close(self) -> None:
        try:
            self.good_peer_delivers()
        finally:
            self.service.stop()


class ControlTarget(Target):
    """A ControlServer with fake handlers, one hostile request per connection: a reply or a close."""

    name = "control"

    def __init__(self, directory):
        import os

        from coopd.daemon.control import BlobReply, ControlServer

        handlers = {"status": lambda args: {"echo": args},
                    "blob": lambda args: BlobReply({"n": 3}, b"abc")}
        self.server = ControlServer(os.path.join(directory, "c.sock"), handlers, max_request_bytes=4096,
                                    max_clients=4, timeout_s=1.0).start()

    def seeds(self) -> list[bytes]:
        from coopd.daemon.control import encode_frame

        return [encode_frame({"v": 1, "cmd": "status", "args": {"a": [1, 2.5, None, "x"]}}),
                encode_frame({"v": 1, "cmd": "blob", "args": {}}), encode_frame({"v": 1, "cmd": "ping"}),
                encode_frame({"v": 1, "cmd": "nope", "args": {}}),
                self.raw_frame(b'{"v":1,"cmd":"status","args":{"a":[NaN,1e400,-Infinity,1e-400]}}')]

    @staticmethod
    def raw_frame(body: bytes) -> bytes:
        """A request frame around body as is (which may be JSON Python reads but encode_frame won't write)."""
        return struct.pack(">I", len(body)) + body

    def check(self, data: bytes) -> None:
        import json
        import socket

        from coopd.daemon.control import LENGTH

        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(SOCKET_CASE_S)
            s.connect(self.server.path)
            reply, closed = send_and_drain(s, data, SOCKET_CASE_S)
        if not closed:
            raise Finding("control: connection still open after the request and its reply")
        if reply:
            if len(reply) < LENGTH.size:
                raise Finding(f"control: reply of {len(reply)} bytes has no length prefix")
            (n,) = LENGTH.unpack_from(reply)
            try:
                body = json.loads(reply[LENGTH.size:LENGTH.size + n])
            except ValueError as e:
                raise Finding(f"control: reply is not JSON: {reply[:80]!r}") from e
            if not isinstance(body, dict) or not isinstance(body.get("ok"), bool):
                raise Finding(f"control: reply without a boolean 'ok': {body!r}")
            if not body["ok"] and (body.get("code") == "internal" or not body.get("error")):
                raise Finding(f"control: error reply without a reason, or an internal error: {body!r}")
        if self.server.counters["errors"]:
            raise Finding("control: the server loop raised (counted in 'errors')")

    def close(self) -> None:
        from coopd.daemon import control

        try:
            result, _ = control.request(self.server.path, "ping", timeout_s=5)
            if result.get("protocol") != control.PROTOCOL_VERSION:
                raise Finding(f"control: ping after the fuzzing answered {result!r}")
        finally:
            self.server.stop()


class ControlClientTarget(Target):
    """control.request (coopctl's side) against a hostile daemon that answers with the input."""

    name = "control_client"

    def __init__(self, directory):
        import os
        import socket
        import threading

        self.path = os.path.join(directory, "d.sock")
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.listener.bind(self.path)
        self.listener.listen(4)
        self.listener.settimeout(0.2)
        self.reply = b""
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._serve, name="fuzz-hostile-daemon", daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stopping.is_set():
            try:
                conn, _ = self.listener.accept()
            except (TimeoutError, OSError):
                continue
            with conn:
                try:
                    conn.settimeout(2)
                    head = conn.recv(4, 0x100)  # MSG_WAITALL: the request's length prefix
                    if len(head) == 4:
                        conn.recv(int.from_bytes(head, "big"), 0x100)
                    conn.sendall(self.reply)
                except OSError:
                    pass

    def seeds(self) -> list[bytes]:
        from coopd.daemon.control import encode_frame

        ok = {"v": 1, "ok": True, "result": {"state": "running"}}
        return [encode_frame(ok), encode_frame({**ok, "blob_bytes": 3}) + b"abc",
                encode_frame({"v": 1, "ok": False, "code": "failed", "error": "no map"}),
                ControlTarget.raw_frame(b'{"v":1,"ok":true,"result":{"a":1},"blob_bytes":1e400}')]

    def check(self, data: bytes) -> None:
        from coopd.daemon import control

        self.reply = data
        with time_limit(CALL_LIMIT_S, "control.request"):
            got = expect_only(control.ControlError, "control.request", lambda: control.request(
                self.path, "status", timeout_s=1.0, max_blob_bytes=1024))
        if got is not None:
            result, blob = got
            blob_ok = blob is None or isinstance(blob, bytes) and len(blob) <= 1024
            if not isinstance(result, dict) or not blob_ok:
                raise Finding(f"control.request returned {type(result).__name__} result / blob {blob!r:.40}")

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(2)
        self.listener.close()


class CameraSocketTarget(Target):
    """A SocketDepthSource against a hostile driver on a unix socket: one connection per input."""

    name = "camera_socket"

    def __init__(self, directory):
        import os
        import socket

        from coopd.camera import SocketDepthSource, SocketSourceConfig

        path = os.path.join(directory, "cam.sock")
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.listener.bind(path)
        self.listener.listen(4)
        self.listener.settimeout(SOCKET_CASE_S)
        config = SocketSourceConfig(path, max_payload_bytes=1 << 16, stall_timeout_s=1.0, frame_timeout_s=2.0,
                                    backoff_s=(0.002, 0.01))
        self.source = SocketDepthSource(config)
        self.source.start()

    def seeds(self) -> list[bytes]:
        import msgpack

        out = []
        for seq in (0, 1):
            frames = b""
            for k in range(3):
                h = {"v": 1, "seq": seq + k, "t_us": 1000 * (seq + k + 1), "w": 4, "h": 3, "fx": 5.0,
                     "fy": 5.0, "cx": 1.5, "cy": 1.0, "scale": 0.001, "enc": "z16", "n": 24, "min_m": 0.2,
                     "max_m": 5.0}
                raw = msgpack.packb(h, use_bin_type=True)
                frames += struct.pack("<I", len(raw)) + raw + bytes(range(24))
            out.append(frames)
        return out

    def check(self, data: bytes) -> None:
        counters = self.source.counters
        ended = lambda: sum(v for k, v in counters.items() if k.startswith("disconnect_"))  # noqa: E731
        before = ended()
        try:
            conn, _ = self.listener.accept()
        except TimeoutError:
            raise Finding("camera_socket: the source did not reconnect to the driver") from None
        with conn:
            send_and_drain(conn, data, SOCKET_CASE_S)
        if not wait_for(lambda: ended() > before, SOCKET_CASE_S):
            raise Finding("camera_socket: the source did not notice the driver closing the connection\n"
                          + self.where_is_the_source())
        if counters["internal_errors"]:
            raise Finding("camera_socket: a hostile driver caused an internal error in the source")
        if self.source._thread is None or not self.source._thread.is_alive():
            raise Finding("camera_socket: the camera thread died")

    def where_is_the_source(self) -> str:
        """The camera thread's stack, counters and the machine's load: tells a hang from a starved run."""
        import os
        import sys
        import traceback

        thread = self.source._thread
        frame = sys._current_frames().get(thread.ident) if thread is not None else None
        stack = "".join(traceback.format_stack(frame)) if frame is not None else "(no camera thread)\n"
        return (f"load average {os.getloadavg()}; counters {dict(self.source.counters)}\n"
                f"camera thread stack:\n{stack}")

    def close(self) -> None:
        self.source.stop()
        self.listener.close()


class MavlinkUdpTarget(Target):
    """A running VehicleLink on a loopback udpin port: it keeps running and counts every datagram."""

    name = "mavlink_udp"
    max_len = 600

    def __init__(self):
        import socket

        from coopd.vehicle import LinkConfig, VehicleLink

        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        self.link = VehicleLink(LinkConfig(connection=f"udpin:127.0.0.1:{port}"))
        self.link.start()
        self.address = ("127.0.0.1", port)
        self.tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sent = 0
        if not wait_for(lambda: self.link.transport.is_open, SOCKET_CASE_S):
            raise RuntimeError(f"VehicleLink did not open udpin port {port}")

    def seeds(self) -> list[bytes]:
        return _mavlink_seeds()

    post_mutate = MavlinkIngestTarget.post_mutate

    def check(self, data: bytes) -> None:
        if not data:
            return  # an empty datagram carries nothing to count
        self.tx.sendto(data, self.address)
        self.sent += len(data)
        if not wait_for(lambda: self.link.counters["rx_bytes"] >= self.sent, SOCKET_CASE_S):
            raise Finding(f"mavlink_udp: link counted {self.link.counters['rx_bytes']} of {self.sent} bytes")
        if self.link.counters["loop_errors"]:
            raise Finding("mavlink_udp: a datagram raised inside the link loop (loop_errors)")
        if self.link._thread is None or not self.link._thread.is_alive():
            raise Finding("mavlink_udp: the link thread died")

    def close(self) -> None:
        self.tx.close()
        self.link.stop()


# ------------------------------------------------------------------------------------ registry
def make_target(name: str, directory):
    """The target called `name`; file and socket targets keep their files under `directory`."""
    factories = {
        "codec": CodecTarget, "planes": PlanesTarget, "wire": WireTarget, "mtp": MtpTarget,
        "merge_result": MergeResultTarget, "delta": DeltaTarget,
        "camera_header": CameraHeaderTarget, "mavlink": MavlinkIngestTarget,
        "cmap": lambda: CmapTarget(directory), "octomap": OctomapTarget,
        "config": lambda: ConfigTarget(directory),
        "transport": TransportTarget, "control": lambda: ControlTarget(directory),
        "control_client": lambda: ControlClientTarget(directory),
        "camera_socket": lambda: CameraSocketTarget(directory), "mavlink_udp": MavlinkUdpTarget,
    }
    if name not in factories:
        raise KeyError(f"unknown fuzz target {name!r}; known: {', '.join(factories)}")
    return factories[name]()


TARGETS = ("codec", "planes", "wire", "merge_result", "delta", "cmap", "octomap", "mtp", "transport",
           "camera_header", "camera_socket", "control", "control_client", "config", "mavlink", "mavlink_udp")
