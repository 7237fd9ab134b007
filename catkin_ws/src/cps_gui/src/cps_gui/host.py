"""The standalone host: runs FleetOperatorPlugin in a QMainWindow where rqt_gui is not installed,
with its settings persisted through QSettings (an ini file), and takes screenshots for `make demo`.
"""

import argparse
import json
import os
import sys

from python_qt_binding.QtCore import QObject, QSettings, QTimer
from python_qt_binding.QtGui import QGuiApplication
from python_qt_binding.QtWidgets import QApplication, QMainWindow

DEFAULT_SETTINGS_PATH = os.path.join(os.path.expanduser("~"), ".config", "cps_gui", "cps_gui.ini")
# Mesa's renderer for an unattended screenshot: softpipe, which compiles no shader. llvmpipe's shader
# JIT crashed inside libLLVM-15 while Ogre swapped rviz's buffers (SIGSEGV on a corrupted LLVM
# constant; Mesa 22.3.6, Debian 12; a core dump's stack): 1 of 50 launches beside two busy loops, 2 of
# 5 full test runs. softpipe cost about 15 % more CPU over the screenshot test. Set GALLIUM_DRIVER to choose.
SCREENSHOT_GALLIUM_DRIVER = "softpipe"


def choose_gl_driver(environ, screenshot):
    """For a screenshot, Mesa's SCREENSHOT_GALLIUM_DRIVER unless the caller chose one (in `environ`,
    before any GL context loads the driver); an operator's window keeps Mesa's own choice."""
    if screenshot:
        environ.setdefault("GALLIUM_DRIVER", SCREENSHOT_GALLIUM_DRIVER)


class QSettingsAdapter:
    """rqt's Settings API (`value`, `set_value`, `contains`) over one group of a QSettings."""

    def __init__(self, qsettings, group):
        self._settings, self._group = qsettings, group

    def _key(self, key):
        return f"{self._group}/{key}"

    def value(self, key, default_value=None):
        return self._settings.value(self._key(key), default_value)

    def set_value(self, key, value):
        self._settings.setValue(self._key(key), value)

    def contains(self, key):
        return self._settings.contains(self._key(key))


class HostContext(QObject):
    """The part of rqt's PluginContext the plugin uses: add_widget and serial_number."""

    def __init__(self, window):
        super().__init__(window)
        self._window = window

    def add_widget(self, widget):
        self._window.setCentralWidget(widget)
        self._window.setWindowTitle(widget.windowTitle())

    def serial_number(self):
        return 1


