"""Which camera topic the video pane shows before the operator picks one: the compressed variant
whenever it is advertised."""

from cps_fleet import names
from cps_gui.widgets.video import preferred_image_topic

RAW = names.absolute(names.robot_topic("jackal", names.CAMERA_IMAGE))
JPEG = names.absolute(names.robot_topic("jackal", names.CAMERA_IMAGE_COMPRESSED))
OTHER_RAW = names.absolute(names.robot_topic("champ", names.CAMERA_IMAGE))


def test_first_camera_is_shown_through_its_compressed_variant():
    assert (
        preferred_image_topic(sorted([RAW, JPEG, names.absolute(names.robot_topic("spot", names.CAMERA_IMAGE))]))
        == JPEG
    )
    assert preferred_image_topic([RAW]) == RAW
    assert preferred_image_topic([JPEG]) == JPEG
    assert preferred_image_topic([]) == ""


def test_a_restored_camera_is_upgraded_to_compressed_when_advertised():
    topics = sorted([OTHER_RAW, RAW, JPEG])
    assert preferred_image_topic(topics, RAW) == JPEG
    assert preferred_image_topic(topics, OTHER_RAW) == OTHER_RAW
    assert preferred_image_topic(topics, JPEG) == JPEG
    assert preferred_image_topic([], RAW) == RAW  # not advertised yet: wait for it
