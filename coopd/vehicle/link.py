"""The MAVLink link thread: heartbeat, stream requests, odometry into the pose buffer, clock sync."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mav

from .clock import ClockSync
from .fc_params import ObstacleDemandWatch
from .frame_continuity import ESTIMATOR_RESET, FC_REBOOT, ContinuityLimits, FrameContinuity
from .odometry import OdometryLimits, OdometryTracker
from .pose_buffer import PoseBuffer, PoseSample
from .signing import KEY_BYTES, StreamSigning
from .statustext import StatusTextLimiter
from .transport import Transport, make_transport

log = logging.getLogger("coopd.vehicle")

READ_TIMEOUT_S = 0.02
IDLE_READ_TIMEOUT_S = 0.2
"""The read's wait while no FC is heard (before the first bytes, or after the link was lost): nothing
is due sooner than the heartbeat, and the FC's first bytes end the wait anyway. Polling at
READ_TIMEOUT_S then cost 0.7 % of a core per idle daemon (30 of them on 2 cores: a fifth of one)."""
MAX_MESSAGES_PER_READ = 512
FC_REBOOT_BACKSTEP_S = 1.0
FALLBACK_AFTER_S = 1.0
MISMATCH_LOG_AFTER_S = 2.0
"""An autopilot with another system id heard for this long while ours is silent: logged (once)."""
NON_VEHICLE_TYPES = (
    mav.MAV_TYPE_GCS,
    mav.MAV_TYPE_ONBOARD_CONTROLLER,
    mav.MAV_TYPE_GIMBAL,
    mav.MAV_TYPE_ADSB,
)


@dataclass(frozen=True)
class LinkConfig:
    """How to reach the flight controller and what to expect from it."""

    connection: str = "udpin:0.0.0.0:14540"
    source_system: int = 1
    source_component: int = mav.MAV_COMP_ID_ONBOARD_COMPUTER
    target_system: int = 0  # 0: lock onto the first autopilot heartbeat
    odometry_rate_hz: float = 30.0
    heartbeat_period_s: float = 1.0
    timesync_period_s: float = 1.0
    stream_request_period_s: float = 3.0
    link_timeout_s: float = 1.5
    odometry_timeout_s: float = 0.5
    reopen_backoff_s: tuple[float, float] = (0.2, 5.0)
    pose_buffer_capacity: int = 1200
    pose_max_gap_s: float = 0.25
    odometry: OdometryLimits = field(default_factory=OdometryLimits)
    continuity: ContinuityLimits = field(default_factory=ContinuityLimits)
    """When the FC's frame after a reboot or estimator reset counts as the old one continued."""
    watch_obstacle_demand: bool = False
    """Ask the FC whether it uses obstacle data (CP_DIST / PRX1_TYPE: fc_params) and keep asking."""
    signing_key: bytes | None = field(default=None, repr=False)
    """MAVLink 2 signing key (32 bytes): sign ours, accept only validly signed FC messages; None: off."""

    def __post_init__(self):
        if self.signing_key is not None and len(self.signing_key) != KEY_BYTES:
            raise ValueError(f"signing_key must have {KEY_BYTES} bytes")
        if not (1 <= self.source_system <= 255 and 1 <= self.source_component <= 255):
            raise ValueError("source_system and source_component must be within 1..255")
        if not (0 <= self.target_system <= 255):
            raise ValueError("target_system must be within 0..255")
        if not (0.1 <= self.odometry_rate_hz <= 500):
            raise ValueError("odometry_rate_hz must be within 0.1..500")
        if not (0 < self.odometry_timeout_s <= self.link_timeout_s <= 60):
            raise ValueError("need 0 < odometry_timeout_s <= link_timeout_s <= 60")


class _Sink:
    """pymavlink writes packed messages here; they go straight to the transport."""

    def __init__(self):
        self.transport: Transport | None = None

    def write(self, buf: bytes) -> None:
        if self.transport is not None:
            self.transport.write(bytes(buf))


