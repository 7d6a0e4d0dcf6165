"""The minimal adapter in docs/camera-protocol.md runs as printed and coopd's client takes its frames."""

import subprocess
import sys

import numpy as np
from fake_driver import take_frames

from coopd.camera import SocketDepthSource, SocketSourceConfig
from tests.docs_examples import adapter_example


def test_the_documented_adapter_delivers_host_stamped_frames(tmp_path):
    script = tmp_path / "adapter.py"
    script.write_text(adapter_example())
    sock = tmp_path / "camera.sock"
    proc = subprocess.Popen([sys.executable, str(script), str(sock)], stderr=subprocess.PIPE)
    config = SocketSourceConfig(str(sock), backoff_s=(0.05, 0.2))
    src = SocketDepthSource(config, host_to_fc=lambda t: t + 100.0)
    try:
        src.start()
        frames = take_frames(src, 3, 20.0)
        assert len(frames) == 3, (src.status(), proc.poll())
        assert sock.stat().st_mode & 0o067 == 0o060  # the group (coopd) may connect, others not
        for f in frames:
            assert f.depth.shape == (480, 640) and np.all(f.depth == 2000)
            # stamped at grab() on the host clock, converted by the fit (here +100 s); sent at once
            assert f.received_local + 100.0 - 0.5 < f.t_fc <= f.received_local + 100.0
        assert [f.seq for f in frames] == sorted(f.seq for f in frames)
    finally:
        src.stop()
        proc.kill()
        _, err = proc.communicate(timeout=10)
    assert b"Traceback" not in err, err.decode()[-2000:]
