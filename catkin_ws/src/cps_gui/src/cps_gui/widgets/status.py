"""Pane 4, logging and status: plots of the link per robot (bandwidth: every managed stream, each
robot's cloud and video, stacked against the manager's budget line; rate, latency) and battery, the fleet health table with alarms, and a filtered /rosout.
Everything is redrawn by `refresh` from a FleetState; stale values are drawn in red.
"""

import math
import time

import pyqtgraph as pg
from python_qt_binding.QtCore import Qt
from python_qt_binding.QtGui import QColor
from python_qt_binding.QtWidgets import (
    QComboBox,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QPlainTextEdit,
    QSplitter,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from cps_fleet import names
from cps_gui.colours import robot_colour
from cps_gui.fleet_state import STREAMS

STALE_RGB = (198, 40, 40)
ALARM_BACKGROUND = QColor(255, 205, 210)
HEALTH_COLUMNS = (
    "robot",
    "mode",
    "mission",
    "battery %",
    "heartbeat s",
    "link",
    "map voxels",
    "dropped",
    "priority",
    "alarms",
)
LEVELS = ("DEBUG", "INFO", "WARN", "ERROR", "FATAL")


class StatusPane(QWidget):
    def __init__(self, fleet, state, parent=None):
        super().__init__(parent)
        self.setObjectName("status_pane")
        self.fleet, self.state = fleet, state
        robot_names = fleet.robot_names

        self.plots = pg.GraphicsLayoutWidget()
        self.plots.setBackground("w")
        self.curves = {}
        specs = (("bandwidth", "MB/s"), ("rate", "Hz"), ("latency", "ms"), ("battery", "%"))
        self.plot_items = {}
        for column, (key, unit) in enumerate(specs):
            plot = self.plots.addPlot(row=0, col=column, title=f"{key} [{unit}]")
            plot.showGrid(x=True, y=True, alpha=0.3)
            plot.setLabel("bottom", "t [s]")
            if column == 0:
                plot.addLegend(offset=(5, 5))
            self.plot_items[key] = plot
            if key == "bandwidth":
                continue  # stacked streams, below
            for index, name in enumerate(robot_names):
                pen = pg.mkPen(robot_colour(index), width=2)
                self.curves[(key, name)] = _without_segments(plot.plot([], [], pen=pen))
        # Bandwidth: one filled layer per (robot, stream), stacked robot by robot, cloud then video
        # (the video a lighter shade of the robot's colour); each curve is the top of its layer.
        self.stack_curves = {}
        layers = [(name, stream) for name in robot_names for stream in STREAMS]
        for depth, (name, stream) in enumerate(layers):
            colour = QColor(*robot_colour(robot_names.index(name)))
            if stream == "video":
                colour = colour.lighter(150)
            fill = QColor(colour)
            fill.setAlpha(170)
            curve = self.plot_items["bandwidth"].plot(
                [], [], pen=pg.mkPen(colour, width=1), fillLevel=0.0, brush=fill, name=f"{name} {stream}"
            )
            curve.setZValue(-depth)  # lower layers drawn over the higher ones' fill
            self.stack_curves[(name, stream)] = _without_segments(curve)
        self.budget_curve = _without_segments(
            self.plot_items["bandwidth"].plot(
                [], [], pen=pg.mkPen((0, 0, 0), width=2, style=Qt.DashLine), name="budget"
            )
        )
        # The manager's estimate of the link (what its budget is made from) and, on the test bed,
        # the true capacity the scenario set (an oracle the manager never allocates from).
        self.estimate_curve = _without_segments(
            self.plot_items["bandwidth"].plot([], [], pen=pg.mkPen((30, 90, 200), width=2), name="link estimate")
        )
        self.true_capacity_curve = _without_segments(
            self.plot_items["bandwidth"].plot(
                [], [], pen=pg.mkPen((120, 120, 120), width=2, style=Qt.DotLine), name="true capacity (oracle)"
            )
        )

        self.link_label = QLabel("link: no data")
        self.link_lost_banner = QLabel("")
        self.link_lost_banner.setObjectName("link_lost_banner")
        self.link_lost_banner.setStyleSheet(
            "background: rgb(%d,%d,%d); color: white; font-weight: bold; font-size: 16pt; padding: 6px" % STALE_RGB
        )
        self.link_lost_banner.hide()
        self.table = QTableWidget(len(robot_names), len(HEALTH_COLUMNS))
        self.table.setHorizontalHeaderLabels(HEALTH_COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QTableWidget.NoEditTriggers)
        for row in range(len(robot_names)):
            for col in range(len(HEALTH_COLUMNS)):
                self.table.setItem(row, col, QTableWidgetItem(""))

        self.level_combo = QComboBox()
        self.level_combo.addItems(LEVELS)
        self.level_combo.setCurrentText("INFO")
        self.filter_edit = QLineEdit()
        self.filter_edit.setPlaceholderText("filter: node or text")
        self.log_view = QPlainTextEdit()
        self.log_view.setReadOnly(True)
        self.log_view.setMaximumBlockCount(1000)
        self._log_shown = None
        self.level_combo.currentIndexChanged.connect(self._invalidate_log)
        self.filter_edit.textChanged.connect(self._invalidate_log)

        log_box = QWidget()
        log_layout = QVBoxLayout(log_box)
        log_layout.setContentsMargins(0, 0, 0, 0)
        filters = QHBoxLayout()
        filters.addWidget(QLabel(names.ROSOUT))
        filters.addWidget(self.level_combo)
        filters.addWidget(self.filter_edit, 1)
        log_layout.addLayout(filters)
        log_layout.addWidget(self.log_view)

        table_box = QWidget()
        table_layout = QVBoxLayout(table_box)
        table_layout.setContentsMargins(0, 0, 0, 0)
        table_layout.addWidget(self.link_lost_banner)
        table_layout.addWidget(self.link_label)
        table_layout.addWidget(self.table)

        self.splitter = QSplitter(Qt.Vertical)
        self.splitter.addWidget(self.plots)
        self.splitter.addWidget(table_box)
        self.splitter.addWidget(log_box)
        self.splitter.setSizes([220, 170, 110])
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.splitter)

    def refresh(self):
        self._refresh_plots()
        self._refresh_table()
        self._refresh_log()

    def _refresh_plots(self):
        per_robot, budget, stats_age_s = self.state.plot_series()
        for (key, name), curve in self.curves.items():
            t, v = per_robot[name][key]
            curve.setData(t, [x if math.isfinite(x) else 0.0 for x in v])
        for (name, stream), (t, top) in stacked_streams(self.state.stream_series()).items():
            self.stack_curves[(name, stream)].setData(t, top)
        self.budget_curve.setData(*budget)
        estimate, estimate_series, true_series = self.state.link_estimate()
        self.estimate_curve.setData(*estimate_series)
        self.true_capacity_curve.setData(*true_series)
        available_mbps, allocation, allocation_age_s = self.state.link_summary()
        parts = [_age_text("stats", stats_age_s), _age_text("allocation", allocation_age_s)]
        if allocation is not None:
            parts.append(
                f"budget {allocation.budget_mbytes_per_s:.2f} MB/s, allocated "
                f"{allocation.allocated_mbytes_per_s:.2f} MB/s" + ("" if allocation.feasible else " (INFEASIBLE)")
            )
        if estimate is not None:
            parts.append(f"link {estimate.text()}")
        elif math.isfinite(available_mbps):
            parts.append(f"link {available_mbps:.1f} Mbit/s")
        self.link_label.setText(" | ".join(parts))
        stale = self.state.is_stale(stats_age_s) or (allocation is not None and self.state.is_stale(allocation_age_s))
        self.link_label.setStyleSheet("color: rgb(%d,%d,%d); font-weight: bold" % STALE_RGB if stale else "")

    def _refresh_link_lost(self):
        text = self.state.link_lost_text()
        if text != self.link_lost_banner.text():
            self.link_lost_banner.setText(text)
        self.link_lost_banner.setVisible(bool(text))

    def _refresh_table(self):
        self._refresh_link_lost()
        for row, health in enumerate(self.state.health_rows()):
            battery = "--" if not math.isfinite(health.battery_percent) else f"{health.battery_percent:.0f}"
            heartbeat = "never" if not math.isfinite(health.heartbeat_age_s) else f"{health.heartbeat_age_s:.1f}"
            values = (
                health.robot,
                health.mode,
                health.mission_state,
                battery,
                heartbeat,
                health.link_state,
                str(health.map_voxels),
                str(health.clouds_dropped),
                "" if health.priority is None else ("high" if health.priority else "normal"),
                ", ".join(health.alarms),
            )
            stale_columns = {3: health.battery_stale, 4: health.heartbeat_stale, 5: health.link_state not in ("ok",)}
            for col, text in enumerate(values):
                item = self.table.item(row, col)
                if item.text() != text:
                    item.setText(text)
                red = stale_columns.get(col, False)
                item.setForeground(QColor(*STALE_RGB) if red else QColor(0, 0, 0))
                item.setBackground(ALARM_BACKGROUND if health.alarms else QColor(255, 255, 255))

    def _invalidate_log(self, *_):
        self._log_shown = None

    def _refresh_log(self):
        version, entries = self.state.log_entries()
        key = (version, self.level_combo.currentIndex(), self.filter_edit.text())
        if key == self._log_shown:
            return
        self._log_shown = key
        lines = filter_log(entries, self.level_combo.currentText(), self.filter_edit.text())
        self.log_view.setPlainText("\n".join(lines[-500:]))
        self.log_view.verticalScrollBar().setValue(self.log_view.verticalScrollBar().maximum())

    def save_settings(self, settings):
        settings.set_value("status/splitter", self.splitter.saveState())
        settings.set_value("status/log_level", self.level_combo.currentText())
        settings.set_value("status/log_filter", self.filter_edit.text())

    def restore_settings(self, settings):
        state = settings.value("status/splitter", None)
        if state is not None:
            self.splitter.restoreState(state)
        level = settings.value("status/log_level", None)
        if level in LEVELS:
            self.level_combo.setCurrentText(level)
        text = settings.value("status/log_filter", None)
        if text is not None:
            self.filter_edit.setText(str(text))


