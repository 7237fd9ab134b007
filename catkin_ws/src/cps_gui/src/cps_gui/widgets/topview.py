"""Pane 3, the secondary top view, drawn with QPainter (a second rviz frame cannot live in the
same process): the projected map, fenced areas, routes with their waypoints, and every robot's
position and heading (outlined red when its pose is stale), and the site changes a monitoring
mission found (appeared green, disappeared red; `focus_on` centres the view on one).
"""

import math

from python_qt_binding.QtCore import QPointF, QRectF, Qt
from python_qt_binding.QtGui import QBrush, QColor, QFont, QImage, QPainter, QPen, QPolygonF
from python_qt_binding.QtWidgets import QSizePolicy, QWidget

from cps_gui import topview
from cps_gui.colours import robot_colour
from cps_gui.widgets.status import STALE_RGB

FENCE_RGBA = (255, 152, 0, 70)


class TopViewPane(QWidget):
    def __init__(self, fleet, state, fences=(), parent=None):
        """fences: [(name, [(x, y), ...])] in `map`, e.g. from cps_gui.topview.load_fences."""
        super().__init__(parent)
        self.setObjectName("topview_pane")
        self.setMinimumSize(200, 160)
        self.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Expanding)
        self.fleet, self.state = fleet, state
        self.fences = list(fences)
        self.routes = {}
        for robot in fleet.robots:
            try:
                self.routes[robot.name] = [(w.x, w.y, w.inspect) for w in fleet.route(robot.name).waypoints]
            except Exception:  # a broken route file is reported by the route controller
                self.routes[robot.name] = []
        self._map_version = -1
        self._map_qimage = None
        self._map = None
        self._poses = {}
        self._map_age_s = math.inf
        self._changes = ()
        self.focus = None  # (x, y) the operator selected, or None: the whole scene

    def refresh(self):
        grid, version, age_s = self.state.projected_map()
        if version != self._map_version:
            self._map_version, self._map = version, grid
            self._map_qimage = None if grid is None else _to_qimage(grid.rgb)
        self._map_age_s = age_s
        self._poses = self.state.poses()
        self._changes = self.state.map_changes()[1]
        self.update()

    def focus_on(self, x, y):
        """Show the square around (x, y) (None: the whole scene again)."""
        self.focus = None if x is None else (x, y)
        self.update()

    def paintEvent(self, _event):
        painter = QPainter(self)
        painter.setRenderHint(QPainter.Antialiasing)
        painter.fillRect(self.rect(), QColor(250, 250, 250))
        point_sets = [[(x, y) for x, y, _ in route] for route in self.routes.values()]
        point_sets += [poly for _, poly in self.fences]
        point_sets.append([(pose.x, pose.y) for pose, _ in self._poses.values()])
        bounds = topview.focus_bounds(*self.focus) if self.focus else topview.scene_bounds(self._map, point_sets)
        to_screen = topview.WorldToScreen.fit(bounds, self.width(), self.height() - 18)

        if self._map_qimage is not None:
            x0, y1 = to_screen(self._map.x_min, self._map.y_min + self._map.height_m)
            x1, y0 = to_screen(self._map.x_min + self._map.width_m, self._map.y_min)
            painter.drawImage(QRectF(x0, y1, x1 - x0, y0 - y1), self._map_qimage)

        painter.setPen(QPen(QColor(230, 120, 0), 2, Qt.DashLine))
        painter.setBrush(QBrush(QColor(*FENCE_RGBA)))
        for _, polygon in self.fences:
            painter.drawPolygon(QPolygonF([QPointF(*to_screen(x, y)) for x, y in polygon]))

        for change in self._changes:
            (cx, cy, _), (sx, sy, _) = change.center_m, change.size_m
            x0, y0 = to_screen(cx - sx / 2, cy + sy / 2)
            x1, y1 = to_screen(cx + sx / 2, cy - sy / 2)
            colour = QColor(*topview.CHANGE_RGB[change.kind])
            painter.setPen(QPen(colour, 2))
            colour.setAlpha(120)
            painter.setBrush(QBrush(colour))
            painter.drawRect(QRectF(x0 - 2, y0 - 2, x1 - x0 + 4, y1 - y0 + 4))
            if change.from_m is not None:  # a move: a line from where the item stood
                painter.drawLine(QPointF(*to_screen(*change.from_m[:2])), QPointF(*to_screen(cx, cy)))

        for index, robot in enumerate(self.fleet.robots):
            colour = QColor(*robot_colour(index))
            route = self.routes.get(robot.name, [])
            painter.setPen(QPen(colour, 1.5, Qt.DotLine))
            painter.setBrush(Qt.NoBrush)
            if len(route) > 1:
                painter.drawPolyline(QPolygonF([QPointF(*to_screen(x, y)) for x, y, _ in route]))
            for x, y, inspect in route:
                painter.setBrush(QBrush(colour) if inspect else Qt.NoBrush)
                painter.drawEllipse(QPointF(*to_screen(x, y)), 3.5, 3.5)

        font = QFont()
        font.setPointSize(8)
        painter.setFont(font)
        for index, robot in enumerate(self.fleet.robots):
            if robot.name not in self._poses:
                continue
            pose, stale = self._poses[robot.name]
            cx, cy = to_screen(pose.x, pose.y)
            size = 11.0
            heading = -pose.yaw_rad  # screen y points down
            tip = QPointF(cx + size * math.cos(heading), cy + size * math.sin(heading))
            left = QPointF(cx + size * 0.6 * math.cos(heading + 2.4), cy + size * 0.6 * math.sin(heading + 2.4))
            right = QPointF(cx + size * 0.6 * math.cos(heading - 2.4), cy + size * 0.6 * math.sin(heading - 2.4))
            painter.setBrush(QBrush(QColor(*robot_colour(index))))
            painter.setPen(QPen(QColor(*STALE_RGB) if stale else QColor(0, 0, 0), 3 if stale else 1))
            painter.drawPolygon(QPolygonF([tip, left, right]))
            painter.setPen(QColor(*STALE_RGB) if stale else QColor(0, 0, 0))
            painter.drawText(QPointF(cx + 9, cy - 9), robot.name)

        stale_map = self.state.is_stale(self._map_age_s)
        painter.setPen(QColor(*STALE_RGB) if stale_map and self._map is not None else QColor(60, 60, 60))
        if self._map is None:
            text = "map: none yet"
        else:
            text = (
                f"map: {self._map.occupied_cells} occupied cells, {self._map.cell_m:.2f} m/px, "
                f"age {self._map_age_s:.1f} s"
            )
        painter.drawText(QRectF(4, self.height() - 18, self.width() - 8, 16), Qt.AlignLeft | Qt.AlignVCenter, text)
        painter.end()


def _to_qimage(rgb):
    height, width, _ = rgb.shape
    return QImage(rgb.data, width, height, 3 * width, QImage.Format_RGB888).copy()
