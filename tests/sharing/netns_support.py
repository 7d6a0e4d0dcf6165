"""Multi-host test support: sharing_node processes driven over pipes, on the hosts of a
firmware_sim.netns lab (namespaces on a bridge, or loopback addresses)."""

import json
import os
import queue
import subprocess
import sys
import threading
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
PYTHON = sys.executable

from firmware_sim.netns import LoopbackLab, NetnsLab, netns_unavailable_reason  # noqa: E402,F401


class Node:
    """A sharing_node.py process: start, send commands, read JSON status, kill."""

    def __init__(self, lab, i: int, vid: int, port: int, peers: str, *extra: str):
        self.lab, self.i, self.vid = lab, i, vid
        env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{HERE}")
        argv = [PYTHON, str(HERE / "sharing_node.py"), "--vid", str(vid), "--host", lab.address(i),
                "--port", str(port), "--peers", peers, *extra]
        self.log_path = Path(os.environ.get("TMPDIR", "/tmp")) / f"coopdt-{os.getpid()}-node{vid}-{i}.log"
        self._log = open(self.log_path, "a")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(lab.command(i, argv), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=self._log, text=True, env=env)
        self._lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        first = self._next(15)
        if not first.startswith("ready"):
            raise RuntimeError(f"node {vid} did not start: {first!r}; log {self.log_path}")

    def _read(self) -> None:
        for line in self.proc.stdout:
            self._lines.put(line.strip())
        self._lines.put("")

    def _next(self, timeout: float) -> str:
        try:
            return self._lines.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"node {self.vid} silent for {timeout} s; log {self.log_path}") from None

    def _cmd(self, line: str) -> str:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        return self._next(10)

    def publish(self, version: int, size: int) -> None:
        assert self._cmd(f"publish {version} {size}") == "ok"

    def status(self) -> dict:
        return json.loads(self._cmd("status"))

    def rss_kb(self) -> dict:
        """{'VmHWM': peak kB, 'VmRSS': current kB} of the node process."""
        return json.loads(self._cmd("rss"))

    def received(self) -> dict:
        return {int(k): v for k, v in self.status()["received"].items()}

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(10)
        self._log.close()

    def stop(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(10)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(10)
        if not self._log.closed:
            self._log.close()

    def log_text(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""
