"""The prepared points of benchmarks/real_gpu.py, packed for the trip to the GPU machine. A module of its own, with no
absl flags, so that tests import it beside the other benchmarks' flags."""

import zlib

import numpy as np

# The prepared points travel in 0.1 mm integers, compressed: a third smaller than float32, so that three sequences
# fit the 64 MiB a device call carries; the rounding (at most 0.05 mm) is far below the field's detail and the sensor's
# noise.
POINT_UNIT_M = 1e-4


def pack_points(points: np.ndarray) -> bytes:
    """points [N, 3] metres -> zlib-compressed int32 in POINT_UNIT_M, column by column."""
    return zlib.compress(np.round(np.asarray(points, np.float64).T / POINT_UNIT_M).astype(np.int32).tobytes(), 6)


def unpack_points(packed: bytes) -> np.ndarray:
    """pack_points' inverse: [N, 3] float64 metres."""
    return np.frombuffer(zlib.decompress(packed), np.int32).reshape(3, -1).T * POINT_UNIT_M
