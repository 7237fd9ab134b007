"""The GUI's side of monitoring: /twin/map_changes as the map server builds it becomes the change
list, and the views can centre on a change; the list pane shows and selects changes."""

import pytest
from std_msgs.msg import Header

from cps_fleet import names
from cps_gui.fleet_state import FleetState
from cps_gui.ros_io import map_changes_of
from cps_gui.topview import focus_bounds
from cps_mapping.change_detection import Change
from cps_mapping.map_messages import change_markers


def _changes():
    return [
        Change("disappeared", 100, (3.1, -1.0, 0.5), (1.0, 1.0, 1.0), 0.1, (2.7, -1.5, 0.0), (3.7, -0.5, 1.0)),
        Change("appeared", 40, (3.0, -3.5, 0.8), (0.8, 0.2, 1.6), 0.04, (2.6, -3.9, 0.0), (3.4, -3.7, 1.6)),
        Change(
            "moved",
            60,
            (5.0, 1.0, 0.5),
            (0.8, 0.8, 1.0),
            0.06,
            (4.6, 0.6, 0.0),
            (5.4, 1.4, 1.0),
            displacement_m=(0.0, 1.0, 0.0),
            from_m=(5.0, 0.0, 0.5),
        ),  # fmt: skip
    ]


def test_markers_of_the_map_server_become_the_change_list():
    changes = map_changes_of(change_markers(_changes(), Header(frame_id=names.MAP_FRAME)))
    assert [c.kind for c in changes] == ["disappeared", "appeared", "moved"]
    assert changes[0].center_m == pytest.approx((3.2, -1.0, 0.5))
    assert changes[1].size_m == pytest.approx((0.8, 0.2, 1.6)) and changes[1].from_m is None
    assert changes[2].center_m == pytest.approx((5.0, 1.0, 0.5)) and changes[2].from_m == pytest.approx((5.0, 0.0, 0.5))
    state = FleetState([("champ", "legged_depth")])
    version, _ = state.map_changes()
    state.set_map_changes(changes)
    assert state.map_changes() == (version + 1, tuple(changes))
    assert map_changes_of(change_markers([], Header(frame_id=names.MAP_FRAME))) == []


def test_focus_is_a_square_around_the_change():
    b = focus_bounds(3.2, -1.0, half_side_m=2.0)
    assert (b.x_min, b.y_min, b.x_max, b.y_max) == pytest.approx((1.2, -3.0, 5.2, 1.0))


def test_change_pane_lists_and_selects(qapp):
    from cps_gui.widgets.changes import ChangesPane

    state = FleetState([("champ", "legged_depth")])
    selected = []
    pane = ChangesPane(state, selected.append)
    state.set_map_changes(map_changes_of(change_markers(_changes(), Header(frame_id=names.MAP_FRAME))))
    pane.refresh()
    assert pane.list.count() == 3 and "1 appeared, 1 disappeared, 1 moved" in pane.title.text()
    assert pane.list.item(0).text().startswith("disappeared: 1.0 x 1.0 x 1.0 m at (3.2, -1.0")
    assert pane.list.item(2).text().endswith("from (5.0, 0.0)")
    pane.list.itemClicked.emit(pane.list.item(1))
    assert selected[0].kind == "appeared"
