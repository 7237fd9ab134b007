"""Hostile sensor_msgs/PointCloud2 and cps_msgs/CompressedPointCloud2 for fuzz tests (hypothesis
strategies): wrong field layouts, counts and sizes, truncated or padded data, NaN/Inf and absurd
coordinates. Every message is passed through rospy's serialization, so it holds only what could
arrive on the wire."""

import io

import numpy as np
from hypothesis import strategies as st
from sensor_msgs.msg import PointCloud2, PointField

# NaN/Inf, one point 10 km away, float32's largest values, a denormal, and ordinary coordinates.
HOSTILE_COORDINATES_M = (float("nan"), float("inf"), -float("inf"), 1e4, -1e4, 3.4e38, -3.4e38, 1e-42, 0.0, 1.5)
_POINTFIELD_TYPES = {
    np.dtype(np.float32): PointField.FLOAT32,
    np.dtype(np.float64): PointField.FLOAT64,
    np.dtype(np.uint32): PointField.UINT32,
}
FIELD_NAMES = ("x", "y", "z", "rgb", "intensity", "ring", "", "xy")
MUTATIONS = (
    "none",
    "truncate",
    "extend",
    "xyz_count",
    "bigendian",
    "point_step",
    "row_step",
    "offset",
    "datatype",
    "duplicate",
    "drop_z",
    "height",
)
_MAX_DATA_BYTES = 4096


def packed_cloud(columns, frame_id="jackal/camera_depth_optical_frame"):
    """A well-formed little-endian, unorganized PointCloud2 of ordered columns {name: 1-D array}."""
    names = list(columns)
    dtype = np.dtype([(name, columns[name].dtype.newbyteorder("<")) for name in names])
    points = np.empty(len(columns[names[0]]), dtype=dtype)
    for name in names:
        points[name] = columns[name]
    msg = PointCloud2(
        height=1,
        width=len(points),
        is_bigendian=False,
        point_step=dtype.itemsize,
        row_step=dtype.itemsize * len(points),
        is_dense=False,
        data=points.tobytes(),
    )
    msg.fields = [
        PointField(name=name, offset=dtype.fields[name][1], datatype=_POINTFIELD_TYPES[dtype[name]], count=1)
        for name in names
    ]
    msg.header.frame_id = frame_id
    return msg


def wire_copy(msg):
    """`msg` serialized and read back, as a subscriber receives it."""
    buffer = io.BytesIO()
    msg.serialize(buffer)
    out = type(msg)()
    out.deserialize(buffer.getvalue())
    return out


@st.composite
def random_layout_clouds(draw):
    """Any layout: 0..5 fields of any name, offset, datatype and count; height, width, steps and
    data length that may or may not agree; random bytes."""
    fields = [
        PointField(
            name=draw(st.sampled_from(FIELD_NAMES)),
            offset=draw(st.integers(0, 40)),
            datatype=draw(st.integers(0, 9)),
            count=draw(st.sampled_from((0, 1, 1, 1, 2, 3, 70000))),
        )
        for _ in range(draw(st.integers(0, 5)))
    ]
    height, width = draw(st.integers(0, 4)), draw(st.integers(0, 8))
    point_step = draw(st.integers(0, 48))
    row_step = draw(st.one_of(st.just(width * point_step), st.integers(0, 400), st.just(2**32 - 1)))
    data_len = draw(st.one_of(st.just(min(height * row_step, _MAX_DATA_BYTES)), st.integers(0, 400)))
    msg = packed_cloud({"x": np.zeros(1, np.float32)})
    msg.fields, msg.height, msg.width = fields, height, width
    msg.point_step, msg.row_step = point_step, row_step
    msg.is_bigendian = draw(st.booleans())
    msg.data = draw(st.binary(min_size=data_len, max_size=data_len))
    return wire_copy(msg)


