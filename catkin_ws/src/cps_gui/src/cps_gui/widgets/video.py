"""Pane 1, video: every sensor_msgs/Image and sensor_msgs/CompressedImage topic in a dropdown
(found by type, refreshed), the picture scaled to the pane, and its frame rate, bandwidth and age
underneath (red when stale). Only the topic on screen is subscribed; a frame is converted when it
is new and drawn. Until the operator picks a topic, a camera is shown through its JPEG variant
(`<topic>/compressed`) when one is advertised: the raw stream would not fit the link's reserve.
"""

import math

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
        self.combo = QComboBox()
        self.combo.setSizeAdjustPolicy(QComboBox.AdjustToMinimumContentsLengthWithIcon)
        self.picture = QLabel("no image topic yet")
        self.picture.setAlignment(Qt.AlignCenter)
        self.picture.setSizePolicy(QSizePolicy.Ignored, QSizePolicy.Ignored)
        self.picture.setMinimumSize(160, 120)
        self.picture.setStyleSheet("background: #202020; color: #dddddd")
        self.info = QLabel("")
        top = QHBoxLayout()
        top.addWidget(QLabel("Camera"))
        top.addWidget(self.combo, 1)
        layout = QVBoxLayout(self)
        layout.addLayout(top)
        layout.addWidget(self.picture, 1)
        layout.addWidget(self.info)
        self._wanted_topic = ""
        self._picked = False  # the operator chose the topic in the dropdown: keep it, raw or not
        self._shown_received_s = None
        self._pixmap = None
        self.combo.currentIndexChanged.connect(self._on_choice)

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
            try:
                self._pixmap = QPixmap.fromImage(rgb_to_qimage(frame_to_rgb(frame)))
            except ValueError as exc:
                self._pixmap = None
                self.picture.setText(str(exc))
        if self._pixmap is not None:
            self.picture.setPixmap(self._pixmap.scaled(self.picture.size(), Qt.KeepAspectRatio, Qt.FastTransformation))
        stale = self.state.is_stale(age_s)
        kind = frame.encoding if frame.transport == "raw" else frame.transport
        self.info.setText(
            f"{frame.width}x{frame.height} {kind} | {rate_hz:.1f} Hz | {mbytes:.2f} MB/s | age {age_s:.1f} s"
        )
        self.info.setStyleSheet("color: rgb(198,40,40); font-weight: bold" if stale else "")

    def save_settings(self, settings):
        settings.set_value("video/topic", self._wanted_topic if self._picked else self.topic)

    def restore_settings(self, settings):
        topic = settings.value("video/topic", None)
        if topic:
            self.prefer(str(topic))
