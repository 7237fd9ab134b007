"""Pane 1, video: the operator picks a camera robot; the pane shows its managed video
(`<robot>/camera/image_raw/compressed`, at the level and rate the bandwidth manager allocated) and
says so on /tissue/selected_robot, so that the manager gives that robot operator-quality video.
Any other sensor_msgs/Image or CompressedImage topic can be picked in the topic dropdown (found by
type, refreshed). Under the picture: size, frame rate, bandwidth, age (red when stale), latency
(header stamp to display, wall clock) and the level and rate the robot's video status reports.
Only the topic on screen is subscribed; a frame is converted when it is new and drawn.
"""

import math
import time

import numpy as np
from python_qt_binding.QtCore import Qt
from python_qt_binding.QtGui import QImage, QPixmap
from python_qt_binding.QtWidgets import QComboBox, QHBoxLayout, QLabel, QSizePolicy, QVBoxLayout, QWidget

from cps_fleet import names

_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8UC1": 1, "8UC3": 3}


def frame_to_rgb(frame, max_side_px=640):
    """An ImageFrame as an HxWx3 uint8 array, every n-th pixel so that no side exceeds
    `max_side_px`. ValueError for unsupported encodings or data shorter than height x step."""
    channels = _CHANNELS.get(frame.encoding)
    if channels is None:
        raise ValueError(f"unsupported image encoding '{frame.encoding}' (shown: {', '.join(_CHANNELS)})")
    if frame.width <= 0 or frame.height <= 0:
        raise ValueError(f"empty image ({frame.width}x{frame.height})")
    step = frame.step or frame.width * channels
    if step < frame.width * channels or len(frame.data) < step * frame.height:
        raise ValueError(f"image data has {len(frame.data)} bytes, expected {frame.height} rows of {step}")
    rows = np.frombuffer(frame.data, dtype=np.uint8, count=step * frame.height).reshape(frame.height, step)
    pixels = rows[:, : frame.width * channels].reshape(frame.height, frame.width, channels)
    stride = max(1, int(math.ceil(max(frame.width, frame.height) / float(max_side_px))))
    pixels = pixels[::stride, ::stride]
    if channels == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    elif frame.encoding.startswith("bgr"):
        pixels = pixels[:, :, 2::-1]
    else:
        pixels = pixels[:, :, :3]
    return np.ascontiguousarray(pixels)


def preferred_image_topic(topics, wanted=""):
    """The topic to show when the operator has not picked one: `wanted` (a restored camera), else
    the first topic; either through its `/compressed` variant when that is advertised."""
    available = set(topics)
    base = wanted or (topics[0] if topics else "")
    compressed = f"{base}/{names.COMPRESSED_SUFFIX}"
    if base and compressed in available:
        return compressed
    return base


def rgb_to_qimage(rgb):
    height, width, _ = rgb.shape
    return QImage(rgb.data, width, height, 3 * width, QImage.Format_RGB888).copy()


