"""docs/operations.md's troubleshooting table quotes coopd's own log and status text: every quoted
fragment below is in the table and in the code that prints it, so a reworded message fails here."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

# (fragment as the doc quotes it, the source file that prints it)
QUOTED = [
    ("coopd: configuration: ", "coopd/daemon/main.py"),
    ("cannot start: ", "coopd/daemon/main.py"),
    ("MAVLink transport ", "coopd/vehicle/link.py"),
    (" not available (", "coopd/vehicle/link.py"),
    ("no traffic for ", "coopd/vehicle/link.py"),
    ("odometry stale, mapping pauses", "coopd/vehicle/link.py"),
    (": FC rebooted", "coopd/vehicle/link.py"),
    ("paused: odometry stale (link ", "coopd/daemon/status.py"),
    ("fc frame moved ", "coopd/vehicle/frame_continuity.py"),
    ("mapping paused: FC frame moved after ", "coopd/vehicle/frame_continuity.py"),
    ("mapping resumed: new FC frame re-anchored on the map, shift ", "coopd/vehicle/frame_continuity.py"),
    ("re-anchoring refused after ", "coopd/mapping/reanchor.py"),
    ("the views do not pin the frame down", "coopd/mapping/reanchor.py"),
    ("requested ODOMETRY/LOCAL_POSITION_NED/ATTITUDE_QUATERNION at ", "coopd/vehicle/link.py"),
    ("waiting for camera frames", "coopd/daemon/status.py"),
    (" not reachable (", "coopd/camera/socket_source.py"),
    (" disconnected (", "coopd/camera/socket_source.py"),
    (" clock: dropped", "coopd/camera/socket_source.py"),
    ("camera time reference reset", "coopd/camera/socket_source.py"),
    ("implausible intrinsics", "coopd/camera/socket_source.py"),
    ("sending to ", "coopd/sharing/service.py"),
    ("swarm key mismatch", "coopd/sharing/transport.py"),
    ("did not prove the swarm key", "coopd/sharing/transport.py"),
    ("sharing is OPEN (sharing.open = true, no swarm key)", "coopd/daemon/service.py"),
    ("over the memory budget: ", "coopd/daemon/merger.py"),
    (" needs ", "coopd/daemon/budget.py"),
    (" of the budget free", "coopd/daemon/budget.py"),
    ("is over the budget of ", "coopd/daemon/service.py"),
    ("memory budget: refused ", "coopd/daemon/budget.py"),
    ("is below the baseline RSS ", "coopd/daemon/budget.py"),
    ("OVER BUDGET for ", "coopd/cli/daemon_commands.py"),
    ("not healthy (watchdog not fed)", "coopd/cli/daemon_commands.py"),
    ("without using CPU for ", "coopd/daemon/threads.py"),
    ("not healthy, the systemd watchdog is no longer fed", "coopd/daemon/service.py"),
    (" needs CAP_SYS_NICE; running at ", "coopd/daemon/threads.py"),
    ("merging is off: ", "coopd/daemon/merger.py"),
    ("importing coopd.merging failed: ", "coopd/daemon/merger.py"),
    ("coopd is not running: ", "coopd/daemon/control.py"),
    ("permission denied on ", "coopd/daemon/control.py"),
]


def troubleshooting_section() -> str:
    text = (ROOT / "docs" / "operations.md").read_text()
    match = re.search(r"^## Troubleshooting\n(.*?)^## ", text, re.S | re.M)
    assert match, "docs/operations.md has no Troubleshooting section"
    return match.group(1)


@pytest.mark.parametrize("fragment, source", QUOTED)
def test_quoted_text_is_in_the_table_and_in_the_code(fragment, source):
    assert fragment in troubleshooting_section()
    assert fragment in (ROOT / source).read_text(), f"{source} no longer prints {fragment!r}"
