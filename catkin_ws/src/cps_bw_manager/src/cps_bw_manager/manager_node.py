"""The bandwidth manager's ROS adapter: parameters, topics, the service and the allocation timer
wired to `ManagerCore` (nodes/bandwidth_manager starts it). See the package README for the interface."""

import math
import threading

import rospy
from std_msgs.msg import Float64, String, UInt8

from cps_bw_manager.estimation import LINK_REPORT_OPTIONS, DeliveryRateEstimator
from cps_bw_manager.level_allocation import CLOUD, VIDEO
from cps_bw_manager.manager import (
    ALLOCATION_CSV_COLUMNS,
    DEFAULT_INPUT_RATE_HOLD_S,
    LINK_STATE_CSV_COLUMNS,
    EncoderReport,
    ManagerCore,
    ManagerSettings,
    allocation_csv_rows,
    link_state_csv_row,
    link_totals,
)
from cps_bw_manager.setpoints import (
    DEFAULT_MIN_INTERVAL_S,
    DEFAULT_RATE_DEADBAND,
    SetpointFilter,
    in_force_allocation,
    targets_of,
)
from cps_fleet import names
from cps_fleet.csv_log import CsvLog
from cps_fleet.fleet import load_fleet, robot_names_arg
from cps_msgs.msg import (
    BandwidthAllocation,
    BandwidthAllocationArray,
    InsertCapacity,
    LinkCapacity,
    LinkEstimate,
    LinkReport,
    LinkState,
    RateLimiterStatus,
    TopicStatsArray,
)
from cps_msgs.srv import SetPriority, SetPriorityResponse
from cps_ros.fault_report import FaultReport
from cps_ros.publisher import Publisher
from cps_ros.timers import guarded_timer

LINK_REPORT_INPUT, TISSUE_STATS_INPUT = "link_report", "tissue_stats"

ESTIMATOR_INPUTS = (LINK_REPORT_INPUT, TISSUE_STATS_INPUT)
LINK_ESTIMATE_CSV_COLUMNS = (
    "stamp_s",
    "capacity_mbps",
    "estimate_mbps",
    "mode",
    "true_capacity_mbps",
    "ratio",
    "unmanaged_mbps",
    "interval_s",
    "delivered_mbps",
    "sent_mbps",
    "delivered_link_mbps",
    "sent_link_mbps",
    "acked_link_mbps",
    "sender_socket_full",
    "offered_mbps",
    "app_limited",
    "sender_blocked_s",
    "rtt_median_ms",
    "receiver_behind",
    "receive_queue_max_bytes",
    "send_queue_max_bytes",
    "superseded",
    "expired",
    "pacing_mbps",
    "overuse",
    "probe_mbps",
    "probe_trains",
    "probe_train_mbps",
    "probe_train_sent_mbps",
    "probe_train_receiver_wait_ms",
    "refused",
    "probe_refused",
)


def link_estimate_msg(core, true_capacity_mbps, now_s) -> LinkEstimate:
    """cps_msgs/LinkEstimate of the manager's state (not stamped)."""
    est = core.estimator
    capacity = est.capacity_mbps if est else math.nan
    true = true_capacity_mbps if math.isfinite(true_capacity_mbps) and true_capacity_mbps > 0 else math.nan
    return LinkEstimate(
        capacity_mbps=capacity,
        estimate_mbps=core.available_mbps,
        mode=est.mode if est else "off",
        source=core.capacity_source,
        true_capacity_mbps=true,
        ratio=(capacity if est else core.available_mbps) / true if math.isfinite(true) else math.nan,
        unmanaged_mbps=core.unmanaged_mbps(now_s),
        twin_capacity_mbps=est.twin_capacity_mbps if est else math.nan,
        receiver_behind=bool(est and est.receiver_behind),
        ignored_reports=est.ignored_samples if est else 0,
    )


