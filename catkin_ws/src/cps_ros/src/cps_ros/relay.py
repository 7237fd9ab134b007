"""Republishing rospy.AnyMsg without deserializing it, under the type its publisher declared."""

import rospy


def relay_class(connection_header):
    """A rospy.AnyMsg subclass that registers and serializes as the type in a connection header,
    so raw bytes go out on a publisher of the real type (rostopic, roscpp and typed subscribers work)."""
    return type(
        "Relay_" + connection_header["type"].replace("/", "_"),
        (rospy.AnyMsg,),
        {
            "_type": connection_header["type"],
            "_md5sum": connection_header["md5sum"],
            "_full_text": connection_header.get("message_definition", ""),
            "__slots__": (),
        },
    )


def relay_message(relay_cls, any_msg):
    out = relay_cls()
    out._buff = any_msg._buff
    return out
