"""sensor_msgs/PointCloud2 <-> numpy structured arrays, with validation.

A cloud is checked before it is read: data length = height x row_step, every field inside the
point with a known datatype, a non-empty name and a sane count, x/y/z present as one float each,
and at most MAX_CLOUD_BYTES of data. Anything else raises `InvalidCloud` with the reason, so a
node can drop the message, count it and carry on.
"""

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

# PointField datatype -> numpy type (little endian; byte order is applied per cloud).
POINTFIELD_DTYPES = {
    PointField.INT8: np.dtype("i1"),
    PointField.UINT8: np.dtype("u1"),
    PointField.INT16: np.dtype("i2"),
    PointField.UINT16: np.dtype("u2"),
    PointField.INT32: np.dtype("i4"),
    PointField.UINT32: np.dtype("u4"),
    PointField.FLOAT32: np.dtype("f4"),
    PointField.FLOAT64: np.dtype("f8"),
}
DTYPE_TO_POINTFIELD = {dt.str[1:]: code for code, dt in POINTFIELD_DTYPES.items()}


# Larger than any sensor's cloud (a 1875 x 16 lidar with 10 float64 fields is 2.4 MB), small
# enough that a hostile header cannot make a reader allocate gigabytes.
MAX_CLOUD_BYTES = 1 << 28
MAX_FIELD_COUNT = 1024


class InvalidCloud(ValueError):
    """A PointCloud2 (or its compressed form) that cannot be read as it claims to be."""


def field_dtype(datatype, count=1, bigendian=False):
    """numpy dtype of one PointField; InvalidCloud for an unknown datatype."""
    if datatype not in POINTFIELD_DTYPES:
        raise InvalidCloud(f"unknown PointField datatype {datatype}")
    base = POINTFIELD_DTYPES[datatype].newbyteorder(">" if bigendian else "<")
    return base if count == 1 else np.dtype((base, (count,)))


def cloud_dtype(fields, point_step, bigendian=False):
    """Structured dtype of one point (itemsize = point_step); checks every field fits."""
    names, formats, offsets = [], [], []
    for field in fields:
        if not isinstance(field.name, str) or not field.name:
            raise InvalidCloud(f"a field has no name ({field.name!r})")
        if not 1 <= field.count <= MAX_FIELD_COUNT:
            raise InvalidCloud(f"field '{field.name}' has count {field.count} (1..{MAX_FIELD_COUNT})")
        dtype = field_dtype(field.datatype, field.count, bigendian)
        if field.offset + dtype.itemsize > point_step:
            raise InvalidCloud(
                f"field '{field.name}' (offset {field.offset}, {dtype.itemsize} bytes) "
                f"does not fit in point_step {point_step}"
            )
        if field.name in names:
            raise InvalidCloud(f"field '{field.name}' appears twice")
        names.append(field.name)
        formats.append(dtype)
        offsets.append(field.offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def validate_cloud_layout(height, width, point_step, row_step, data_len, fields, require_xyz=True):
    """Raise InvalidCloud unless the layout numbers describe `data_len` bytes of readable points."""
    if height * width == 0:
        raise InvalidCloud(f"empty cloud ({height} x {width} points)")
    if data_len > MAX_CLOUD_BYTES:
        raise InvalidCloud(f"data of {data_len} bytes is over the limit of {MAX_CLOUD_BYTES}")
    if point_step == 0:
        raise InvalidCloud("point_step is 0")
    if row_step < width * point_step:
        raise InvalidCloud(f"row_step {row_step} < width {width} x point_step {point_step}")
    if data_len != height * row_step:
        raise InvalidCloud(f"data has {data_len} bytes, height {height} x row_step {row_step} = {height * row_step}")
    if require_xyz:
        names = {f.name for f in fields}
        missing = [axis for axis in "xyz" if axis not in names]
        if missing:
            raise InvalidCloud(f"no field {', '.join(missing)} (fields: {', '.join(sorted(names)) or 'none'})")
        for field in fields:
            if field.name in ("x", "y", "z") and field.datatype not in (PointField.FLOAT32, PointField.FLOAT64):
                raise InvalidCloud(f"field '{field.name}' must be FLOAT32 or FLOAT64, got datatype {field.datatype}")
            if field.name in ("x", "y", "z") and field.count != 1:
                raise InvalidCloud(f"field '{field.name}' must hold one value per point, got count {field.count}")


def cloud_to_array(msg: PointCloud2, require_xyz=True):
    """All points of a PointCloud2 as a flat structured array (row-major for organized clouds).

    The array views the message's bytes where the rows are unpadded (read-only then)."""
    validate_cloud_layout(msg.height, msg.width, msg.point_step, msg.row_step, len(msg.data), msg.fields, require_xyz)
    dtype = cloud_dtype(msg.fields, msg.point_step, msg.is_bigendian)
    data = msg.data if isinstance(msg.data, (bytes, bytearray)) else bytes(msg.data)
    if msg.row_step == msg.width * msg.point_step:
        return np.frombuffer(data, dtype=dtype, count=msg.height * msg.width)
    rows = np.frombuffer(data, dtype=np.uint8).reshape(msg.height, msg.row_step)[:, : msg.width * msg.point_step]
    return np.ascontiguousarray(rows).view(dtype).reshape(-1)


def xyz_of(points):
    """(N, 3) coordinates of a structured point array, in the fields' own float type."""
    names = points.dtype.names
    dtypes = {points.dtype.fields[a][0] for a in "xyz"}
    out_type = np.float64 if any(d.itemsize == 8 for d in dtypes) else np.float32
    out = np.empty((len(points), 3), dtype=out_type)
    for i, axis in enumerate("xyz"):
        if axis not in names:
            raise InvalidCloud(f"no field {axis}")
        out[:, i] = points[axis]
    return out


def finite_mask(xyz):
    """True for points whose three coordinates are finite (NaN marks 'no return' in ROS clouds)."""
    return np.isfinite(xyz).all(axis=1)


def packed_fields(names_and_dtypes):
    """PointFields for densely packed fields [(name, numpy dtype)], and the point_step."""
    fields, offset = [], 0
    for name, dtype in names_and_dtypes:
        dtype = np.dtype(dtype)
        key = dtype.str[1:]
        if key not in DTYPE_TO_POINTFIELD:
            raise InvalidCloud(f"field '{name}' has a type PointField cannot hold: {dtype}")
        fields.append(PointField(name=name, offset=offset, datatype=DTYPE_TO_POINTFIELD[key], count=1))
        offset += dtype.itemsize
    return fields, offset


def array_to_cloud(columns, header=None, height=1, width=None):
    """A little-endian PointCloud2 from ordered columns {name: 1-D array}, densely packed."""
    names = list(columns)
    n = len(columns[names[0]]) if names else 0
    fields, point_step = packed_fields([(name, np.asarray(columns[name]).dtype) for name in names])
    packed = np.empty(
        n,
        dtype=np.dtype(
            {
                "names": names,
                "formats": [np.asarray(columns[k]).dtype.newbyteorder("<") for k in names],
                "offsets": [f.offset for f in fields],
                "itemsize": point_step,
            }
        ),
    )
    for name in names:
        packed[name] = columns[name]
    msg = PointCloud2()
    if header is not None:
        msg.header = header
    msg.height = height
    msg.width = n // height if width is None else width
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = point_step
    msg.row_step = point_step * msg.width
    msg.is_dense = bool(all(np.isfinite(columns[a]).all() for a in "xyz" if a in columns))
    msg.data = packed.tobytes()
    return msg
