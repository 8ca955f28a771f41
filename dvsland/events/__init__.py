"""Event camera: the DVS pixel model (frames -> events), packed events and their representations.

Public names:
    Events: packed events (b, x, y int64; t int64 µs; p int8 ±1) sorted by (b, t), with count
        images (B, 2, H, W; channel 0 = ON, the opposite of tonic's ToFrame), voxel grids and
        tonic interop.
    EventEmulator: exact batched DVS emulator (reset(frames, t_us); step(frames, t_us) -> Events;
        the stage contract init_state / step_state / reset_where over EmulatorState, settings
        EmulatorParams).
    LEVEL_TOL: tolerance (in thresholds) when counting level crossings.
    TONIC_DTYPE: numpy dtype of tonic event arrays (x, y int16, t int64, p int8 OFF=0/ON=1).
    save_events, load_events: .npz / .h5 files, exact round trip (:mod:`dvsland.events.io`).
    read_recording, write_recording, Recording, GroundTruth, read_ground_truth, write_ground_truth:
        recordings of others and for others: AEDAT4, HDF5, tonic arrays, npz, CSV
        (:mod:`dvsland.events.recording`; ``GroundTruth`` in :mod:`dvsland.events.ground_truth`);
        bin_recording, binned_pixel: a recording seen through pixels F x F times larger.
    validate_events, check_event_arrays, check_events, EventDataError: the one check of events on
        the way in, for every reader and every estimator (:mod:`dvsland.events.validate`;
        ``validate_events``, which packs the checked columns into Events, in :mod:`dvsland.events.events`).
    PixelModelParams: the non-ideal pixel parts (:mod:`dvsland.events.pixel_model`).
"""

from .emulator import LEVEL_TOL, EmulatorParams, EmulatorState, EventEmulator
from .events import TONIC_DTYPE, Events, validate_events
from .ground_truth import GroundTruth
from .io import load_events, save_events
from .pixel_model import PixelModelParams
from .recording import (Recording, bin_recording, binned_pixel, read_ground_truth, read_recording,
                        write_ground_truth, write_recording)
from .validate import EventDataError, check_event_arrays, check_events
from .recording import RecordingError

__all__ = ["Events", "EventEmulator", "EmulatorParams", "EmulatorState", "LEVEL_TOL", "TONIC_DTYPE", "save_events", "load_events",
           "read_recording", "write_recording", "bin_recording", "binned_pixel", "Recording", "GroundTruth", "read_ground_truth",
           "write_ground_truth", "validate_events", "PixelModelParams", "EventDataError", "RecordingError", "check_event_arrays",
           "check_events"]
