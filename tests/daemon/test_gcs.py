"""What the FC and GCS are told: events from health changes and the HEARTBEAT system_status."""

from pymavlink.dialects.v20 import common as mav

from coopd.daemon.gcs import GcsReporter, Health, health_events, system_status

GOOD = Health(link_ok=True, odometry_fresh=True, camera_fresh=True, camera_age_s=0.1)


def with_(h: Health, **changes) -> Health:
    return Health(**{**h.__dict__, **changes})


def test_events_on_changes_only():
    assert health_events(None, GOOD) == [] and health_events(GOOD, GOOD) == []
    stale = with_(GOOD, odometry_fresh=False)
    assert health_events(GOOD, stale) == [(mav.MAV_SEVERITY_WARNING, "coopd: no odometry, mapping paused")]
    lost = with_(stale, link_ok=False)
    assert health_events(stale, lost) == [(mav.MAV_SEVERITY_WARNING, "coopd: FC link lost")]
    assert health_events(lost, GOOD) == [(mav.MAV_SEVERITY_NOTICE, "coopd: FC link up"),
                                         (mav.MAV_SEVERITY_NOTICE, "coopd: odometry ok")]
    stalled = with_(GOOD, camera_fresh=False, camera_age_s=2.4)
    warning = (mav.MAV_SEVERITY_WARNING, "coopd: camera stalled, no frame for 2 s")
    assert health_events(GOOD, stalled) == [warning]
    assert health_events(stalled, GOOD) == [(mav.MAV_SEVERITY_NOTICE, "coopd: camera frames ok")]
    merged = with_(GOOD, merged=frozenset({4, 2}))
    assert health_events(GOOD, merged) == [(mav.MAV_SEVERITY_INFO, "coopd: merge confirmed for vehicle 2"),
                                           (mav.MAV_SEVERITY_INFO, "coopd: merge confirmed for vehicle 4")]
    assert health_events(merged, with_(GOOD, merged=frozenset({2, 4, 5})))[0][1].endswith("vehicle 5")


def test_system_status_follows_health():
    waiting = Health(link_ok=True, odometry_fresh=True, camera_fresh=False)
    assert system_status(GOOD, True, True) == mav.MAV_STATE_ACTIVE
    assert system_status(waiting, odometry_seen=True, camera_seen=False) == mav.MAV_STATE_STANDBY
    assert system_status(waiting, odometry_seen=True, camera_seen=True) == mav.MAV_STATE_CRITICAL
    no_odometry = Health(link_ok=False, odometry_fresh=False, camera_fresh=True)
    assert system_status(no_odometry, odometry_seen=True, camera_seen=True) == mav.MAV_STATE_CRITICAL


class FakeLink:
    def __init__(self):
        self.system_status, self.sent = None, []

    def statustext(self, severity, text):
        self.sent.append((severity, text))
        return True


def test_reporter_boots_then_follows():
    link = FakeLink()
    gcs = GcsReporter(link)
    assert link.system_status == mav.MAV_STATE_BOOT
    gcs.update(Health(link_ok=False, odometry_fresh=False, camera_fresh=False))
    assert link.system_status == mav.MAV_STATE_STANDBY and link.sent == []
    gcs.update(GOOD)
    assert link.system_status == mav.MAV_STATE_ACTIVE and [t for _, t in link.sent] == [
        "coopd: FC link up", "coopd: odometry ok", "coopd: camera frames ok"]
    gcs.update(with_(GOOD, camera_fresh=False, camera_age_s=3.0))
    assert link.system_status == mav.MAV_STATE_CRITICAL
    assert link.sent[-1][1] == "coopd: camera stalled, no frame for 3 s"


def test_what_works_at_the_first_sample_is_announced():
    link = FakeLink()
    GcsReporter(link).update(GOOD)
    assert [t for _, t in link.sent] == ["coopd: FC link up", "coopd: odometry ok", "coopd: camera frames ok"]


def test_a_moved_fc_frame_pauses_and_resumes_mapping_for_the_gcs():
    paused = with_(GOOD, frame_note="map paused: FC frame moved 3.2 m")
    text = "coopd: map paused: FC frame moved 3.2 m"
    assert health_events(GOOD, paused) == [(mav.MAV_SEVERITY_WARNING, text)] and len(text) <= 50
    assert health_events(paused, paused) == []
    assert health_events(paused, GOOD) == [(mav.MAV_SEVERITY_NOTICE, "coopd: map frame re-anchored, mapping")]
    assert system_status(paused, True, True) == mav.MAV_STATE_CRITICAL