def link_estimate_csv_row(stamp_s, msg, report, overuse="", refused=""):
    """One row of link_estimate.csv (LINK_ESTIMATE_CSV_COLUMNS) for a link report, its estimate,
    the overuse the report made the estimator see (deficit, link_full, rtt; "" none) and why the
    estimator refused the report as a whole ("" taken: DeliveryRateEstimator.last_refused)."""

    def rate(n_bytes, seconds):
        return f"{n_bytes * 8e-6 / seconds:.4f}" if seconds > 0 else ""

    rtts = sorted(report.rtt_s)
    return (
        f"{stamp_s:.3f}",
        f"{msg.capacity_mbps:.4f}",
        f"{msg.estimate_mbps:.4f}",
        msg.mode,
        f"{msg.true_capacity_mbps:.4f}" if math.isfinite(msg.true_capacity_mbps) else "",
        f"{msg.ratio:.4f}" if math.isfinite(msg.ratio) else "",
        f"{msg.unmanaged_mbps:.4f}" if math.isfinite(msg.unmanaged_mbps) else "",
        f"{report.interval_s:.4f}",
        rate(report.delivered_bytes, report.interval_s),
        rate(report.sent_bytes, report.sender_interval_s),
        rate(report.delivered_link_bytes, report.interval_s),
        rate(report.sent_link_bytes, report.sender_interval_s),
        rate(report.acked_link_bytes, report.sender_interval_s),
        f"{report.sender_socket_full:.2f}",
        rate(report.offered_bytes, report.sender_interval_s),
        int(report.app_limited),
        f"{report.sender_blocked_s:.3f}",
        f"{1e3 * rtts[len(rtts) // 2]:.2f}" if rtts else "",
        int(report.receiver_behind),
        report.receive_queue_max_bytes,
        report.send_queue_max_bytes,
        report.superseded,
        report.expired,
        f"{report.pacing_mbps:.3f}",
        overuse,
        rate(report.probe_bytes, report.interval_s),
        report.probe_trains,
        rate(report.probe_train_bytes, report.probe_train_spread_s) if report.probe_train_bytes else "",
        f"{report.probe_train_sent_mbps:.3f}" if report.probe_train_bytes else "",
        f"{1e3 * report.probe_train_receiver_wait_s:.1f}"
        if report.probe_train_bytes and math.isfinite(report.probe_train_receiver_wait_s)
        else "",
        refused,
        report.probe_refused,
    )


def report_time_s(msg, now_s):
    """When a link report's interval closed: its stamp (the twin's bridge stamps it with the clock
    reading its interval_s was measured on), else `now_s`. Not when the manager took it, which can
    wait for the allocation's lock: live beside busy loops the estimator refused the interval right
    after a 60 -> 20 Mbit/s step as a repeat (clock_step), twice in eight runs (once with reports
    stamped at the bridge's publishing: cps_link.zenoh_bridge.link_report_msg)."""
    stamp_s = msg.header.stamp.to_sec()
    return stamp_s if stamp_s > 0 else now_s


def _param(name, default, kind):
    value = rospy.get_param(name, default)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise ValueError(f"parameter {name} must be {kind.__name__}, got {value!r}")
    return value


