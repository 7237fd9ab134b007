"""The reference mission's twin seen in a viewer no one here wrote: the npm @foxglove/ws-protocol
client, run on the twin's side for a few seconds while every process is up
(cps_harness.reference.observe_while_up), lists the endpoint's channels, subscribes the map, a
pose, the video and the change topic, and decodes every message with its channel's advertised
schema."""

from cps_fleet import names
from cps_harness.reference import ROBOTS, TELEOP_ROBOT, viewer_topics
from cps_web import twin_view


def test_the_twin_in_foxglove(reference_mission):
    reference_mission.check()
    observed = reference_mission.observed
    report = observed.viewer
    assert report is not None, observed.errors
    print(f"viewer: {report['messages']}; samples: {report['samples']}")
    advertised = {c["topic"]: c["schemaName"] for c in report["channels"]}
    assert set(advertised) == set(twin_view.channels_of(ROBOTS)), advertised
    assert set(viewer_topics()) <= set(advertised)
    assert report["errors"] == [] and report["decode_errors"] == {}, report
    got = report["messages"]
    # The map (latched: sent as the viewer subscribes), the teleop robot's pose, the managed video
    # of the selected (else first camera) robot, the fleet's scene, health and the link.
    for topic in (twin_view.MAP, twin_view.pose_channel(TELEOP_ROBOT), twin_view.VIDEO, twin_view.FLEET):
        assert got.get(topic, 0) >= 1, (topic, got)
    assert got.get(twin_view.HEALTH, 0) >= 1 and got.get(twin_view.LINK, 0) >= 1, got
    samples = report["samples"]
    assert samples[twin_view.MAP]["frame_id"] == names.MAP_FRAME and samples[twin_view.MAP]["whole"]
    assert samples[twin_view.MAP]["points"] > 1000, samples[twin_view.MAP]
    assert samples[twin_view.VIDEO]["format"] == "jpeg" and samples[twin_view.VIDEO]["jpeg_soi"]
    assert samples[twin_view.pose_channel(TELEOP_ROBOT)]["frame_id"] == names.odom_frame(TELEOP_ROBOT)
    assert sorted(samples[twin_view.FLEET]["entities"]) == sorted(ROBOTS)