class OperatorWindow(QMainWindow):
    """The main window; the plugin's settings are restored on start and saved on close."""

    def __init__(self, settings_path=DEFAULT_SETTINGS_PATH, **plugin_args):
        super().__init__()
        from cps_gui.plugin import FleetOperatorPlugin

        self.settings_path = settings_path
        os.makedirs(os.path.dirname(os.path.abspath(settings_path)), exist_ok=True)
        self.qsettings = QSettings(settings_path, QSettings.IniFormat)
        self.resize(1600, 1000)
        self.context = HostContext(self)
        self.plugin = FleetOperatorPlugin(self.context, **plugin_args)
        geometry = self.qsettings.value("window/geometry", None)
        if geometry is not None:
            self.restoreGeometry(geometry)
        self.plugin.restore_settings(
            QSettingsAdapter(self.qsettings, "plugin"), QSettingsAdapter(self.qsettings, "instance")
        )
        self._closed = False
        self.closed_for_good = False

    def save(self):
        self.qsettings.setValue("window/geometry", self.saveGeometry())
        self.plugin.save_settings(
            QSettingsAdapter(self.qsettings, "plugin"), QSettingsAdapter(self.qsettings, "instance")
        )
        self.qsettings.sync()
        if self.qsettings.status() != QSettings.NoError:
            raise OSError(f"cannot write the settings file {self.settings_path}")

    def closeEvent(self, event):
        if not self._closed:
            self._closed = True
            self.save()
            self.plugin.shutdown_plugin()
        super().closeEvent(event)
        self.closed_for_good = True

    def screenshot(self, path):
        """Save the whole window as PNG and `<path>.panes.json` with each pane's rectangle in it.

        On a real X server the pixels come from the server (so rviz's OpenGL view is included);
        with the offscreen platform Qt renders the widgets itself.
        """
        QApplication.processEvents()
        if QGuiApplication.platformName() == "offscreen":
            pixmap = self.grab()
        else:
            pixmap = self.screen().grabWindow(self.winId())
        if pixmap.isNull() or not pixmap.save(path, "PNG"):
            raise OSError(f"cannot save the screenshot {path}")
        panes = {}
        for name, widget in self.plugin.panes.items():
            origin = widget.mapTo(self, widget.rect().topLeft())
            panes[name] = {"x": origin.x(), "y": origin.y(), "width": widget.width(), "height": widget.height()}
        with open(path + ".panes.json", "w") as stream:
            json.dump({"width": pixmap.width(), "height": pixmap.height(), "panes": panes}, stream, indent=1)


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="cps_gui", description="The fleet operator GUI (standalone host).")
    parser.add_argument(
        "--settings",
        default=DEFAULT_SETTINGS_PATH,
        help=f"ini file the window layout and choices persist in (default {DEFAULT_SETTINGS_PATH})",
    )
    parser.add_argument("--fleet-file", default=None, help="fleet.yaml (default: CPS_FLEET_FILE or cps_bringup's)")
    parser.add_argument(
        "--robots",
        default=None,
        help="comma-separated robots of this mission (default: the whole fleet); the GUI shows only these",
    )
    parser.add_argument("--no-rviz", action="store_true", help="leave the rviz 3D pane out (no OpenGL needed)")
    parser.add_argument(
        "--stale-after",
        type=float,
        default=2.0,
        metavar="S",
        help="age in seconds at which data is shown red (default 2.0)",
    )
    parser.add_argument("--screenshot", metavar="PATH", help="save a PNG of the whole window and exit")
    parser.add_argument(
        "--after", type=float, default=5.0, metavar="S", help="seconds to wait before the screenshot (default 5.0)"
    )
    parser.add_argument("--geometry", default="1600x1000", help="window size WxH (default 1600x1000)")
    args = parser.parse_args(argv)
    if args.stale_after <= 0:
        parser.error(f"--stale-after must be positive, got {args.stale_after}")
    if args.after < 0:
        parser.error(f"--after must be >= 0, got {args.after}")
    try:
        args.size = tuple(int(v) for v in args.geometry.lower().split("x"))
        if len(args.size) != 2 or min(args.size) <= 0:
            raise ValueError
    except ValueError:
        parser.error(f"--geometry must be WxH, got '{args.geometry}'")
    return args


def main(argv=None):
    import faulthandler
    import signal

    import rospy

    # `kill -USR1 <pid>` prints every thread's stack: the first thing to look at if the GUI hangs;
    # a crash prints them too.
    faulthandler.enable(all_threads=True)
    faulthandler.register(signal.SIGUSR1, all_threads=True)

    argv = rospy.myargv(sys.argv if argv is None else argv)
    args = parse_args(argv[1:])
    choose_gl_driver(os.environ, bool(args.screenshot))
    rospy.init_node("cps_gui", disable_signals=True)
    app = QApplication.instance() or QApplication(argv[:1])
    window = OperatorWindow(
        args.settings,
        fleet_file=args.fleet_file,
        with_rviz=not args.no_rviz,
        stale_after_s=args.stale_after,
        robots=args.robots.split(",") if args.robots else None,
    )
    if args.screenshot:
        window.resize(*args.size)
    window.show()
    exit_code = [0]

    def take_screenshot():
        try:
            window.screenshot(args.screenshot)
            rospy.loginfo(f"cps_gui: screenshot saved to {args.screenshot}")
        except OSError as exc:
            rospy.logerr(f"cps_gui: {exc}")
            exit_code[0] = 1
        window.close()

    if args.screenshot:
        QTimer.singleShot(int(args.after * 1000), take_screenshot)
    # Ctrl-C: Qt's loop does not return to Python by itself, so poll for rospy's shutdown.
    stop_requested = []
    signal.signal(signal.SIGINT, lambda *_: stop_requested.append(True))
    signal.signal(signal.SIGTERM, lambda *_: stop_requested.append(True))

    def watch():
        if (stop_requested or rospy.is_shutdown()) and not window.closed_for_good:
            window.close()
        if window.closed_for_good:
            app.quit()

    poll = QTimer()
    poll.timeout.connect(watch)
    poll.start(200)
    app.exec_()
    rospy.signal_shutdown("GUI closed")
    # Settings are saved and the plugin shut down by now. Skip the C++ static destructors of
    # rviz/Ogre and roscpp: tearing them down after Qt has gone can crash (seen: SIGBUS).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(exit_code[0])
