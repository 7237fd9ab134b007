"""The change list of a monitoring mission: what the twin found against the baseline map (kind,
size, position), newest detection; a click centres the 3D and top views on the change.
"""

from python_qt_binding.QtGui import QColor
from python_qt_binding.QtWidgets import QLabel, QListWidget, QListWidgetItem, QVBoxLayout, QWidget

from cps_gui.topview import CHANGE_RGB


def change_text(change):
    x, y, z = change.center_m
    sx, sy, sz = change.size_m
    text = f"{change.kind}: {sx:.1f} x {sy:.1f} x {sz:.1f} m at ({x:.1f}, {y:.1f}, {z:.1f})"
    if change.from_m is not None:
        text += f" from ({change.from_m[0]:.1f}, {change.from_m[1]:.1f})"
    return text


class ChangesPane(QWidget):
    def __init__(self, state, on_select, parent=None):
        """on_select(change): called with the MapChange the operator clicked."""
        super().__init__(parent)
        self.setObjectName("changes_pane")
        self.state, self.on_select = state, on_select
        self._version = -1
        self._changes = ()
        self.title = QLabel("Site changes: no baseline comparison yet")
        self.title.setWordWrap(True)  # a long line would widen the whole window
        self.list = QListWidget()
        self.list.itemClicked.connect(lambda item: self.on_select(self._changes[self.list.row(item)]))
        layout = QVBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        layout.addWidget(self.title)
        layout.addWidget(self.list)

    def refresh(self):
        version, changes = self.state.map_changes()
        if version == self._version:
            return
        self._version, self._changes = version, changes
        self.list.clear()
        counts = {kind: sum(c.kind == kind for c in changes) for kind in ("appeared", "disappeared", "moved")}
        self.title.setText(
            f"Site changes: {counts['appeared']} appeared, {counts['disappeared']} disappeared, "
            f"{counts['moved']} moved (click one to centre the views on it)"
        )
        for change in changes:
            item = QListWidgetItem(change_text(change))
            item.setForeground(QColor(*CHANGE_RGB[change.kind]))
            self.list.addItem(item)
