"""The link-cut test's reading of a link_watch file: ages, what was captured before the link came
back, link-state delays; a torn last line is skipped."""

import numpy as np

from cps_fleet import names
from cps_harness.cut_analysis import LINK_STATE, ages_after, captured_before, first_state_after, read_watch

TOPIC = names.absolute(names.managed_cloud_at_twin("scout"))


def test_a_cloud_held_through_the_cut_shows_how_long_before_the_restore_it_was_captured(tmp_path):
    watch_file = tmp_path / "watch.txt"
    watch_file.write_text(
        f"{LINK_STATE} 100.2 down 0\n"
        f"{TOPIC} 99.5 99.3 1000\n"  # before the restore: not counted
        f"{LINK_STATE} 110.1 up 0\n"
        f"{TOPIC} 110.3 102.0 1000\n"  # captured 8 s before the restore: held through the cut
        f"{TOPIC} 110.6 110.2 1000\n"  # captured after it
        f"{TOPIC} 111.0 11"  # torn
    )
    watch = read_watch(watch_file)
    assert first_state_after(watch, 100.0, False) == 100.2 and first_state_after(watch, 110.0, True) == 110.1
    np.testing.assert_allclose(ages_after(watch, 110.0, [TOPIC]), [8.3, 0.4])
    np.testing.assert_allclose(captured_before(watch, 110.0, [TOPIC]), [8.0, -0.2])
    assert len(captured_before(watch, 120.0, [TOPIC])) == 0
