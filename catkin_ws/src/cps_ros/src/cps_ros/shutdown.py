"""rospy.init_node whose SIGTERM/SIGINT shutdown runs in a thread, not inside the signal handler.

rospy's own handler runs the whole shutdown (its log line, the shutdown hooks, closing every
connection) inside the handler on the main thread. A second signal that lands while the first is
logging re-enters it with logging's lock held: the connection threads wait for that lock, the
re-entered shutdown waits for their topic lock, and the node never exits. Second signals are the
rule, not the exception: the kernel sends a parent-death signal once per exiting thread of a killed
multi-threaded supervisor. Here the handler only sets an event; a watcher thread runs rospy's
shutdown, hooks included, and the interpreter waits for it before it exits.
"""

import signal
import threading

SHUTDOWN_SIGNALS = (signal.SIGTERM, signal.SIGINT)
# How often the watcher looks whether the main thread has ended without a signal.
WATCH_PERIOD_S = 0.2


def init_node(name, **kwargs):
    """rospy.init_node(name, **kwargs) with the shutdown signals handled by `handle_shutdown_signals`."""
    import rospy

    rospy.init_node(name, disable_signals=True, **kwargs)
    handle_shutdown_signals()


def handle_shutdown_signals(signals=SHUTDOWN_SIGNALS):
    """Route `signals` to rospy.signal_shutdown on a watcher thread; returns that thread."""
    import rospy

    received = []
    wanted = threading.Event()

    def on_signal(signum, _frame):
        received.append(signum)
        wanted.set()

    def watch():
        main = threading.main_thread()
        # Not a daemon, so that hooks such as a map's last save finish before the interpreter exits;
        # it ends by itself once the node's main thread has ended without a signal.
        while main.is_alive() and not rospy.is_shutdown():
            if wanted.wait(WATCH_PERIOD_S):
                rospy.signal_shutdown(f"signal-{received[0]}")
                return

    watcher = threading.Thread(target=watch, name="signal_shutdown")
    watcher.start()
    for signum in signals:
        signal.signal(signum, on_signal)
    return watcher
