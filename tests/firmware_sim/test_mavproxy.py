"""A real ground station nobody here wrote (MAVProxy, driven through its command line) flies a GUIDED
takeoff and landing on the ArduPilot personality's GCS instance."""

from __future__ import annotations

import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("MAVProxy")

from firmware_sim import ardupilot as ap  # noqa: E402
from firmware_sim.simulation import Simulation  # noqa: E402
from firmware_sim.worlds import build_world  # noqa: E402

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"
MODULES = "param,arm,mode,cmdlong,wp,misc"  # what a takeoff and landing need; no GUI, no logs


class MavproxyShell:
    """mavproxy.py as a subprocess: commands on its stdin, its output lines read by a thread."""

    def __init__(self, master: str, cwd: Path):
        self.proc = subprocess.Popen(
            [sys.executable, str(MAVPROXY), f"--master={master}", "--no-state",
             f"--default-modules={MODULES}", "--source-system=255"],
            cwd=cwd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            bufsize=1,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.transcript: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.rstrip())

    def expect(self, pattern: str, timeout: float) -> str:
        """Wait (wall seconds) for an output line matching pattern; fail with the transcript."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                continue
            self.transcript.append(line)
            if re.search(pattern, line):
                return line
        raise AssertionError(f"MAVProxy never printed {pattern!r}:\n" + "\n".join(self.transcript[-40:]))

    def send(self, command: str) -> None:
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait(timeout=10)


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_mavproxy_guided_takeoff_and_land(port_block, tmp_path):
    world = build_world("small_house", seed=0)
    gcs_port = port_block + 4
    sim = Simulation(world, 1, seed=3, speed=2.0, camera=None, mavlink_base_port=port_block,
                     gcs_port=gcs_port, autopilot="ardupilot")
    sim.start()
    shell = MavproxyShell(f"udpin:127.0.0.1:{gcs_port}", tmp_path)
    try:
        start = sim.true_pose(0)[0].copy()
        shell.expect(r"online system 1", 20)  # its mode table follows the vehicle's heartbeat from here
        shell.expect(r"Received \d+ parameters", 20)  # ArduCopter's names, fetched by the param module
        shell.send("mode guided")
        shell.expect(r"Mode GUIDED", 10)
        shell.send("arm throttle")
        shell.expect(r"^ARMED", 10)
        shell.send("takeoff 2")
        shell.expect(r"NAV_TAKEOFF: ACCEPTED", 10)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and sim.true_pose(0)[0][2] < start[2] + 1.9:
            time.sleep(0.1)
        time.sleep(1.0)
        assert abs(sim.true_pose(0)[0][2] - start[2] - 2.0) < 0.3
        assert sim.vehicle(0).autopilot_state["mode"] == ap.GUIDED
        shell.send("mode land")
        shell.expect(r"Mode LAND", 10)
        shell.expect(r"^DISARMED", 30)  # touched down and disarmed itself
        assert sim.true_pose(0)[0][2] < start[2] + 0.1
        v = sim.vehicle(0)
        assert v.gcs_link.stats["rx_messages"] > 0 and v.link.stats["rx_messages"] == 0  # the GCS port only
    finally:
        shell.close()
        sim.stop()
