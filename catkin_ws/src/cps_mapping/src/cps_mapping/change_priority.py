"""The map server's change-detection timer: publish the changes, and give robots near a new change
high priority through cps_bw_manager's /tissue/set_priority (the paper's section 5 trigger)."""

from cps_fleet import names


def change_detection_timer(server, options, log):
    """The timer callback: publish the changes, then ask /tissue/set_priority for high priority for
    each robot near a change new since the last detection (where its last inserted cloud was taken)."""
    import rospy

    from cps_mapping.change_attention import ChangeAttention
    from cps_msgs.srv import SetPriority

    attention = ChangeAttention(options.change_attention_radius_m) if options.change_attention_radius_m > 0 else None
    set_priority = rospy.ServiceProxy(names.absolute(names.SET_PRIORITY), SetPriority)  # the map server is in /twin

    def positions():
        poses = dict(server.latest_poses)
        return {robot: poses[frame][1][:2] for robot, frame in server.sensor_frames.items() if frame in poses}

    def detect(_event):
        changes = server.publish_changes(rospy.Time.now())
        for robot, change in attention.robots_to_raise(changes, positions) if attention else ():
            try:
                reply = set_priority(robot=robot, priority=1)
                log.info(
                    f"map_server: {change.kind} change at ({change.centroid_m[0]:.1f}, {change.centroid_m[1]:.1f}) "
                    f"near {robot}: high priority {'granted' if reply.success else 'refused: ' + reply.message}"
                )
            except (rospy.ServiceException, rospy.ROSException) as exc:
                log.warning(f"map_server: could not raise {robot}'s priority: {exc}")

    return detect
