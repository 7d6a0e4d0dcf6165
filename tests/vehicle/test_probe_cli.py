"""`python -m coopd.vehicle`: the operator's probe prints status lines and exits non-zero without a link."""

import json

from coopd.vehicle.__main__ import main
from firmware_sim.simulation import Simulation
from firmware_sim.worlds import build_world


def test_probe_reports_link_camera_and_association(udp_port, tmp_path, capsys):
    sim = Simulation(
        build_world("small_house", 0),
        1,
        seed=0,
        speed=2.0,
        mavlink_base_port=udp_port,
        camera_dir=str(tmp_path),
    )
    sim.start()
    try:
        rc = main([f"udpin:127.0.0.1:{udp_port}", "--camera", sim.vehicle(0).camera_path, "--seconds", "3.5"])
    finally:
        sim.stop()
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines() if x.startswith("{")]
    assert rc == 0 and len(lines) >= 3
    last = lines[-1]
    assert last["vehicle"]["link"] == "ok" and last["camera"]["counters"]["frames"] > 5
    assert last["association"]["associated"] > 5


def test_probe_refuses_bad_connection_and_reports_no_link(capsys, udp_port):
    assert main(["carrier-pigeon:1"]) == 2
    assert main([f"udpin:127.0.0.1:{udp_port}", "--seconds", "1.2"]) == 1  # nobody there


def test_probe_takes_a_signing_key_file(capsys, tmp_path, udp_port):
    (tmp_path / "key").write_text("not hex")
    assert main([f"udpin:127.0.0.1:{udp_port}", "--signing-key-file", str(tmp_path / "key")]) == 2
    assert "64 hexadecimal" in capsys.readouterr().err
    (tmp_path / "key").write_text(bytes(range(32)).hex())
    args = [f"udpin:127.0.0.1:{udp_port}", "--signing-key-file", str(tmp_path / "key"), "--seconds", "1.2"]
    assert main(args) == 1  # nobody there
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines() if x.startswith("{")]
    assert lines and lines[-1]["vehicle"]["signing"] and lines[-1]["vehicle"]["reason"] == "no_traffic"
