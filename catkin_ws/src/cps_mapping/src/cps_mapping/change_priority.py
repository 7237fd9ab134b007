"""The map server's change-detection timer: publish the changes, and give robots near a new change
high priority through cps_bw_manager's /tissue/set_priority (the paper's section 5 trigger)."""

from cps_fleet import names


def change_detection_timer(server, options, log):
    """The timer callback: publish the changes, note where the robots are (their last inserted
    clouds' sensor poses), and ask /tissue/set_priority for high priority for each robot that came
    near a newly reported change (cps_mapping.change_attention); say so for one no robot came near."""
    import rospy

    from cps_mapping.change_attention import ChangeAttention
    from cps_msgs.srv import SetPriority

    attention = ChangeAttention(options.change_attention_radius_m) if options.change_attention_radius_m > 0 else None
    set_priority = rospy.ServiceProxy(names.absolute(names.SET_PRIORITY), SetPriority)  # the map server is in /twin

    def positions():
        poses = dict(server.latest_poses)
        return {robot: poses[frame][1][:2] for robot, frame in server.sensor_frames.items() if frame in poses}

    def where(change):
        return f"{change.kind} change at ({change.place_m[0]:.1f}, {change.place_m[1]:.1f})"

    def detect(_event):
        now = rospy.Time.now()
        server.publish_changes(now)
        if attention is None:
            return
        attention.note_positions(now.to_sec(), positions())
        raise_them, unattended = attention.attend(server.tracker.reported())
        for u in unattended:
            nearest = f"nearest {u.nearest_robot} at {u.distance_m:.1f} m" if u.nearest_robot else "no robot pose yet"
            log.info(
                f"map_server: {where(u.change)}: no robot within {attention.radius_m:g} m since it was found "
                f"({nearest}): no one raised"
            )
        for a in raise_them:
            near = f"near {a.robot} ({a.distance_m:.1f} m, {now.to_sec() - a.at_s:.0f} s ago)"
            try:
                reply = set_priority(robot=a.robot, priority=1)
                log.info(
                    f"map_server: {where(a.change)} {near}: high priority "
                    f"{'granted' if reply.success else 'refused: ' + reply.message}"
                )
            except (rospy.ServiceException, rospy.ROSException) as exc:
                log.warning(f"map_server: {where(a.change)} {near}: could not raise {a.robot}'s priority: {exc}")

    return detect