class VehicleLink:
    """Owns the FC connection and everything learnt from it; run() on its own (highest-priority) thread."""

    def __init__(self, config: LinkConfig = LinkConfig(), transport: Transport | None = None):
        self.config = config
        self.transport = transport or make_transport(config.connection)
        self._sink = _Sink()
        self._sink.transport = self.transport
        self.mav = mav.MAVLink(
            self._sink, srcSystem=config.source_system, srcComponent=config.source_component
        )
        self.mav.robust_parsing = True
        self.signing = None if config.signing_key is None else StreamSigning(self.mav, config.signing_key)
        self.poses = PoseBuffer(config.pose_buffer_capacity, config.pose_max_gap_s)
        self.odometry = OdometryTracker(config.odometry)
        self.frames = FrameContinuity(config.continuity, config.pose_buffer_capacity, config.pose_max_gap_s)
        """The FC frame -> map frame correction, and the mapping pause after a frame break."""
        self.clock = ClockSync()
        self.obstacle_demand = ObstacleDemandWatch()
        """Whether the FC is set up to use OBSTACLE_DISTANCE (its parameters, asked when configured)."""
        self.counters: Counter = Counter()
        self.target_system = config.target_system
        self.state = "connecting"
        self.native_id: int | None = None
        self._heartbeat_in_read = False
        self.max_step_s = 0.0  # longest loop iteration: shows the thread never stalls
        self._last_heartbeat = -math.inf
        self._last_rx = -math.inf
        self._last_odometry = -math.inf
        self._last_odometry_msg = -math.inf
        self._timers = {"heartbeat": -math.inf, "timesync": -math.inf, "streams": -math.inf}
        self._streams_flowing = False
        self._foreign: Counter = Counter()  # messages per other system id (at most 256 keys)
        self._foreign_autopilots: dict[int, list[float]] = {}  # other system id -> [first, last] heartbeat
        self._mismatch_logged: set[int] = set()
        self._open_error: str | None = None
        self.system_status = mav.MAV_STATE_ACTIVE
        """MAV_STATE in our HEARTBEAT; the daemon sets it from its health (BOOT, STANDBY, ACTIVE...)."""
        self.statustexts = StatusTextLimiter()
        self._obstacles: tuple | None = None
        """The newest OBSTACLE_DISTANCE waiting for the link thread (send_obstacle_distance)."""
        self._backoff = config.reopen_backoff_s[0]
        self._next_open = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        """Start the link thread."""
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self.run, name="coopd-mavlink", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the thread and close the transport."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self.transport.close()

    def run(self) -> None:
        """The loop: read (bounded wait), handle, run timers; exceptions are counted, never fatal."""
        self.native_id = threading.get_native_id()
        log.info(
            "MAVLink link starting on %s as %d/%d",
            self.config.connection,
            self.config.source_system,
            self.config.source_component,
        )
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                self.step(t0)
            except Exception:  # a bug in a handler must not take the link down: count and log once a while
                self.counters["loop_errors"] += 1
                if self.counters["loop_errors"] <= 3:
                    log.exception("MAVLink link loop error (continuing)")
                self._stop.wait(0.05)
            self.max_step_s = max(self.max_step_s, time.monotonic() - t0)

    def step(self, now: float) -> None:
        """One iteration: (re)open if needed, read what arrived within READ_TIMEOUT_S, run timers."""
        if not self.transport.is_open:
            self._try_open(now)
            if not self.transport.is_open:
                self._stop.wait(min(READ_TIMEOUT_S * 5, max(0.0, self._next_open - now)))
                self._update_state(time.monotonic())
                return
        data = self.transport.read(READ_TIMEOUT_S if self.state == "ok" else IDLE_READ_TIMEOUT_S)
        if data:
            self._ingest(data, time.monotonic())
        now = time.monotonic()
        self._update_state(now)
        self._check_mismatch(now)
        self._run_timers(now)

    def _try_open(self, now: float) -> None:
        if now < self._next_open:
            return
        try:
            self.transport.open()
            self.transport.counters["reopens"] += 1
            self._backoff = self.config.reopen_backoff_s[0]
            self._open_error = None
            log.info("MAVLink transport open: %s", self.config.connection)
        except OSError as e:
            self.counters["open_failures"] += 1
            self._open_error = str(e)
            self._next_open = now + self._backoff
            log.warning(
                "MAVLink transport %s not available (%s); retry in %.1f s",
                self.config.connection,
                e,
                self._backoff,
            )
            self._backoff = min(self._backoff * 2, self.config.reopen_backoff_s[1])

    # -- inbound --------------------------------------------------------------------------------

    def _ingest(self, data: bytes, now: float) -> None:
        self.counters["rx_bytes"] += len(data)
        if self.transport.datagrams:
            self._reset_parser()
        try:
            msgs = self.mav.parse_buffer(data) or []
        except Exception:  # pymavlink raises on some malformed input even with robust parsing
            self.counters["rx_parse_errors"] += 1
            return
        from_fc = False
        self._heartbeat_in_read = False
        for m in msgs[:MAX_MESSAGES_PER_READ]:
            if m.get_type() == "BAD_DATA":
                self.counters["rx_bad_data"] += 1
                continue
            try:
                from_fc |= self._dispatch(m, now)
            except (ValueError, TypeError, AttributeError, OverflowError):
                self.counters["rx_handler_errors"] += 1
        if from_fc and (self._heartbeat_in_read or self.transport.peer is None):
            self.transport.accept_source()

    def _reset_parser(self) -> None:
        """A datagram holds whole packets: a broken one must not swallow the start of the next."""
        if self.mav.buf_index < len(self.mav.buf):
            self.counters["rx_partial_discarded"] += 1
        self.mav.buf = bytearray()
        self.mav.buf_index = 0
        self.mav.expected_length = mav.HEADER_LEN_V1 + 2
        self.mav.have_prefix_error = False

    def _dispatch(self, m, now: float) -> bool:
        """Handle one message; True if it came from the FC we follow."""
        kind = m.get_type()
        src = m.get_srcSystem()
        if kind == "HEARTBEAT" and self.target_system == 0 and self._is_autopilot(m):
            self.target_system = src
            log.info("locked onto autopilot system %d (component %d)", src, m.get_srcComponent())
        if self.target_system == 0:
            self.counters["rx_before_lock"] += 1  # no autopilot heartbeat yet: nobody to follow
            return False
        if src != self.target_system:
            self.counters["rx_foreign"] += 1
            self._foreign[src] += 1
            if kind == "HEARTBEAT" and self._is_autopilot(m):
                self._foreign_autopilots.setdefault(src, [now, now])[1] = now
            return False
        self.counters["rx_messages"] += 1
        self._last_rx = now
        if self._last_odometry_msg == -math.inf:
            self._last_odometry_msg = now  # give ODOMETRY FALLBACK_AFTER_S to show up before falling back
        if kind == "HEARTBEAT":
            if self._is_autopilot(m):
                self._last_heartbeat = now
                self._heartbeat_in_read = True  # the FC's address may move only with its heartbeat
                self.obstacle_demand.follow(m.autopilot)
        elif kind == "ODOMETRY":
            self._last_odometry_msg = now
            self._take_pose(m.time_usec * 1e-6, lambda: self.odometry.from_odometry(m), now)
        elif kind == "ATTITUDE_QUATERNION":
            self.odometry.on_attitude_quaternion(m)
        elif kind == "LOCAL_POSITION_NED":
            if now - self._last_odometry_msg > FALLBACK_AFTER_S:
                self.counters["fallback_samples"] += 1
                self._take_pose(m.time_boot_ms * 1e-3, lambda: self.odometry.from_local_position(m), now)
        elif kind == "TIMESYNC":
            self._on_timesync(m, now)
        elif kind == "SYSTEM_TIME":
            self.clock.on_system_time(m.time_boot_ms, now)
        elif kind == "PARAM_VALUE":
            name = m.param_id.split("\x00", 1)[0] if isinstance(m.param_id, str) else ""
            if self.obstacle_demand.on_value(name, m.param_value, m.param_type):
                self.counters["obstacle_params_heard"] += 1
        elif kind == "COMMAND_ACK" and m.command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            self.counters[f"interval_ack_{m.result}"] += 1
        return True

    @staticmethod
    def _is_autopilot(m) -> bool:
        return m.type not in NON_VEHICLE_TYPES and m.autopilot != mav.MAV_AUTOPILOT_INVALID

    def _take_pose(self, t_fc: float, convert, now: float) -> None:
        """Detect an FC reboot (time base restarted), convert, and buffer the pose."""
        newest = self.poses.span()
        if newest is not None and t_fc < newest[1] - FC_REBOOT_BACKSTEP_S:
            self.counters["fc_reboots"] += 1
            log.warning(
                "FC time went back from %.3f s to %.3f s: FC rebooted, pose buffer and clock reset",
                newest[1],
                t_fc,
            )
            self.frames.on_break(FC_REBOOT, self.poses.latest(), self._last_odometry)
            self.poses.clear()
            self.odometry.restart_time_base()
            self.clock.reset()
            self._streams_flowing = False
        sample = convert()
        if self.odometry.take_reset():
            self.frames.on_break(ESTIMATOR_RESET, self.poses.latest(), self._last_odometry)
        if sample is None:
            return
        sample = self.frames.admit(sample, now)
        if sample is None:  # odometry flows, in a frame not anchored on the map yet: mapping pauses
            self._last_odometry = now
            self._streams_flowing = True
            return
        if self.poses.append(sample):
            self._last_odometry = now
            self._streams_flowing = True
        else:
            self.counters["poses_out_of_order"] += 1

    def _on_timesync(self, m, now: float) -> None:
        now_ns = time.monotonic_ns()
        if m.tc1 == 0:  # the FC asks us: answer with our clock, as PX4 expects from a companion
            self.mav.send(self.mav.timesync_encode(now_ns, m.ts1))
            self.counters["timesync_answered"] += 1
        else:
            self.clock.on_timesync_reply(m.tc1, m.ts1, now_ns)

    # -- outbound and state ---------------------------------------------------------------------

    def statustext(self, severity: int, text: str) -> bool:
        """Send a STATUSTEXT (MAV_SEVERITY_*, up to 50 ASCII bytes) to the FC, which forwards it to
        the GCS; any thread may call it. False when the rate limit refused it (counted)."""
        return self.statustexts.push(severity, text, time.monotonic())

    def send_obstacle_distance(self, distances_cm, min_cm: int, max_cm: int, t_fc_s: float | None) -> None:
        """Queue an OBSTACLE_DISTANCE (72 uint16 cm, sector 0 forward, 5 degrees clockwise, body FRD)
        for the link thread, the only one that writes MAVLink; a newer one replaces one not yet sent
        (counted). Any thread may call it; t_fc_s is the FC time of the pose it was computed at."""
        message = ([int(d) for d in distances_cm], int(min_cm), int(max_cm), t_fc_s)
        with self._lock:
            if self._obstacles is not None:
                self.counters["obstacle_distance_replaced"] += 1
            self._obstacles = message

    def _send_obstacles(self) -> None:
        with self._lock:
            message, self._obstacles = self._obstacles, None
        if message is None:
            return
        distances, min_cm, max_cm, t_fc = message
        t_us = 0 if t_fc is None else max(0, int(t_fc * 1e6))
        self.mav.send(self.mav.obstacle_distance_encode(
            t_us, mav.MAV_DISTANCE_SENSOR_UNKNOWN, distances, 5, min_cm, max_cm, 5.0, 0.0,
            mav.MAV_FRAME_BODY_FRD))
        self.counters["obstacle_distance_sent"] += 1

    def _run_timers(self, now: float) -> None:
        cfg, t = self.config, self._timers
        if now - t["heartbeat"] >= cfg.heartbeat_period_s:
            t["heartbeat"] = now
            self.mav.send(
                self.mav.heartbeat_encode(
                    mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, self.system_status
                )
            )
        if self.state == "ok":  # else they wait (bounded queue) for the FC: sent to nobody they are lost
            for severity, text in self.statustexts.take():
                self.mav.send(self.mav.statustext_encode(severity, text))
                self.counters["statustext_sent"] += 1
        if self.target_system == 0 or self.state != "ok":
            with self._lock:
                self._obstacles = None  # computed for a pose the FC may no longer hold: never late
            return
        self._send_obstacles()
        if self.config.watch_obstacle_demand:
            for name in self.obstacle_demand.due(now):
                self.mav.send(self.mav.param_request_read_encode(self.target_system, 1, name.encode(), -1))
                self.counters["obstacle_params_asked"] += 1
        est = self.clock.estimate()
        period = cfg.timesync_period_s if est is not None and est.samples >= 10 else cfg.timesync_period_s / 5
        if now - t["timesync"] >= period:
            t["timesync"] = now
            self.mav.send(self.mav.timesync_encode(0, self.clock.new_request(time.monotonic_ns())))
        odometry_quiet = now - self._last_odometry > cfg.odometry_timeout_s
        if (not self._streams_flowing or odometry_quiet) and now - t[
            "streams"
        ] >= cfg.stream_request_period_s:
            t["streams"] = now
            self._request_streams()

    def _request_streams(self) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL for what we use (ODOMETRY, its fallback pair, SYSTEM_TIME)."""
        interval_us = 1e6 / self.config.odometry_rate_hz
        for msg_id, us in (
            (mav.MAVLINK_MSG_ID_ODOMETRY, interval_us),
            (mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, interval_us),
            (mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, interval_us),
            (mav.MAVLINK_MSG_ID_SYSTEM_TIME, 1e6),
        ):
            self.mav.send(
                self.mav.command_long_encode(
                    self.target_system, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, us, 0, 0, 0, 0, 0
                )
            )
        self.counters["stream_requests"] += 1
        log.info(
            "requested ODOMETRY/LOCAL_POSITION_NED/ATTITUDE_QUATERNION at %.0f Hz from system %d",
            self.config.odometry_rate_hz,
            self.target_system,
        )

    def _update_state(self, now: float) -> None:
        alive = now - max(self._last_heartbeat, self._last_rx) <= self.config.link_timeout_s
        new = "ok" if alive else ("lost" if self._last_rx > -math.inf else "connecting")
        if new != self.state:
            with self._lock:
                old, self.state = self.state, new
            if new == "ok":
                self._timers["streams"] = -math.inf  # (re)request streams at once: the FC may have rebooted
                log.info("FC link up (system %d), was %s", self.target_system, old)
            else:
                self.counters["link_losses"] += 1
                log.warning(
                    "FC link %s: no traffic for %.1f s; odometry stale, mapping pauses",
                    new,
                    now - max(self._last_heartbeat, self._last_rx),
                )

    def _other_autopilot(self, now: float) -> int | None:
        """The system id of another autopilot heard on this link lately while ours never spoke (the
        busiest if several): vehicle.id and the FC's system id most likely differ. Once ours spoke,
        the id is right: other autopilots on a shared radio or router are no mismatch."""
        if self.state != "connecting" or self.config.target_system == 0 or self._last_rx > -math.inf:
            return None
        recent = [sid for sid, (_, last) in list(self._foreign_autopilots.items())  # status() runs elsewhere
                  if now - last <= max(self.config.link_timeout_s, 3.0)]
        return max(recent, key=lambda sid: self._foreign[sid]) if recent else None

    def _check_mismatch(self, now: float) -> None:
        other = self._other_autopilot(now)
        if other is None or other in self._mismatch_logged:
            return
        if now - self._foreign_autopilots[other][0] >= MISMATCH_LOG_AFTER_S:
            self._mismatch_logged.add(other)
            log.warning(
                "FC link %s: no message from system %d (vehicle.id), but autopilot system %d is on %s "
                "(%d messages from it ignored): if that is this vehicle's FC, set vehicle.id = %d or the "
                "FC's system id (PX4 MAV_SYS_ID, ArduPilot SYSID_THISMAV) to %d",
                self.state, self.target_system, other, self.config.connection, self._foreign[other], other,
                self.target_system,
            )

    def _signature_rejects(self) -> int:
        if self.signing is None:
            return 0
        counts = self.signing.counters()
        return counts["signature_bad"] + counts["unsigned_rejected"]

    def reason(self, now: float | None = None) -> tuple[str, str] | None:
        """Why the link is not up, as (code, sentence for operators); None while it is up."""
        now = time.monotonic() if now is None else now
        if self.state == "ok":
            return None
        if not self.transport.is_open:
            if self._open_error is None:
                return "transport_unavailable", f"opening {self.config.connection}"
            return "transport_unavailable", f"cannot open {self.config.connection}: {self._open_error}"
        other = self._other_autopilot(now)
        if other is not None:
            return "system_id_mismatch", (
                f"system id mismatch: expecting system {self.target_system} (vehicle.id), autopilot system "
                f"{other} is on the link ({self._foreign[other]} messages from it ignored)"
            )
        c = self.counters
        rejected = self._signature_rejects()
        if rejected and c["rx_messages"] == 0:
            return "signature_rejected", (
                f"{rejected} messages refused by MAVLink signing (unsigned, or signed with another key): "
                "the FC needs the key of vehicle.signing_key_file"
            )
        if self.state == "lost":
            quiet = now - max(self._last_rx, self._last_heartbeat)
            return "no_traffic", f"no message from system {self.target_system} for {quiet:.1f} s"
        if c["rx_bytes"] == 0:
            return "no_traffic", f"nothing received on {self.config.connection}"
        if c["rx_messages"] == 0 and c["rx_foreign"] == 0 and c["rx_before_lock"] == 0:
            return "no_valid_mavlink", (
                f"{c['rx_bytes']} bytes received but no valid MAVLink message (baud rate? protocol?)"
            )
        if self.target_system:
            return "no_autopilot", f"MAVLink traffic, but nothing from system {self.target_system}"
        return "no_autopilot", "MAVLink traffic, but no autopilot heartbeat"

    # -- what other stages read -----------------------------------------------------------------

    def odometry_stale(self, now: float | None = None) -> bool:
        """True when no valid odometry arrived within odometry_timeout_s (or the link is down)."""
        now = time.monotonic() if now is None else now
        return self.state != "ok" or now - self._last_odometry > self.config.odometry_timeout_s

    def pose_at(self, t_fc: float) -> PoseSample:
        """Body pose in the map frame at FC time t_fc (raises PoseLookupError; reason frame_paused
        after the newest pose while the FC's frame is not anchored on the map)."""
        if self.frames.paused is not None:
            latest = self.poses.latest()
            if latest is None or t_fc > latest.t_fc:
                raise self.frames.lookup_error()
        return self.poses.at(t_fc)

    def fc_time_at(self, local_s: float) -> float | None:
        """FC time (seconds since FC boot) at our monotonic time local_s, by the clock fit; None before
        there is one. Converts host-stamped camera frames."""
        est = self.clock.estimate()
        return None if est is None else est.fc_time(local_s)

    def fc_time_now(self) -> float | None:
        """Our best estimate of the FC clock now (seconds since FC boot), or None."""
        return self.fc_time_at(time.monotonic())

    def fc_time_latest(self) -> float | None:
        """An FC time that has surely passed: the later of the clock fit's prediction for now and the
        newest pose's stamp (the fit lags while it learns the rate); None before either exists."""
        now = self.fc_time_now()
        latest = self.poses.latest()
        newest = self.frames.newest_raw_t_fc()  # while mapping pauses for the frame, poses still arrive
        if latest is not None:
            newest = latest.t_fc if newest is None else max(newest, latest.t_fc)
        if newest is None:
            return now
        return newest if now is None else max(now, newest)

    def fc_epoch(self) -> int:
        """Counts the FC's time-base restarts (reboots): FC-time stamps from before a change are void."""
        return self.counters["fc_reboots"]

    def status(self) -> dict:
        """Snapshot for `coopctl status` and logs."""
        now = time.monotonic()
        est = self.clock.estimate()
        latest = self.poses.latest()
        span = self.poses.span()
        why = self.reason(now)
        counters = dict(self.counters)
        counters.update({f"odometry_{k}": v for k, v in dict(self.odometry.counters).items()})
        counters.update({f"clock_{k}": v for k, v in dict(self.clock.counters).items()})
        counters.update({f"transport_{k}": v for k, v in dict(self.transport.counters).items()})
        if self.signing is not None:
            counters.update({f"signing_{k}": v for k, v in self.signing.counters().items()})
        limited = self.statustexts.counters
        counters.update({f"statustext_{k}": v for k, v in limited.items() if k != "admitted"})
        return {
            "connection": self.config.connection,
            "signing": self.signing is not None,
            "link": self.state,
            "reason": None if why is None else why[0],
            "reason_detail": None if why is None else why[1],
            "target_system": self.target_system,
            "heartbeat_age_s": None
            if self._last_heartbeat == -math.inf
            else round(now - self._last_heartbeat, 3),
            "odometry_age_s": None
            if self._last_odometry == -math.inf
            else round(now - self._last_odometry, 3),
            "odometry_stale": self.odometry_stale(now),
            "pose": None
            if latest is None
            else {
                "t_fc": latest.t_fc,
                "position": [round(float(x), 4) for x in latest.position],
                "quaternion": [round(float(x), 6) for x in latest.quaternion],
            },
            "pose_buffer": {
                "samples": len(self.poses),
                "span_s": None if span is None else span[1] - span[0],
            },
            "map_origin_fc_enu": None
            if self.odometry.origin_enu is None
            else [round(float(x), 4) for x in self.odometry.origin_enu],
            "map_origin_t_fc": self.odometry.origin_t_fc,
            "frame": self.frames.status(),
            "clock": None
            if est is None
            else {
                "offset_s": est.offset_s,
                "rate": est.rate,
                "uncertainty_s": est.uncertainty_s,
                "samples": est.samples,
                "source": est.source,
            },
            "thread_native_id": self.native_id,
            "max_loop_s": round(self.max_step_s, 4),
            "counters": counters,
        }
