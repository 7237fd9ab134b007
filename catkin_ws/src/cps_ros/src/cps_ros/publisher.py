"""A rospy Publisher that one bad message cannot poison.

rospy serializes each message into its topic's one buffer and clears that buffer only after a
successful send (rospy/topics.py, _PublisherImpl.publish). A field out of its type's range (a
negative uint32) raises mid-serialization and leaves the partial bytes in the buffer; every later
message of the topic goes out behind them, and every subscriber reads garbage from then on. The
map server's statistics went silent for the rest of a mission that way (a queue length of -1 read
between two counters). This Publisher clears the buffer when a message fails, under the topic's
lock, and raises as rospy does: the message is lost, the topic is not."""

import rospy


class Publisher(rospy.Publisher):
    """rospy.Publisher; a message that fails to serialize raises ROSSerializationException, as
    rospy's does, and leaves the topic as it was (its buffer empty, its latched message kept)."""

    def publish(self, *args, **kwds):
        impl = self.impl
        if impl is None:
            return super().publish(*args, **kwds)
        impl.acquire()  # a reentrant lock: rospy's publish takes it again
        try:
            latched = impl.latch
            try:
                return super().publish(*args, **kwds)
            except rospy.ROSSerializationException:
                if impl.buff is not None:
                    impl.buff.seek(0)
                    impl.buff.truncate(0)
                impl.latch = latched  # a late subscriber gets the last good message, not the bad one
                raise
        finally:
            impl.release()
