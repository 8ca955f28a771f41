"""Event camera: the DVS pixel model (frames -> events), packed events and their representations.

Public names:
    Events: packed events (b, x, y, t [int64 µs], p [int8 ±1]) sorted by (b, t), with count
        images, voxel grids and tonic interop.
    TONIC_DTYPE: numpy dtype of tonic event arrays (x, y int16, t int64, p int8 OFF=0/ON=1).
"""

from .events import TONIC_DTYPE, Events

__all__ = ["Events", "TONIC_DTYPE"]
