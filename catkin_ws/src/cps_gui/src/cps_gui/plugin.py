"""The operator GUI as an rqt plugin: the five panes of the paper's Fig. 7 in one widget.

rqt creates `FleetOperatorPlugin(context)` inside its own rospy node; the standalone host
(cps_gui.host, command `cps_gui`) does the same with a small context of its own where rqt_gui is
not installed. Settings go through the rqt Settings API (`value`, `set_value`).
"""

import os

from python_qt_binding.QtCore import QObject, Qt, QTimer
from python_qt_binding.QtWidgets import QLabel, QSplitter, QVBoxLayout, QWidget

from cps_gui import topview
from cps_gui.fleet_state import FleetState

try:
    from qt_gui.plugin import Plugin as _PluginBase
except ImportError:  # no rqt: the standalone host plays its part
    _PluginBase = QObject

REFRESH_PERIOD_MS = 200


class FleetOperatorPlugin(_PluginBase):
    """fleet_file: fleet.yaml (default: CPS_FLEET_FILE or cps_bringup's). robots: the mission's
    robots, a subset of the fleet's (default: all of them); the roster, selectors and views show
    only these (a monitoring mission sends back two robots: the others have no data to show).
    with_rviz: embed the rviz pane (default: unless CPS_GUI_NO_RVIZ=1; rviz needs X with
    OpenGL). stale_after_s: age at which data is drawn red."""

    def __init__(self, context, fleet_file=None, with_rviz=None, stale_after_s=2.0, robots=None):
        super().__init__(context)
        self.setObjectName("FleetOperatorPlugin")
        import rospy

        from cps_fleet.fleet import load_fleet, robot_names_arg
        from cps_gui.ros_io import FleetRosIO
        from cps_gui.widgets.changes import ChangesPane
        from cps_gui.widgets.status import StatusPane
        from cps_gui.widgets.teleop import TeleopPane
        from cps_gui.widgets.topview import TopViewPane
        from cps_gui.widgets.video import VideoPane

        if with_rviz is None:
            with_rviz = os.environ.get("CPS_GUI_NO_RVIZ", "") not in ("1", "true")
        self.fleet = robot_names_arg(load_fleet(fleet_file), list(robots) if robots else None)
        self.state = FleetState([(r.name, r.type) for r in self.fleet.robots], stale_after_s=stale_after_s)
        self.io = FleetRosIO(self.fleet, self.state)
        fences, problem = topview.load_fences(self.fleet.site_path)
        if problem:
            rospy.logwarn(f"cps_gui: {problem}")

        self.widget = QWidget()
        self.widget.setObjectName("cps_fleet_operator")
        self.widget.setWindowTitle("Fleet operator")
        self.video = VideoPane(self.io, self.state)
        if with_rviz:
            from cps_gui.widgets.rviz_pane import RvizPane

            self.view3d = RvizPane(self.fleet)
        else:
            self.view3d = QLabel("3D view disabled (no rviz)")
            self.view3d.setObjectName("rviz_pane")
            self.view3d.setAlignment(Qt.AlignCenter)
        self.topview = TopViewPane(self.fleet, self.state, fences)
        self.status = StatusPane(self.fleet, self.state)
        self.teleop = TeleopPane(self.fleet, self.io, self.state)
        self.changes = ChangesPane(self.state, self.focus_on_change)

        # The change list under the top view: a splitter of its own, so that a layout saved before it
        # existed restores without hiding it.
        self.map_splitter = QSplitter(Qt.Vertical)
        self.map_splitter.addWidget(self.topview)
        self.map_splitter.addWidget(self.changes)
        self.map_splitter.setSizes([380, 120])
        self.top_splitter = QSplitter(Qt.Horizontal)
        for pane in (self.video, self.view3d, self.map_splitter):
            self.top_splitter.addWidget(pane)
        self.top_splitter.setSizes([300, 600, 400])
        self.bottom_splitter = QSplitter(Qt.Horizontal)
        self.bottom_splitter.addWidget(self.status)
        self.bottom_splitter.addWidget(self.teleop)
        self.bottom_splitter.setSizes([900, 400])
        self.main_splitter = QSplitter(Qt.Vertical)
        self.main_splitter.addWidget(self.top_splitter)
        self.main_splitter.addWidget(self.bottom_splitter)
        self.main_splitter.setSizes([500, 450])
        layout = QVBoxLayout(self.widget)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.addWidget(self.main_splitter)

        if hasattr(context, "serial_number") and context.serial_number() > 1:
            self.widget.setWindowTitle(f"{self.widget.windowTitle()} ({context.serial_number()})")
        context.add_widget(self.widget)

        self.timer = QTimer(self.widget)
        self.timer.setInterval(REFRESH_PERIOD_MS)
        self.timer.timeout.connect(self.refresh)
        self.timer.start()

    @property
    def panes(self):
        """{name: widget} of the five panes and the change list, e.g. for screenshots and tests."""
        return {
            "video": self.video,
            "view3d": self.view3d,
            "topview": self.topview,
            "status": self.status,
            "teleop": self.teleop,
            "changes": self.changes,
        }

    def refresh(self):
        """Redraw every pane from the latest data; runs on the GUI thread at 5 Hz."""
        for pane in (self.video, self.topview, self.status, self.teleop, self.changes):
            pane.refresh()

    def focus_on_change(self, change):
        """Centre the top view and the 3D view on a MapChange."""
        self.topview.focus_on(*change.center_m[:2])
        if hasattr(self.view3d, "focus_on"):
            self.view3d.focus_on(*change.center_m)

    def shutdown_plugin(self):
        self.timer.stop()
        self.teleop.shutdown()
        if hasattr(self.view3d, "shutdown"):
            self.view3d.shutdown()
        self.io.close()

    def save_settings(self, plugin_settings, instance_settings):
        for key, splitter in self._splitters().items():
            instance_settings.set_value(f"layout/{key}", splitter.saveState())
        for pane in (self.video, self.status, self.teleop):
            pane.save_settings(instance_settings)

    def restore_settings(self, plugin_settings, instance_settings):
        for key, splitter in self._splitters().items():
            state = instance_settings.value(f"layout/{key}", None)
            if state is not None:
                splitter.restoreState(state)
        for pane in (self.video, self.status, self.teleop):
            pane.restore_settings(instance_settings)

    def _splitters(self):
        return {
            "main": self.main_splitter,
            "top": self.top_splitter,
            "bottom": self.bottom_splitter,
            "map": self.map_splitter,
        }