@st.composite
def hostile_value_clouds(draw):
    """A well-formed x, y, z (+ extras) cloud holding hostile coordinates, then one mutation of
    its layout (`MUTATIONS`); returns (cloud, mutation)."""
    n = draw(st.integers(1, 40))
    xyz_type = draw(st.sampled_from((np.float32, np.float64)))
    xyz = np.asarray(draw(st.lists(st.floats(-8.0, 8.0), min_size=3 * n, max_size=3 * n)), dtype=np.float64)
    for i in draw(st.lists(st.integers(0, 3 * n - 1), max_size=6)):
        xyz[i] = draw(st.sampled_from(HOSTILE_COORDINATES_M))
    xyz = xyz.reshape(n, 3).astype(xyz_type)
    columns = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}
    if draw(st.booleans()):
        columns["intensity"] = np.full(n, draw(st.sampled_from(HOSTILE_COORDINATES_M)), dtype=np.float32)
    if draw(st.booleans()):
        columns["rgb"] = np.full(n, draw(st.integers(0, 2**32 - 1)), dtype=np.uint32)
    msg = packed_cloud(columns)
    mutation = draw(st.sampled_from(MUTATIONS))
    data = bytes(msg.data)
    fields = list(msg.fields)
    pick = draw(st.integers(0, len(fields) - 1))
    if mutation == "truncate":
        msg.data = data[: draw(st.integers(0, len(data) - 1))]
    elif mutation == "extend":
        msg.data = data + bytes(draw(st.integers(1, 64)))
    elif mutation == "xyz_count":
        fields[draw(st.integers(0, 2))].count = draw(st.integers(2, 4))
    elif mutation == "bigendian":
        msg.is_bigendian = not msg.is_bigendian
    elif mutation == "point_step":
        msg.point_step = draw(st.integers(0, msg.point_step + 16))
        msg.row_step = msg.point_step * msg.width
        msg.data = bytes(msg.row_step * msg.height) if msg.row_step * msg.height <= _MAX_DATA_BYTES else b""
    elif mutation == "row_step":
        msg.row_step = draw(st.integers(0, 2**32 - 1))
    elif mutation == "offset":
        fields[pick].offset = draw(st.integers(0, 2**32 - 1))
    elif mutation == "datatype":
        fields[pick].datatype = draw(st.integers(0, 255))
    elif mutation == "duplicate":
        fields.append(PointField(name=fields[pick].name, offset=0, datatype=7, count=1))
    elif mutation == "drop_z":
        fields = [f for f in fields if f.name != "z"]
    elif mutation == "height":
        msg.height = draw(st.integers(0, 2**32 - 1))
    msg.fields = fields
    return wire_copy(msg), mutation


def hostile_clouds():
    """Either kind of hostile PointCloud2 (random layout, or hostile values plus one mutation)."""
    return st.one_of(random_layout_clouds(), hostile_value_clouds().map(lambda pair: pair[0]))


def refused_clouds(frame_id="jackal/camera_depth_optical_frame"):
    """{what: PointCloud2} that every cloud reader must refuse: a handful for live-node tests."""
    xyz = np.array([[1.0, 0.5, 2.0], [1.5, -0.5, 2.5], [2.0, 0.0, 3.0]], dtype=np.float32)

    def cloud(**changes):
        msg = packed_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, frame_id)
        fields = changes.pop("fields", None)
        if fields:
            for index, values in fields.items():
                for key, value in values.items():
                    setattr(msg.fields[index], key, value)
        for key, value in changes.items():
            setattr(msg, key, value)
        return wire_copy(msg)

    full = bytes(cloud().data)
    return {
        "x of count 3": cloud(fields={0: {"count": 3}}),
        "truncated data": cloud(data=full[:-5]),
        "nameless field": cloud(fields={1: {"name": ""}}),
        "z outside the point": cloud(fields={2: {"offset": 4000}}),
        "unknown datatype": cloud(fields={0: {"datatype": 42}}),
        "row_step beyond the data": cloud(row_step=2**32 - 1),
        "height beyond the data": cloud(height=2**31),
        "all NaN": cloud(data=np.full(9, np.nan, np.float32).tobytes()),
    }