class VideoPane(QWidget):
    def __init__(self, io, state, parent=None):
        super().__init__(parent)
        self.setObjectName("video_pane")
        self.io, self.state = io, state
        self.robot_combo = QComboBox()
        self.robot_combo.setObjectName("video_robot")
        for robot in io.fleet.robots:
            if robot.has_depth_camera:
                self.robot_combo.addItem(robot.name, robot.name)
        self.combo = QComboBox()
        self.combo.setSizeAdjustPolicy(QComboBox.AdjustToMinimumContentsLengthWithIcon)
        self.picture = QLabel("no image topic yet")
        self.picture.setAlignment(Qt.AlignCenter)
        self.picture.setSizePolicy(QSizePolicy.Ignored, QSizePolicy.Ignored)
        self.picture.setMinimumSize(160, 120)
        self.picture.setStyleSheet("background: #202020; color: #dddddd")
        self.info = QLabel("")
        top = QHBoxLayout()
        top.addWidget(QLabel("Robot"))
        top.addWidget(self.robot_combo)
        top.addWidget(QLabel("Camera"))
        top.addWidget(self.combo, 1)
        layout = QVBoxLayout(self)
        layout.addLayout(top)
        layout.addWidget(self.picture, 1)
        layout.addWidget(self.info)
        self._wanted_topic = ""
        self._picked = False  # the operator chose the topic in the dropdown: keep it, raw or not
        self._shown_received_s = None
        self._latency_ms = math.nan
        self._pixmap = None
        self.combo.currentIndexChanged.connect(self._on_choice)
        self.robot_combo.currentIndexChanged.connect(self._on_robot_choice)
        self._on_robot_choice()

    @property
    def robot(self):
        """The camera robot the operator watches ("" when the fleet has none)."""
        return self.robot_combo.currentData() or ""

    def select_robot(self, robot):
        """Watch `robot`'s managed video (as if picked in the robot dropdown)."""
        index = self.robot_combo.findData(robot)
        if index < 0:
            raise ValueError(f"'{robot}' is not a camera robot of the fleet")
        self.robot_combo.setCurrentIndex(index)
        self._on_robot_choice()

    def _on_robot_choice(self, *_):
        robot = self.robot
        self.io.select_robot(robot)
        if robot:
            # Its managed JPEG video once advertised (the raw image where only that exists).
            self.prefer(names.absolute(names.robot_topic(robot, names.CAMERA_IMAGE)))

    @property
    def topic(self):
        return self.combo.currentText()

    def _on_choice(self, *_):
        """The operator picked a topic in the dropdown."""
        topic = self.combo.currentText()
        if topic:
            self._wanted_topic = topic
            self._picked = True
        self._subscribe(topic)

    def _subscribe(self, topic):
        self.io.select_image_topic(topic)
        self._shown_received_s = None

    def prefer(self, topic):
        """Show the camera `topic` (through its compressed variant when there is one) until the
        operator picks another in the dropdown."""
        self._wanted_topic, self._picked = topic, False
        self._refresh_topics()

    def _refresh_topics(self):
        topics = self.io.image_topics
        target = self._wanted_topic if self._picked else preferred_image_topic(topics, self._wanted_topic)
        if target and target not in topics:
            topics = sorted(topics + [target])
        current = [self.combo.itemText(i) for i in range(self.combo.count())]
        if topics != current or self.combo.currentText() != target:
            self.combo.blockSignals(True)
            if topics != current:
                self.combo.clear()
                self.combo.addItems(topics)
            index = self.combo.findText(target)
            self.combo.setCurrentIndex(index if index >= 0 else 0)
            self.combo.blockSignals(False)
            self._subscribe(self.combo.currentText())

    def refresh(self):
        self._refresh_topics()
        topic = self.topic
        if not topic:
            self.info.setText("no sensor_msgs/Image or CompressedImage topic advertised")
            return
        frame, rate_hz, mbytes, age_s = self.state.image(topic)
        if frame is None:
            self.info.setText(f"{topic}: waiting for the first frame")
            self.info.setStyleSheet("color: rgb(198,40,40)")
            return
        if frame.received_s != self._shown_received_s:
            self._shown_received_s = frame.received_s
            # Stamp (the render instant, wall clock) to now, when this frame is drawn.
            self._latency_ms = 1e3 * (time.time() - frame.stamp_s) if frame.stamp_s > 0 else math.nan
            try:
                self._pixmap = QPixmap.fromImage(rgb_to_qimage(frame_to_rgb(frame)))
            except ValueError as exc:
                self._pixmap = None
                self.picture.setText(str(exc))
        if self._pixmap is not None:
            self.picture.setPixmap(self._pixmap.scaled(self.picture.size(), Qt.KeepAspectRatio, Qt.FastTransformation))
        stale = self.state.is_stale(age_s)
        kind = frame.encoding if frame.transport == "raw" else frame.transport
        text = (
            f"{frame.width}x{frame.height} {kind} | {rate_hz:.1f} Hz | {mbytes:.2f} MB/s | age {age_s:.1f} s"
            f" | latency {self._latency_ms:.0f} ms"
        )
        robot = self.robot
        if robot and topic == names.absolute(names.robot_topic(robot, names.CAMERA_IMAGE_COMPRESSED)):
            status, status_age_s = self.state.video_status(robot)
            if status is not None:
                text += f" | level {status.level_name} at {status.set_rate_hz:g} Hz"
                stale = stale or self.state.is_stale(status_age_s)
            text = f"{robot}: {text}"
        self.info.setText(text)
        self.info.setStyleSheet("color: rgb(198,40,40); font-weight: bold" if stale else "")

    def save_settings(self, settings):
        settings.set_value("video/topic", self._wanted_topic if self._picked else self.topic)
        settings.set_value("video/robot", self.robot)

    def restore_settings(self, settings):
        robot = settings.value("video/robot", None)
        if robot and self.robot_combo.findData(str(robot)) >= 0:
            self.select_robot(str(robot))
        topic = settings.value("video/topic", None)
        if topic:
            self.prefer(str(topic))
