"""The coopd-sim command: the emulator needs MuJoCo, which the drone install leaves out (it comes
with coopd's sim extra); without it, one line saying so instead of an import traceback."""

import importlib.util
import sys

MISSING = "coopd-sim: the emulator needs MuJoCo, which comes with coopd's sim extra: pip install 'coopd[sim]'"


def main(argv: list[str] | None = None) -> int:
    if importlib.util.find_spec("mujoco") is None:
        print(MISSING, file=sys.stderr)
        return 1
    from firmware_sim.cli import main as run

    return run(argv)
