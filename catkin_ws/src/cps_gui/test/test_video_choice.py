"""Which camera topic the video pane shows before the operator picks one: the compressed variant
whenever it is advertised."""

from cps_gui.widgets.video import preferred_image_topic

RAW = "/jackal/camera/image_raw"
JPEG = RAW + "/compressed"


def test_first_camera_is_shown_through_its_compressed_variant():
    assert preferred_image_topic(sorted([RAW, JPEG, "/spot/camera/image_raw"])) == JPEG
    assert preferred_image_topic([RAW]) == RAW
    assert preferred_image_topic([JPEG]) == JPEG
    assert preferred_image_topic([]) == ""


def test_a_restored_camera_is_upgraded_to_compressed_when_advertised():
    topics = sorted(["/champ/camera/image_raw", RAW, JPEG])
    assert preferred_image_topic(topics, RAW) == JPEG
    assert preferred_image_topic(topics, "/champ/camera/image_raw") == "/champ/camera/image_raw"
    assert preferred_image_topic(topics, JPEG) == JPEG
    assert preferred_image_topic([], RAW) == RAW  # not advertised yet: wait for it
