"""Pane 5, teleoperation: robot choice, virtual joystick, speedometer, auto/teleop switch,
priority toggle, take-off/land for the quadrotor and the stop-all button.

While the knob is held (or a key is down) the command is published at 10 Hz, from a thread of its
own (cps_gui.command_stream) so that a slow repaint does not slow it; the release sends one zero
command and stops. The stream goes on only while the GUI thread renews its lease, and cps_sim's
dead-man stops a robot whose commands stop coming, so a frozen or closed GUI cannot leave a robot
driving.
"""

import math

from python_qt_binding.QtCore import QPointF, QRectF, Qt, QTimer, Signal
from python_qt_binding.QtGui import QBrush, QColor, QFont, QPainter, QPen
from python_qt_binding.QtWidgets import (
    QButtonGroup,
    QCheckBox,
    QComboBox,
    QGridLayout,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QRadioButton,
    QSizePolicy,
    QSlider,
    QVBoxLayout,
    QWidget,
)

from cps_gui import joystick
from cps_gui.command_stream import CommandStream

# The command stream's period, and how long it goes on without the GUI thread (less than the robots'
# dead-man, cps_sim.fleet_control.DEADMAN_S 0.5 s: a frozen GUI stops its robot within the two).
PUBLISH_PERIOD_S = 0.1
COMMAND_LEASE_S = 0.35

_KEY_NAMES = {
    Qt.Key_W: "w",
    Qt.Key_S: "s",
    Qt.Key_A: "a",
    Qt.Key_D: "d",
    Qt.Key_Q: "q",
    Qt.Key_E: "e",
    Qt.Key_R: "r",
    Qt.Key_F: "f",
    Qt.Key_Up: "up",
    Qt.Key_Down: "down",
    Qt.Key_Left: "left",
    Qt.Key_Right: "right",
}


class JoystickPad(QWidget):
    """A round pad with a knob: dragging emits the knob's offset from the centre in pixels."""

    moved = Signal(float, float)
    released = Signal()

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setMinimumSize(140, 140)
        self.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Expanding)
        self._knob = QPointF(0.0, 0.0)
        self._dragging = False

    @property
    def radius_px(self):
        return max(10.0, min(self.width(), self.height()) / 2.0 - 14.0)

    @property
    def centre(self):
        return QPointF(self.width() / 2.0, self.height() / 2.0)

    def mousePressEvent(self, event):
        if event.button() == Qt.LeftButton:
            self._dragging = True
            self._drag_to(event.localPos())

    def mouseMoveEvent(self, event):
        if self._dragging:
            self._drag_to(event.localPos())

    def mouseReleaseEvent(self, event):
        if event.button() == Qt.LeftButton and self._dragging:
            self._dragging = False
            self._knob = QPointF(0.0, 0.0)
            self.update()
            self.released.emit()

    def _drag_to(self, pos):
        offset = QPointF(pos) - self.centre
        x, y = joystick.clip_to_unit_circle(offset.x() / self.radius_px, offset.y() / self.radius_px)
        self._knob = QPointF(x * self.radius_px, y * self.radius_px)
        self.update()
        self.moved.emit(offset.x(), offset.y())

    def paintEvent(self, _event):
        painter = QPainter(self)
        painter.setRenderHint(QPainter.Antialiasing)
        c, r = self.centre, self.radius_px
        painter.setPen(QPen(QColor(90, 90, 90), 2))
        painter.setBrush(QBrush(QColor(225, 228, 232)))
        painter.drawEllipse(c, r, r)
        painter.setPen(QPen(QColor(160, 160, 160), 1, Qt.DashLine))
        painter.drawLine(QPointF(c.x() - r, c.y()), QPointF(c.x() + r, c.y()))
        painter.drawLine(QPointF(c.x(), c.y() - r), QPointF(c.x(), c.y() + r))
        painter.setPen(QPen(QColor(30, 30, 30), 2))
        painter.setBrush(QBrush(QColor(40, 110, 200) if self._dragging else QColor(120, 130, 140)))
        painter.drawEllipse(c + self._knob, 13, 13)


