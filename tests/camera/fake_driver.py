"""A scripted camera driver on a Unix socket, for hostile and fault tests of the camera client."""

import contextlib
import os
import socket
import struct
import threading
import time

import msgpack
import numpy as np

from tests.vehicle.sim_helpers import wait_until

__all__ = ["FakeDriver", "depth_of", "frame_bytes", "header", "take_frames", "wait_until"]


def header(seq=0, t_us=1000, w=8, h=6, **over):
    d = {
        "v": 1,
        "seq": seq,
        "t_us": t_us,
        "w": w,
        "h": h,
        "fx": 5.0,
        "fy": 5.0,
        "cx": 3.5,
        "cy": 2.5,
        "scale": 0.001,
        "enc": "z16",
        "n": w * h * 2 if type(w) is type(h) is int else 0,
        "min_m": 0.2,
        "max_m": 5.0,
    }
    d.update(over)
    return d


def frame_bytes(hdr: dict, payload: bytes | None = None) -> bytes:
    h = msgpack.packb(hdr, use_bin_type=True)
    if payload is None:
        payload = depth_of(hdr).tobytes()
    return struct.pack("<I", len(h)) + h + payload


def depth_of(hdr: dict) -> np.ndarray:
    """A recognisable image for a header: value = 1000 + seq + pixel index."""
    n = hdr["w"] * hdr["h"]
    return ((1000 + hdr["seq"] + np.arange(n)) % 65536).astype("<u2").reshape(hdr["h"], hdr["w"])


class FakeDriver:
    """Accepts connections on `path`; each is handed to script(conn, index) on its own thread."""

    def __init__(self, path: str, script):
        self.path, self.script = path, script
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        self.listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.listener.bind(path)
        self.listener.listen(4)
        self.listener.settimeout(0.1)
        self.connections = 0
        self.stopping = threading.Event()
        self.threads = []
        self.acceptor = threading.Thread(target=self._accept, daemon=True)
        self.acceptor.start()

    def _accept(self):
        while not self.stopping.is_set():
            try:
                conn, _ = self.listener.accept()
            except (TimeoutError, OSError):
                continue
            index = self.connections
            self.connections += 1
            t = threading.Thread(target=self._serve, args=(conn, index), daemon=True)
            self.threads.append(t)
            t.start()

    def _serve(self, conn, index):
        with contextlib.suppress(OSError), conn:
            self.script(conn, index, self.stopping)

    def close(self):
        self.stopping.set()
        self.acceptor.join(2)
        for t in self.threads:
            t.join(2)
        self.listener.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)


def take_frames(source, count: int, timeout: float) -> list:
    """Up to `count` frames from a depth source's slot, waiting at most `timeout` seconds in all."""
    frames, deadline = [], time.monotonic() + timeout
    while len(frames) < count and time.monotonic() < deadline:
        f = source.slot.take(timeout=0.5)
        if f is not None:
            frames.append(f)
    return frames
