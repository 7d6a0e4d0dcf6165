"""coopctl key: a swarm key file the daemon reads with the same decoder, created mode 0600."""

import json
import os
import stat

from coopd.cli.coopctl import main
from coopd.sharing import swarmkey


def test_generate_writes_a_private_hex_key_the_daemon_reads(tmp_path, capsys):
    path = tmp_path / "swarm.key"
    assert main(["key", "generate", "--out", str(path)]) == 0
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    text = path.read_text()
    assert text.startswith("hex:") and len(text) == 4 + 64 + 1 and text.endswith("\n")
    key = swarmkey.read_key_file(path)
    assert key == bytes.fromhex(text[4:].strip()) and len(key) == 32
    assert main(["key", "check", str(path)]) == 0
    assert "a swarm key of 32 bytes" in capsys.readouterr().out


def test_generate_never_overwrites_a_key_silently(tmp_path, capsys):
    path = tmp_path / "swarm.key"
    path.write_text("hex:" + "ab" * 32)
    path.chmod(0o644)
    assert main(["key", "generate", "--out", str(path)]) == 1
    assert "exists" in capsys.readouterr().err and path.read_text() == "hex:" + "ab" * 32
    assert main(["key", "generate", "--out", str(path), "--force"]) == 0
    assert path.read_text() != "hex:" + "ab" * 32 and stat.S_IMODE(path.stat().st_mode) == 0o600


def test_check_refuses_what_the_daemon_would_refuse(tmp_path, capsys):
    cases = {"short": "hex:abcd", "bad-hex": "hex:zz" + "00" * 20, "huge": "x" * 5000, "empty": ""}
    for name, text in cases.items():
        (tmp_path / name).write_text(text)
        assert main(["key", "check", str(tmp_path / name)]) == 1, name
    err = capsys.readouterr().err
    assert "at least 16 bytes" in err and "larger than 4096 bytes" in err and "holds no key" in err


def test_key_stays_private_under_any_umask_and_speaks_json(tmp_path, capsys):
    path = tmp_path / "swarm.key"
    old = os.umask(0)
    try:
        assert main(["key", "generate", "--out", str(path), "--json"]) == 0
    finally:
        os.umask(old)
    assert json.loads(capsys.readouterr().out) == {"file": str(path), "key_bytes": 32, "mode": "0600"}
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert main(["key", "check", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"file": str(path), "key_bytes": 32}
    (tmp_path / "bad.key").write_text("hex:zz")
    assert main(["key", "check", str(tmp_path / "bad.key"), "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["error"].startswith(f"{tmp_path / 'bad.key'}: ")