def stacked_streams(series):
    """{(robot, stream): (t, top of its layer)} from FleetState.stream_series(): each layer's top is
    the sum of its and every earlier layer's MB/s (non-finite counted as 0) at the shared instants."""
    out, below, shared_t = {}, None, None
    for robot, stream, t, values in series:
        values = [v if math.isfinite(v) else 0.0 for v in values]
        if below is None or len(below) != len(values):
            below, shared_t = [0.0] * len(values), t
        top = [b + v for b, v in zip(below, values)]
        out[(robot, stream)] = (shared_t, top)
        below = top
    return out


def _without_segments(item):
    """pyqtgraph 0.13.1's segmented line drawing calls a QPainter.drawLines overload that PyQt5
    5.15 (Debian 12) does not have; draw curves as one path instead."""
    item.curve.setSegmentedLineMode("off")
    return item


def filter_log(entries, min_level, text):
    """Log lines at or above `min_level` whose node or message contains `text` (case-insensitive)."""
    floor = LEVELS.index(min_level) if min_level in LEVELS else 0
    needle = (text or "").lower()
    lines = []
    for wall_s, level, node, message in entries:
        if level in LEVELS and LEVELS.index(level) < floor:
            continue
        if needle and needle not in node.lower() and needle not in message.lower():
            continue
        stamp = time.strftime("%H:%M:%S", time.localtime(wall_s)) if wall_s > 0 else "--:--:--"
        lines.append(f"{stamp} [{level}] {node}: {message}")
    return lines


def _age_text(what, age_s):
    return f"{what}: never" if not math.isfinite(age_s) else f"{what} {age_s:.1f} s ago"
