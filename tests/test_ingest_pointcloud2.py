"""PointCloud2 decoding against hand-packed bytes (struct), independent of the decoder's dtype logic."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from stages.ingest.pointcloud2 import Field, PointCloudError, decode, resolve_fields


def _decode(fields, data, n, point_step, big=False, height=1, row_step=None, columns=None):
    return decode(fields, data, point_step=point_step, row_step=row_step if row_step is not None else n * point_step,
                  width=n // height, height=height, is_bigendian=big,
                  columns=columns or {f.name: f.name for f in fields})


def test_coloradar_radar_layout_with_padding() -> None:
    # x y z, 4 padding bytes, intensity range doppler, 4 trailing bytes: point_step 32
    pts = [(1.0, 2.0, 3.0, 10.0, 3.7, -0.5), (-4.5, 0.25, 1e-3, 7.0, 4.6, 1.25)]
    data = b"".join(struct.pack("<3f4x3f4x", *p) for p in pts)
    fields = [Field("x", 0, 7), Field("y", 4, 7), Field("z", 8, 7), Field("intensity", 16, 7),
              Field("range", 20, 7), Field("doppler", 24, 7)]
    out = _decode(fields, data, 2, 32, columns={"x": "x", "y": "y", "z": "z", "intensity": "intensity",
                                                "doppler": "doppler"})
    assert set(out) == {"x", "y", "z", "intensity", "doppler"}
    np.testing.assert_array_equal(out["x"], np.float32([1.0, -4.5]))
    np.testing.assert_array_equal(out["doppler"], np.float32([-0.5, 1.25]))
    np.testing.assert_array_equal(out["intensity"], np.float32([10.0, 7.0]))
    assert out["x"].dtype == np.float32 and out["x"].flags.c_contiguous


def test_big_endian_odd_offsets_and_mixed_types() -> None:
    # uint8 flag @0, float64 x @1, float32 y @9, int16 z @13, uint16 intensity @15, float32 v @17; point_step 23
    pts = [(7, 1.5, -2.25, -300, 65000, 0.125), (1, -1e6, 3.5, 12, 3, -9.0)]
    data = b"".join(struct.pack(">BdfhHf2x", *p) for p in pts)
    fields = [Field("flag", 0, 2), Field("x", 1, 8), Field("y", 9, 7), Field("z", 13, 3), Field("intensity", 15, 4),
              Field("velocity", 17, 7)]
    out = _decode(fields, data, 2, 23, big=True,
                  columns={"x": "x", "y": "y", "z": "z", "intensity": "intensity", "doppler": "velocity"})
    np.testing.assert_array_equal(out["x"], np.float32([1.5, -1e6]))
    np.testing.assert_array_equal(out["y"], np.float32([-2.25, 3.5]))
    np.testing.assert_array_equal(out["z"], np.float32([-300, 12]))
    np.testing.assert_array_equal(out["intensity"], np.float32([65000, 3]))
    np.testing.assert_array_equal(out["doppler"], np.float32([0.125, -9.0]))
    little = b"".join(struct.pack("<BdfhHf2x", *p) for p in pts)
    out_le = _decode(fields, little, 2, 23, big=False, columns={"x": "x", "z": "z"})
    np.testing.assert_array_equal(out_le["z"], np.float32([-300, 12]))


def test_row_step_padding_with_two_rows() -> None:
    # an organised cloud (height 2, width 3) whose rows carry 5 padding bytes each
    rows = []
    for r in range(2):
        row = b"".join(struct.pack("<ff", 10 * r + c, -(10 * r + c)) for c in range(3)) + b"\xab" * 5
        rows.append(row)
    data = b"".join(rows)
    fields = [Field("x", 0, 7), Field("y", 4, 7)]
    out = _decode(fields, data, 6, 8, height=2, row_step=3 * 8 + 5)
    np.testing.assert_array_equal(out["x"], np.float32([0, 1, 2, 10, 11, 12]))
    np.testing.assert_array_equal(out["y"], -np.float32([0, 1, 2, 10, 11, 12]))
    # the last row may end without its padding
    out2 = _decode(fields, data[:-5], 6, 8, height=2, row_step=3 * 8 + 5)
    np.testing.assert_array_equal(out2["x"], out["x"])


def test_count_greater_than_one_keeps_first_element() -> None:
    data = b"".join(struct.pack("<3f", i, i + 0.5, i + 0.25) for i in range(3))
    out = _decode([Field("xyz", 0, 7, count=3)], data, 3, 12, columns={"x": "xyz"})
    np.testing.assert_array_equal(out["x"], np.float32([0, 1, 2]))


def test_errors_name_the_problem() -> None:
    fields = [Field("x", 0, 7), Field("y", 4, 7)]
    with pytest.raises(PointCloudError, match=r"missing field.*doppler.*has: x, y"):
        _decode(fields, bytes(16), 2, 8, columns={"x": "x", "doppler": "doppler"})
    with pytest.raises(PointCloudError, match="data holds 12 bytes, the layout needs 16"):
        _decode(fields, bytes(12), 2, 8)
    with pytest.raises(PointCloudError, match="does not fit in point_step 6"):
        _decode(fields, bytes(12), 2, 6)
    with pytest.raises(PointCloudError, match="unknown PointField datatype 42"):
        _decode([Field("x", 0, 42)], bytes(8), 2, 4)


def test_empty_cloud_and_field_resolution() -> None:
    out = _decode([Field("x", 0, 7)], b"", 0, 4)
    assert out["x"].shape == (0,)
    fields = [Field("x", 0, 7), Field("velocity", 4, 7), Field("snr", 8, 7)]
    mapping, missing = resolve_fields(fields, {"doppler": ["doppler", "velocity"], "intensity": ["intensity", "snr"],
                                               "z": ["z"]})
    assert mapping == {"doppler": "velocity", "intensity": "snr"} and missing == ["z"]