class BandwidthManagerNode:
    """Reads its parameters, allocates on every input that changes the answer and at update_rate_hz."""

    def __init__(self):
        fleet = load_fleet(rospy.get_param("~fleet_file", None) or None)
        robots = rospy.get_param("~robots", [])
        if isinstance(robots, str):
            robots = [r for r in robots.replace(",", " ").split() if r]
        fleet = robot_names_arg(fleet, robots)
        link = fleet.link
        settings = ManagerSettings(
            available_mbps=_param("~available_mbps", link.available_mbps, float),
            reserve_fraction=_param("~reserve_fraction", link.reserve_fraction, float),
            min_rate_hz=_param("~min_rate_hz", link.min_rate_hz, float),
            max_rate_hz=_param("~max_rate_hz", link.max_rate_hz, float),
            high_priority_weight=_param("~high_priority_weight", 4.0, float),
            floor_rate_hz=_param("~floor_rate_hz", 0.1, float),
            assumed_message_bytes=_param("~assumed_message_bytes", 60000.0, float),
            window_s=_param("~window_s", 1.0, float),
            headroom_messages=_param("~headroom_messages", 1.0, float),
            copies_on_link=_param("~copies_on_link", 1, int),
            input_rate_hold_s=_param("~input_rate_hold_s", DEFAULT_INPUT_RATE_HOLD_S, float),
            done_weight=_param("~done_weight", ManagerSettings.done_weight, float),
            pin_done=_param("~pin_done", ManagerSettings.pin_done, bool),
            cpu_idle_reserve=_param("~cpu_idle_reserve", ManagerSettings.cpu_idle_reserve, float),
            upgrade_margin=_param("~upgrade_margin", ManagerSettings.upgrade_margin, float),
        )
        settings.validate()  # before the estimator, which would refuse a bad rate less clearly
        self.update_rate_hz = _param("~update_rate_hz", 2.0, float)
        if not math.isfinite(self.update_rate_hz) or self.update_rate_hz < 1.0:
            raise ValueError(f"parameter ~update_rate_hz must be >= 1 Hz, got {self.update_rate_hz}")
        estimator = None
        # What the estimator is fed: the bridges' per-interval link reports (default), or over a
        # TCPROS link (no bridge) /tissue/stats with the limiters' status, 2 s sliding averages.
        self.estimator_input = _param("~estimator_input", LINK_REPORT_INPUT, str)
        if self.estimator_input not in ESTIMATOR_INPUTS:
            raise ValueError(
                f"parameter ~estimator_input must be one of {', '.join(ESTIMATOR_INPUTS)}, got {self.estimator_input!r}"
            )
        default_window_s = 0.0 if self.estimator_input == LINK_REPORT_INPUT else 2.0
        estimate_window_s = _param("~estimate_window_s", default_window_s, float)
        if not math.isfinite(estimate_window_s) or not 0 <= estimate_window_s <= 10:
            raise ValueError(f"parameter ~estimate_window_s must be in [0, 10] s, got {estimate_window_s}")
        if _param("~estimate_bandwidth", link.estimate_bandwidth, bool):
            estimator = DeliveryRateEstimator(
                initial_mbps=settings.available_mbps,
                line_rate_mbps=_param("~max_estimate_mbps", settings.available_mbps, float),
                min_mbps=_param("~min_estimate_mbps", 1.0, float),
                # /tissue/stats and the limiters' status are 2 s sliding averages: a probe shorter
                # than that is not seen, and after an outage the window still holds it (the
                # bridges' link reports are per interval: 0)
                measure_window_s=estimate_window_s,
                probe_s=max(0.5, estimate_window_s),
                **(LINK_REPORT_OPTIONS if self.estimator_input == LINK_REPORT_INPUT else {}),
            )
        video_robots = rospy.get_param("~video_robots", None)
        if video_robots is None:  # default: the fleet's camera robots
            video_robots = [r.name for r in fleet.robots if r.has_depth_camera]
        elif isinstance(video_robots, str):
            video_robots = [r for r in video_robots.replace(",", " ").split() if r]
        unknown = sorted(set(video_robots) - set(fleet.robot_names))
        if unknown:
            raise ValueError(f"parameter ~video_robots: unknown robot {', '.join(unknown)}")
        self.core = ManagerCore(
            fleet.robot_names, settings, estimator, streams=fleet.streams, camera_robots=video_robots
        )
        selected = str(rospy.get_param("~selected_robot", "")).strip()
        if selected and selected not in video_robots:
            raise ValueError(
                f"parameter ~selected_robot: '{selected}' is not a camera robot ({', '.join(video_robots)})"
            )
        self.core.on_selected_robot(selected)  # until the operator's GUI says otherwise
        self.lock = threading.Lock()
        csv_path = rospy.get_param("~csv_path", "")
        csv_max_bytes = int(fleet.limits.csv_max_mbytes * 1e6)
        self.csv_log = (
            CsvLog(csv_path, ALLOCATION_CSV_COLUMNS, max_bytes=csv_max_bytes, on_failure=rospy.logerr)
            if csv_path
            else None
        )
        self.csv_report = FaultReport("csv_log")
        link_csv_path = rospy.get_param("~link_state_csv_path", "")
        self.link_csv = (
            CsvLog(link_csv_path, LINK_STATE_CSV_COLUMNS, max_bytes=csv_max_bytes, on_failure=rospy.logerr)
            if link_csv_path
            else None
        )
        self.last_result = None
        # The test bed's true capacity (an oracle: only to label the estimate), Mbit/s.
        self.true_capacity_mbps = math.nan
        estimate_csv_path = rospy.get_param("~link_estimate_csv_path", "")
        self.estimate_csv = (
            CsvLog(estimate_csv_path, LINK_ESTIMATE_CSV_COLUMNS, max_bytes=csv_max_bytes, on_failure=rospy.logerr)
            if estimate_csv_path
            else None
        )
        self.estimate_pub = Publisher(names.LINK_ESTIMATE, LinkEstimate, queue_size=5)

        # Issue 36: only the setpoints that matter go out (setpoints.py), and each one is logged.
        self.setpoints = SetpointFilter(
            rate_deadband=_param("~setpoint_deadband", DEFAULT_RATE_DEADBAND, float),
            min_interval_s=_param("~setpoint_min_interval_s", DEFAULT_MIN_INTERVAL_S, float),
        )
        self.setpoint_messages = 0
        setpoints_csv_path = rospy.get_param("~setpoints_csv_path", "")
        self.setpoints_csv = (
            CsvLog(setpoints_csv_path, SETPOINT_CSV_COLUMNS, max_bytes=csv_max_bytes, on_failure=rospy.logerr)
            if setpoints_csv_path
            else None
        )

        def latched(robot, name, kind):
            return Publisher(names.robot_topic(robot, name), kind, queue_size=1, latch=True)

        self.rate_pubs = {r: latched(r, names.LIMITER_RATE_HZ, Float64) for r in self.core.robots}
        self.level_pubs = {r: latched(r, names.LIMITER_LEVEL, UInt8) for r in self.core.robots}
        self.video_rate_pubs = {r: latched(r, names.VIDEO_RATE_HZ, Float64) for r in self.core.camera_robots}
        self.video_level_pubs = {r: latched(r, names.VIDEO_LEVEL, UInt8) for r in self.core.camera_robots}
        self.alloc_pub = Publisher(names.ALLOCATION, BandwidthAllocationArray, queue_size=1, latch=True)
        self.bw_pub = Publisher(names.AVAILABLE_BANDWIDTH, Float64, queue_size=1, latch=True)

        def per_robot(robot, name, kind, callback):
            return rospy.Subscriber(names.robot_topic(robot, name), kind, callback, callback_args=robot, queue_size=10)

        self.subs = [
            per_robot(robot, name, kind, callback)
            for robot in self.core.robots
            for name, kind, callback in (
                (names.MISSION_STATE, String, self._on_mission_state),
                (names.LIMITER_STATUS, RateLimiterStatus, self._on_status),
                (names.CONTROL_MODE_ACTIVE, String, self._on_control_mode),
            )
        ]
        self.subs += [
            per_robot(robot, names.VIDEO_STATUS, RateLimiterStatus, self._on_video_status)
            for robot in self.core.camera_robots
        ]
        self.subs.append(rospy.Subscriber(names.SELECTED_ROBOT, String, self._on_selected, queue_size=10))
        self.subs.append(
            rospy.Subscriber(
                names.in_twin(names.INSERT_CAPACITY), InsertCapacity, self._on_insert_capacity, queue_size=10
            )
        )
        self.subs.append(rospy.Subscriber(names.TISSUE_STATS, TopicStatsArray, self._on_stats, queue_size=2))
        self.subs.append(rospy.Subscriber(names.LINK_STATE, LinkState, self._on_link_state, queue_size=10))
        self.subs.append(rospy.Subscriber(names.LINK_CAPACITY, LinkCapacity, self._on_link_capacity, queue_size=10))
        self.subs.append(rospy.Subscriber(names.LINK_REPORT, LinkReport, self._on_link_report, queue_size=10))
        self.subs.append(
            rospy.Subscriber(names.LINK_TRUE_CAPACITY, LinkCapacity, self._on_true_capacity, queue_size=10)
        )
        self.service = rospy.Service(names.SET_PRIORITY, SetPriority, self._on_set_priority)
        rospy.loginfo(
            "bandwidth manager: robots %s, %.1f Mbit/s (%s), reserve %.0f %%, rates %.1f..%.1f Hz",
            ", ".join(self.core.robots),
            settings.available_mbps,
            self.core.capacity_source,
            100 * settings.reserve_fraction,
            settings.min_rate_hz,
            settings.max_rate_hz,
        )
        self.update()
        self.timer = guarded_timer(1.0 / self.update_rate_hz, lambda _: self.update(), "allocation")
        self.estimate_timer = guarded_timer(1.0, lambda _: self.publish_estimate(None), "link estimate")

    def _on_mission_state(self, msg, robot):
        try:
            with self.lock:
                changed = self.core.on_mission_state(robot, msg.data.strip())
        except ValueError as exc:
            rospy.logwarn_throttle(5.0, f"bandwidth manager: {exc}; ignored")
            return
        if changed:
            rospy.loginfo("bandwidth manager: %s is %s -> priority %d", robot, msg.data, self.core.book.priority(robot))
            self.update()

    def _on_status(self, msg, robot):
        self._take_status(
            (robot, CLOUD),
            msg,
            lambda: self.core.on_limiter_status(
                robot,
                msg.mean_message_bytes,
                msg.input_rate_hz,
                msg.output_rate_hz,
                now_s=rospy.get_time(),
                level=msg.level,
                level_mean_message_bytes=msg.level_mean_message_bytes,
                encoder=encoder_report(msg),
            ),
        )

    def _on_video_status(self, msg, robot):
        self._take_status(
            (robot, VIDEO),
            msg,
            lambda: self.core.on_video_status(
                robot,
                msg.level,
                msg.level_mean_message_bytes,
                msg.mean_message_bytes,
                msg.output_rate_hz,
                now_s=rospy.get_time(),
                encoder=encoder_report(msg),
            ),
        )

    def _take_status(self, key, msg, apply):
        """A stream's status: `apply()` (the core's on_*_status) under the lock, reallocating when it
        says something changed or its encoder runs another setpoint than the one in force (lost:
        sent again); a status the core refuses is ignored, logged with the count so far."""
        try:
            with self.lock:
                changed = apply()
                level = self.core.encoder_level(*key)
                stale = self.setpoints.echo(key, msg.set_rate_hz, level, rospy.get_time())
                in_force = self.setpoints.in_force(key) if stale else None
            if stale:
                rospy.logwarn(
                    "bandwidth manager: %s/%s runs %.3f Hz at level %s, not the setpoint in force %s: sent again",
                    *key,
                    msg.set_rate_hz,
                    level,
                    in_force,
                )
            changed = changed or stale
        except ValueError as exc:
            rospy.logwarn_throttle(
                5.0, f"bandwidth manager: {exc}; ignored ({self.core.invalid_inputs} bad inputs so far)"
            )
            return
        if changed:
            self.update()

    def _on_selected(self, msg):
        with self.lock:
            changed = self.core.on_selected_robot(msg.data)
        if changed:
            rospy.loginfo("bandwidth manager: operator selected '%s'", msg.data)
            self.update()

    def _on_control_mode(self, msg, robot):
        with self.lock:
            changed = self.core.on_control_mode(robot, msg.data)
        if changed:
            rospy.loginfo("bandwidth manager: %s in %s", robot, msg.data)
            self.update()

    def _on_insert_capacity(self, msg):
        try:
            with self.lock:
                changed = self.core.on_insert_capacity(msg.clouds_per_s, rospy.get_time(), msg.points_per_s)
        except ValueError as exc:
            rospy.logwarn_throttle(5.0, f"bandwidth manager: {exc}; ignored")
            return
        if changed:
            self.update()

    def _on_stats(self, msg):
        if self.estimator_input != TISSUE_STATS_INPUT:
            return
        delivered_mbps, _ = link_totals(msg.topics)  # one-way latency is not used (issue 23)
        with self.lock:
            moved = self.core.on_link_stats(rospy.get_time(), delivered_mbps)
        if moved:
            self.update()

    def _on_link_report(self, msg):
        """One interval of the bridges' link report: the estimator's input and the unmanaged traffic."""
        if self.estimator_input != LINK_REPORT_INPUT:
            return
        with self.lock:
            est = self.core.estimator
            overuses = est.overuses if est else 0
            fed = est is not None and not self.core.paused  # on_bridge_report feeds it only then
            moved = self.core.on_bridge_report(
                report_time_s(msg, rospy.get_time()),
                msg.interval_s,
                msg.sender_interval_s,
                msg.delivered_bytes,
                msg.unmanaged_bytes,
                msg.sent_bytes,
                msg.app_limited,
                rtt_s=msg.rtt_s,
                receiver_behind=msg.receiver_behind,
                offered_bytes=msg.offered_bytes,
                sender_blocked_s=msg.sender_blocked_s,
                delivered_link_bytes=msg.delivered_link_bytes,
                sent_link_bytes=msg.sent_link_bytes,
                acked_link_bytes=msg.acked_link_bytes,
                sender_socket_full=msg.sender_socket_full if msg.acked_link_bytes else math.nan,
                probe_bytes=msg.probe_bytes,
                probe_sent_bytes=msg.probe_sent_bytes,
                probe_train_bytes=msg.probe_train_bytes,
                probe_train_spread_s=msg.probe_train_spread_s,
                probe_train_sent_mbps=msg.probe_train_sent_mbps,
                probe_train_receiver_wait_s=msg.probe_train_receiver_wait_s,
                probe_cost_mbps=msg.probe_cost_mbps,
                send_queue_max_bytes=msg.send_queue_max_bytes if msg.acked_link_bytes else math.nan,
            )
            overuse = est.last_overuse if est and est.overuses > overuses else ""
            refused = est.last_refused if fed else ""
        self.publish_estimate(msg, overuse, refused)
        if moved:
            self.update()

    def _on_true_capacity(self, msg):
        with self.lock:
            self.true_capacity_mbps = msg.capacity_mbps if math.isfinite(msg.capacity_mbps) else math.nan

    def publish_estimate(self, report, overuse="", refused=""):
        """/tissue/link_estimate (and a row of link_estimate.csv): the estimate beside the true
        capacity, and the link report it came from (None: the 1 Hz repeat) with the overuse it
        made the estimator see and why the estimator refused it ("" none)."""
        with self.lock:
            msg = link_estimate_msg(self.core, self.true_capacity_mbps, rospy.get_time())
        msg.header.stamp = rospy.Time.now()
        self.estimate_pub.publish(msg)
        if self.estimate_csv and report is not None:
            self.estimate_csv.write(link_estimate_csv_row(msg.header.stamp.to_sec(), msg, report, overuse, refused))

    def _on_link_state(self, msg):
        with self.lock:
            changed = self.core.on_link_state(msg.up, msg.since.to_sec(), msg.outages, msg.last_outage_s, msg.peer)
            available = self.core.available_mbps
        if changed:
            (rospy.loginfo if msg.up else rospy.logwarn)(
                "bandwidth manager: link to %s %s; %s",
                msg.peer or "the other side",
                "back" if msg.up else "DOWN",
                f"allocating again from {available:.1f} Mbit/s" if msg.up else "allocation paused, rates held",
            )
            if self.link_csv:
                self.link_csv.write(link_state_csv_row(rospy.get_time(), self.core.link, available))
            self.update()

    def _on_link_capacity(self, msg):
        """An announced link capacity: the budget's basis from the next allocation (made now)."""
        try:
            with self.lock:
                changed = self.core.set_capacity_mbps(msg.capacity_mbps, msg.source, now_s=rospy.get_time())
                available = self.core.available_mbps
        except ValueError as exc:
            rospy.logerr(f"bandwidth manager: {exc} ({self.core.invalid_inputs} bad inputs so far)")
            return
        if changed:
            rospy.loginfo(
                "bandwidth manager: link capacity %.3g Mbit/s announced by %s; allocating from %.3g Mbit/s",
                msg.capacity_mbps,
                msg.source or "an unnamed source",
                available,
            )
            self.update()

    def _on_set_priority(self, req):
        with self.lock:
            ok, message = self.core.set_priority(req.robot, req.priority)
        (rospy.loginfo if ok else rospy.logwarn)("bandwidth manager: set_priority: %s", message)
        if ok:
            self.update()
        return SetPriorityResponse(success=ok, message=message)

    def update(self):
        """Allocate; send the levels and rates that matter (SetpointFilter: a robot's changes
        together, only for streams whose encoder has reported); publish and log the allocation
        in force."""
        with self.lock:
            now_s = rospy.get_time()
            paused = self.core.pause_status(now_s)
            try:
                target = self.last_result if paused and self.last_result else self.core.allocate_streams(now_s)
            except ValueError as exc:
                rospy.logerr_throttle(5.0, f"bandwidth manager: cannot allocate: {exc}")
                return
            self.last_result = target
            available, pacing = self.core.available_mbps, self.core.pacing_mbps
            states = {r: self.core.book.mission_state(r) for r in self.core.robots}
            changes = {}
            if not paused:
                copies = self.core.settings.copies_on_link
                targets = {
                    key: t
                    for key, t in targets_of(target, self.core.last_demands, self.core.limiter_rates(target)).items()
                    if self.core.reported(*key)
                }
                changes = self.setpoints.decide(
                    now_s,
                    targets,
                    target.budget_mbytes_per_s / copies,
                    link_idle=not target.link_binds,
                    probing=self.core.probing,
                )
            result = in_force_allocation(
                target, self.core.last_demands, self.setpoints, self.core.settings.copies_on_link
            )
            bound = self.core.compute_bound_streams()
            cpu_spare = self.core.cpu_spare_by_stream()
            # Sent in the order decided: the setpoint topics are latched, so the last one published
            # is what a limiter keeps, and the filter believes the last one decided is in force.
            self._send(now_s, changes)
        if paused:
            rospy.logwarn_throttle(5.0, f"bandwidth manager: {paused}")
        elif not target.feasible:
            rospy.logwarn_throttle(5.0, f"bandwidth manager: {target.status}")
        msg = BandwidthAllocationArray()
        msg.header.stamp = rospy.Time.now()
        msg.available_mbps = available
        msg.pacing_mbps = pacing
        msg.reserve_fraction = self.core.settings.reserve_fraction
        msg.budget_mbytes_per_s = result.budget_mbytes_per_s
        msg.allocated_mbytes_per_s = result.allocated_mbytes_per_s
        msg.feasible = result.feasible
        msg.status = paused or result.status
        msg.link_up = not paused
        for a in result.streams:
            topic = (
                names.managed_cloud(a.robot) if a.stream == CLOUD else names.robot_topic(a.robot, names.VIDEO_THROTTLE)
            )
            msg.allocations.append(
                BandwidthAllocation(
                    robot=a.robot,
                    topic=rospy.resolve_name(topic),
                    stream=a.stream,
                    level=a.level,
                    level_name=a.level_name,
                    priority=a.priority,
                    rate_hz=a.rate_hz,
                    min_rate_hz=a.min_rate_hz,
                    max_rate_hz=a.max_rate_hz,
                    message_bytes=a.message_bytes,
                    bandwidth_mbytes_per_s=a.bandwidth_mbytes_per_s,
                    share_percent=a.share_percent,
                    degraded=a.degraded,
                )
            )
        self.alloc_pub.publish(msg)
        self.bw_pub.publish(Float64(available))
        if self.csv_log:
            for row in allocation_csv_rows(
                msg.header.stamp.to_sec(), available, result, states, target, bound, cpu_spare
            ):
                self.csv_log.write(row)
            if self.csv_log.failed:
                self.csv_report.report(self.csv_log.failed, csv_rows_lost=self.csv_log.rows_lost)

    def _send(self, now_s, changes):
        """Publish a robot's changed levels and rates together (the level first: the encoder
        switches, then the rate for that level applies), each field only if it changed."""
        for robot, items in changes.items():
            for c in items:
                cloud = c.key[1] == CLOUD
                if c.level_changed:
                    (self.level_pubs if cloud else self.video_level_pubs)[robot].publish(UInt8(c.level))
                    self.setpoint_messages += 1
                if c.rate_changed:
                    (self.rate_pubs if cloud else self.video_rate_pubs)[robot].publish(Float64(c.rate_hz))
                    self.setpoint_messages += 1
                if self.setpoints_csv:
                    self.setpoints_csv.write(
                        (
                            f"{now_s:.3f}",
                            robot,
                            c.key[1],
                            c.level,
                            f"{c.rate_hz:.3f}",
                            int(c.level_changed),
                            int(c.rate_changed),
                            c.reason,
                        )
                    )

    def close(self):
        for log in (self.csv_log, self.link_csv, self.estimate_csv, self.setpoints_csv):
            if log:
                log.close()


# setpoints.csv: one row per stream per setpoint sent (the level and/or the rate that changed).
SETPOINT_CSV_COLUMNS = ("stamp_s", "robot", "stream", "level", "rate_hz", "level_sent", "rate_sent", "reason")


def encoder_report(msg) -> EncoderReport:
    """The issue-36 fields of a cps_msgs/RateLimiterStatus."""
    return EncoderReport(
        set_rate_hz=msg.set_rate_hz,
        forwarded=msg.forwarded,
        level_mean_cpu_s=msg.level_mean_cpu_s,
        level_mean_points=msg.level_mean_points,
        host=msg.host,
        host_cpus=msg.host_cpus,
        host_idle_fraction=msg.host_idle_fraction,
    )
