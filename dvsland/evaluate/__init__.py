"""Open-loop evaluation of divergence estimators.

Public names: :func:`evaluate` (run estimators on the evaluation streams), :class:`EvaluationResult`,
:func:`closed_form_descents`, :func:`segment_schedule`, :func:`divergence_metrics`,
:func:`band_metrics`, :data:`BANDS`, :func:`format_table`, :func:`write_outputs`, and synthetic
test streams :func:`zoom_blob_events`, :func:`blob_layout`, :class:`ZoomTextureFrames`, and
:func:`evaluate_recording` (the same evaluation on a recorded event stream); :func:`fly_profile` and
:func:`tracking_thrust` fly a prescribed altitude profile on :func:`dvsland.sim.loop_step`.
"""

from .metrics import BANDS, band_metrics, divergence_metrics
from .report import format_table, write_outputs
from .run import TARGET_SITES, EvaluationResult, evaluate, summarise
from .recording import RecordingDescents, evaluate_recording
from .reference import fly_profile, tracking_thrust
from .synthetic import ZoomTextureFrames, blob_layout, zoom_blob_events
from .trajectory import Descents, closed_form_descents, segment_schedule

__all__ = ["evaluate", "EvaluationResult", "summarise", "TARGET_SITES", "closed_form_descents", "Descents",
           "segment_schedule", "divergence_metrics", "band_metrics", "BANDS", "format_table", "write_outputs",
           "zoom_blob_events", "blob_layout", "ZoomTextureFrames", "evaluate_recording", "RecordingDescents",
           "fly_profile", "tracking_thrust"]
