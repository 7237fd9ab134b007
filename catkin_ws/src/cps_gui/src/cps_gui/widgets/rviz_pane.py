"""Pane 2, the primary 3D view: an embedded rviz VisualizationFrame showing the fleet config
(cps_gui.rviz_config) with rviz's own menus, panels and status bar hidden.

rviz needs an X server with OpenGL (Xvfb with Mesa's llvmpipe is enough) and a ROS master; only
one VisualizationFrame can live in a process.
"""

import os
import tempfile

from python_qt_binding.QtWidgets import QVBoxLayout, QWidget

from cps_gui import rviz_config

# How far the orbit camera stands from a change the operator selected.
FOCUS_DISTANCE_M = 8.0


class RvizPane(QWidget):
    def __init__(self, fleet, parent=None):
        super().__init__(parent)
        self.setObjectName("rviz_pane")
        from rviz import bindings as rviz

        self.frame = rviz.VisualizationFrame()
        self.frame.setSplashPath("")
        self.frame.initialize()
        with tempfile.NamedTemporaryFile("w", suffix=".rviz", prefix="cps_gui_", delete=False) as stream:
            stream.write(rviz_config.dump(rviz_config.fleet_rviz_config(fleet)))
            self.config_path = stream.name
        try:
            config = rviz.Config()
            reader = rviz.YamlConfigReader()
            reader.readFile(config, self.config_path)
            if reader.error():
                raise RuntimeError(f"rviz cannot read {self.config_path}: {reader.errorMessage()}")
            self.frame.load(config)
        finally:
            os.unlink(self.config_path)
        self.frame.setMenuBar(None)
        self.frame.setStatusBar(None)
        self.frame.setHideButtonVisibility(False)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.frame)

    def refresh(self):
        """rviz draws itself at its configured frame rate."""

    def focus_on(self, x, y, z):
        """Turn the orbit view's focal point to (x, y, z) in the fixed frame, closer in."""
        view = self.frame.getManager().getViewManager().getCurrent()
        view.subProp("Focal Point").setValue(f"{x}; {y}; {z}")
        view.subProp("Distance").setValue(FOCUS_DISTANCE_M)

    def shutdown(self):
        """Nothing to do: the frame goes with its parent widget. Never `frame.close()`: rviz's
        closeEvent may open a modal "save the config?" dialog, which nobody answers under Xvfb
        and which hangs the exit."""