class Speedometer(QWidget):
    """A car-style dial: the robot's speed over ground against its joystick full scale."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setMinimumSize(120, 90)
        self.speed_mps = math.nan
        self.full_scale_mps = 1.0
        self.stale = True

    def set_speed(self, speed_mps, full_scale_mps, stale):
        self.speed_mps, self.full_scale_mps, self.stale = speed_mps, max(full_scale_mps, 1e-3), stale
        self.update()

    def paintEvent(self, _event):
        painter = QPainter(self)
        painter.setRenderHint(QPainter.Antialiasing)
        side = min(self.width(), self.height() * 1.6)
        rect = QRectF((self.width() - side) / 2 + 8, 8, side - 16, side - 16)
        painter.setPen(QPen(QColor(80, 80, 80), 6))
        painter.drawArc(rect, 0, 180 * 16)
        centre = rect.center()
        radius = rect.width() / 2
        fraction = 0.0 if not math.isfinite(self.speed_mps) else min(abs(self.speed_mps) / self.full_scale_mps, 1.0)
        angle = math.pi * (1.0 - fraction)
        painter.setPen(QPen(QColor(200, 40, 40), 3))
        painter.drawLine(
            centre, QPointF(centre.x() + 0.85 * radius * math.cos(angle), centre.y() - 0.85 * radius * math.sin(angle))
        )
        painter.setPen(QColor(200, 0, 0) if self.stale else QColor(20, 20, 20))
        font = QFont()
        font.setPointSize(10)
        painter.setFont(font)
        text = "-- m/s" if not math.isfinite(self.speed_mps) else f"{self.speed_mps:.2f} m/s"
        painter.drawText(QRectF(rect.left(), centre.y() - 22, rect.width(), 20), Qt.AlignCenter, text)


class TeleopPane(QWidget):
    """Drives one robot at a time through a FleetRosIO (`io`); reads speed from a FleetState."""

    # (ok, text) from the priority service's worker thread, delivered on the GUI thread.
    priority_reply = Signal(bool, str)

    def __init__(self, fleet, io, state, parent=None):
        super().__init__(parent)
        self.setObjectName("teleop_pane")
        self.fleet, self.io, self.state = fleet, io, state
        self.setFocusPolicy(Qt.StrongFocus)
        self._drag = None
        self._keys = set()

        self.robot_combo = QComboBox()
        for robot in fleet.robots:
            self.robot_combo.addItem(f"{robot.name} ({robot.type})", robot.name)
        self.pad = JoystickPad()
        self.climb_slider = QSlider(Qt.Vertical)
        self.climb_slider.setRange(-100, 100)
        self.climb_slider.setToolTip("climb (quadrotor); springs back to 0 on release")
        self.strafe_check = QCheckBox("strafe (x = sideways)")
        self.takeoff_button = QPushButton("Take off")
        self.land_button = QPushButton("Land")
        self.speedometer = Speedometer()
        self.auto_radio = QRadioButton("auto")
        self.teleop_radio = QRadioButton("teleop")
        self._mode_group = QButtonGroup(self)
        self._mode_group.addButton(self.auto_radio)
        self._mode_group.addButton(self.teleop_radio)
        self.priority_button = QPushButton("High priority")
        self.priority_button.setCheckable(True)
        self.stop_button = QPushButton("STOP ALL")
        self.stop_button.setCheckable(True)
        self.stop_button.setStyleSheet(
            "QPushButton { background: #c62828; color: white; font-weight: bold; }"
            "QPushButton:checked { background: #7f0000; }"
        )
        self.status_label = QLabel("")
        self.status_label.setWordWrap(True)

        top = QHBoxLayout()
        top.addWidget(QLabel("Robot"))
        top.addWidget(self.robot_combo, 1)
        pad_row = QHBoxLayout()
        pad_row.addWidget(self.pad, 1)
        pad_row.addWidget(self.climb_slider)
        controls = QGridLayout()
        controls.addWidget(self.auto_radio, 0, 0)
        controls.addWidget(self.teleop_radio, 0, 1)
        controls.addWidget(self.priority_button, 1, 0, 1, 2)
        controls.addWidget(self.strafe_check, 2, 0, 1, 2)
        controls.addWidget(self.takeoff_button, 3, 0)
        controls.addWidget(self.land_button, 3, 1)
        controls.addWidget(self.speedometer, 4, 0, 1, 2)
        body = QHBoxLayout()
        body.addLayout(pad_row, 3)
        body.addLayout(controls, 2)
        layout = QVBoxLayout(self)
        layout.addLayout(top)
        layout.addLayout(body, 1)
        layout.addWidget(self.stop_button)
        layout.addWidget(self.status_label)

        self._stream = CommandStream(self.io.publish_velocity, PUBLISH_PERIOD_S, COMMAND_LEASE_S)
        self._lease_timer = QTimer(self)  # the GUI thread's renewals: a frozen GUI stops sending
        self._lease_timer.setInterval(int(PUBLISH_PERIOD_S * 1000))
        self._lease_timer.timeout.connect(self._stream.renew)
        self.pad.moved.connect(self._on_drag)
        self.pad.released.connect(self._on_release)
        self.climb_slider.valueChanged.connect(self._on_climb)
        self.strafe_check.toggled.connect(self._command_changed)
        self.climb_slider.sliderReleased.connect(lambda: self.climb_slider.setValue(0))
        self.robot_combo.currentIndexChanged.connect(self._on_robot_changed)
        self.auto_radio.clicked.connect(lambda: self.set_mode("auto"))
        self.teleop_radio.clicked.connect(lambda: self.set_mode("teleop"))
        self.priority_button.clicked.connect(self._on_priority)
        self.priority_reply.connect(self._on_priority_reply)
        self.stop_button.toggled.connect(self._on_stop)
        self.takeoff_button.clicked.connect(lambda: self._flight("takeoff"))
        self.land_button.clicked.connect(lambda: self._flight("land"))
        self._on_robot_changed()

    @property
    def robot(self):
        return self.fleet.robot(self.robot_combo.currentData())

    def select_robot(self, name):
        index = self.robot_combo.findData(name)
        if index < 0:
            raise ValueError(f"robot '{name}' is not in the fleet")
        self.robot_combo.setCurrentIndex(index)

    def _on_robot_changed(self, *_):
        self._stop_driving()
        limits = joystick.speed_limits(self.robot.robot_type)
        self.strafe_check.setVisible(limits.can_strafe)
        self.strafe_check.setChecked(False)
        self.climb_slider.setVisible(limits.can_climb)
        flies = self.robot.name in self.io.flight_pubs
        self.takeoff_button.setVisible(flies)
        self.land_button.setVisible(flies)

    def _current_command(self):
        robot_type = self.robot.robot_type
        climb = self.climb_slider.value() / 100.0
        if self._drag is not None:
            dx, dy = self._drag
            return joystick.drag_to_command(
                robot_type, dx, dy, self.pad.radius_px, climb=climb, strafe=self.strafe_check.isChecked()
            )
        if self._keys:
            command = joystick.keys_to_command(robot_type, frozenset(self._keys))
            if climb and not command.linear_z:
                command = joystick.axes_to_command(robot_type, 0.0, 0.0, climb=climb)
            return command
        return joystick.axes_to_command(robot_type, 0.0, 0.0, climb=climb)

    @property
    def last_command(self):
        """The command last sent to the robot (zero before any)."""
        sent = self._stream.last_command
        return joystick.ZERO if sent is None else sent

    def _on_drag(self, dx, dy):
        self._drag = (dx, dy)
        self._start_driving()

    def _on_release(self):
        self._drag = None
        self._maybe_stop()

    def _on_climb(self, value):
        if value:
            self._start_driving()
        else:
            self._maybe_stop()

    def _start_driving(self):
        if self.stop_button.isChecked():
            self.status_label.setText("stop-all is engaged: release it to drive")
        self._stream.drive(self.robot.name, self._current_command())
        if not self._lease_timer.isActive():  # (start() would restart its interval at every move)
            self._lease_timer.start()

    def _command_changed(self, *_):
        """The command the stream sends next, where a control it depends on changed mid-drive."""
        if self._stream.driving:
            self._stream.drive(self.robot.name, self._current_command())

    def _maybe_stop(self):
        if self._drag is None and not self._keys and self.climb_slider.value() == 0:
            self._stop_driving()
        else:
            self._command_changed()

    def _stop_driving(self):
        """Stop the 10 Hz stream and send exactly one zero command."""
        self._lease_timer.stop()
        self._stream.stop(final=joystick.ZERO)

    def keyPressEvent(self, event):
        key = _KEY_NAMES.get(event.key())
        if key is None:
            return super().keyPressEvent(event)
        if not event.isAutoRepeat():
            self._keys.add(key)
            self._start_driving()
        event.accept()

    def keyReleaseEvent(self, event):
        key = _KEY_NAMES.get(event.key())
        if key is None:
            return super().keyReleaseEvent(event)
        if not event.isAutoRepeat():
            self._keys.discard(key)
            self._maybe_stop()
        event.accept()

    def focusOutEvent(self, event):
        self._keys.clear()
        self._maybe_stop()
        super().focusOutEvent(event)

    def set_mode(self, mode):
        self.io.set_mode(self.robot.name, mode)
        (self.auto_radio if mode == "auto" else self.teleop_radio).setChecked(True)
        self.status_label.setText(f"{self.robot.name}: {mode} requested")

    def _on_priority(self, checked):
        robot = self.robot.name
        self.priority_button.setEnabled(False)
        self.status_label.setText(f"{robot}: asking for priority {int(checked)}...")
        self.io.set_priority(robot, 1 if checked else 0, lambda ok, text: self.priority_reply.emit(ok, text))

    def _on_priority_reply(self, ok, text):
        self.priority_button.setEnabled(True)
        if not ok:
            self.priority_button.setChecked(not self.priority_button.isChecked())
        self.status_label.setText(("priority set" if ok else "priority NOT set") + (f": {text}" if text else ""))
        self.status_label.setStyleSheet("" if ok else "color: #c62828")

    def _on_stop(self, stop):
        if stop:
            self._drag = None
            self._keys.clear()
            self._stop_driving()
        self.io.set_estop(stop)
        self.stop_button.setText("STOPPED: click to release" if stop else "STOP ALL")
        self.status_label.setText("all robots stopped" if stop else "stop-all released")

    def _flight(self, command):
        self.io.flight_command(self.robot.name, command)
        self.status_label.setText(f"{self.robot.name}: {command}")

    def refresh(self):
        """Timer redraw: mode, speed and priority of the selected robot from the store."""
        name = self.robot.name
        rows = {row.robot: row for row in self.state.health_rows()}
        row = rows.get(name)
        if row is not None:
            if row.mode == "auto" and not self.auto_radio.isChecked():
                self.auto_radio.setChecked(True)
            elif row.mode == "teleop" and not self.teleop_radio.isChecked():
                self.teleop_radio.setChecked(True)
            if row.priority is not None and self.priority_button.isEnabled():
                self.priority_button.setChecked(row.priority == 1)
        poses = self.state.poses()
        stale = name not in poses or poses[name][1]
        self.speedometer.set_speed(
            self.state.speed_mps(name), joystick.speed_limits(self.robot.robot_type).max_forward_mps, stale
        )

    def save_settings(self, settings):
        settings.set_value("teleop/robot", self.robot.name)

    def restore_settings(self, settings):
        name = settings.value("teleop/robot", None)
        if name and self.robot_combo.findData(name) >= 0:
            self.select_robot(name)

    def shutdown(self):
        self._drag = None
        self._keys.clear()
        self._lease_timer.stop()
        self._stream.close(final=joystick.ZERO)
