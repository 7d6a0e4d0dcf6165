"""coopd-sim on an install without the sim extra: one line naming the extra, exit 1."""

import importlib.util

import pytest

from firmware_sim import launch


def test_without_mujoco_one_line_names_the_extra(monkeypatch, capsys):
    real = importlib.util.find_spec
    without_mujoco = lambda name, *a: None if name == "mujoco" else real(name, *a)  # noqa: E731
    monkeypatch.setattr(importlib.util, "find_spec", without_mujoco)
    assert launch.main(["--help"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == launch.MISSING and "coopd[sim]" in err


def test_with_mujoco_it_is_the_emulator(capsys):
    with pytest.raises(SystemExit) as e:  # argparse's --help
        launch.main(["--help"])
    assert e.value.code == 0 and "usage:" in capsys.readouterr().out
