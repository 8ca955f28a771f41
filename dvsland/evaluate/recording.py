"""Open-loop evaluation on a recorded event stream (a file made by dvsland or by a real camera).

The recording is cut into intervals of the config's frame period (``1 / camera.frame_rate_hz``)
from its start; after each interval every estimator's ``update`` gets that interval's events, as
in :func:`dvsland.evaluate.evaluate`, and the estimate is scored against the ground truth
interpolated at the interval's end (where the recording has one). The result is an
:class:`~dvsland.evaluate.EvaluationResult` with the same metrics, table and files as a simulated
descent; the estimators are built for the recording's sensor size.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np
import torch

from dvsland.config import Config
from dvsland.estimators import Truth
from dvsland.events import Recording, binned_pixel, read_recording
from dvsland.report.checkpoint import estimator_checkpoint
from dvsland.stages import build_estimator

from .run import EvaluationResult, parse_estimator_spec, record_structure, summarise, time_base, variant_config
from .trajectory import Descents


@dataclass
class RecordingDescents(Descents):
    """:class:`Descents` of a recording: the true D is stored (it may be known without altitude).

    Attributes (besides those of :class:`Descents`): d_true (B, K + 1) float64, 1/s, NaN = unknown.
    """

    d_true: Optional[np.ndarray] = None

    @property
    def divergence(self) -> np.ndarray:
        return self.d_true


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


#: bytes per interval of :func:`evaluate_recording`'s arrays (int64 / float64): the interval ends,
#: the cuts, three ground-truth columns, the event counts, the times and two masks
STEP_BYTES = 8 * 8
#: bytes per interval and estimator: its estimate and its timing
STEP_BYTES_PER_ESTIMATOR = 16


def _sized_config(cfg: Config, recording: Recording) -> Config:
    """``cfg`` with the camera set to the recording's sensor (a custom sensor of its W x H px, the
    same field of view). A binned recording (:func:`~dvsland.events.bin_recording`) moves a given
    principal point (in the full sensor's pixels) and pixel pitch to its larger pixels."""
    W, H = recording.sensor_size
    f = int(recording.meta.get("bin_factor", 1))
    pitch = cfg.camera.pixel_pitch_um if cfg.camera.sensor == "custom" else None
    pp = cfg.camera.principal_point_px
    cam = dataclasses.replace(cfg.camera, sensor="custom", width_px=int(W), height_px=int(H),
                              pixel_pitch_um=None if pitch is None else pitch * f, focal_length_mm=None,
                              principal_point_px=None if pp is None else list(binned_pixel(pp, f)))
    return dataclasses.replace(cfg, camera=cam)


def dvs128_bin_factor(cfg: Config, sensor_size) -> int:
    """The binning that gives a recording's pixels about the angle of the DVS128 of the paper (60 deg
    over 128 px): round((60 / 128) / (camera.fov_deg / W)), at least 1."""
    W = int(sensor_size[0])
    return max(1, int(round((60.0 / 128.0) / (float(cfg.camera.fov_deg) / W))))


def _intervals(cfg: Config, recording: Recording, max_steps: Optional[int]) -> tuple:
    """``(t0, dt_us, K)``: the recording cut into K intervals of ``dt_us`` µs (the frame period)
    from ``t0`` µs (the ground truth's start if earlier, else just before the first event)."""
    dt_us = int(round(cfg.dt_s * 1e6))
    t_first, t_last = recording.t_range_us
    gt = recording.ground_truth
    t0 = int(gt.t_us[0]) if gt is not None and int(gt.t_us[0]) < t_first else t_first - 1
    K = int(np.ceil((t_last - t0) / dt_us))
    if max_steps is not None:
        K = min(K, int(max_steps))
    return t0, dt_us, K


def recording_memory_parts(cfg: Config, recording: Recording, estimators: Sequence[str],
                           max_steps: Optional[int] = None) -> dict:
    """Rough peak memory of :func:`evaluate_recording`, bytes, by part: ``intervals`` (the
    per-interval arrays: K x (STEP_BYTES + STEP_BYTES_PER_ESTIMATOR per estimator)) and
    ``estimators`` (each estimator's per-pixel state and cmax search on the recording's W x H
    sensor, :func:`dvsland.config.validate.memory_parts` for one descent). Allocates nothing."""
    from dvsland.config.validate import memory_parts

    cfg = _sized_config(cfg, recording)
    specs = [parse_estimator_spec(e) for e in estimators]
    K = _intervals(cfg, recording, max_steps)[2]
    per_est = 0.0
    for lab, est_name, over in specs:
        parts = memory_parts(variant_config(cfg, est_name, over, lab), n_sites=0, batch_size=1)
        per_est += parts["pixels"] + parts["cmax"]
    return {"intervals": float(K + 1) * (STEP_BYTES + STEP_BYTES_PER_ESTIMATOR * len(specs)),
            "estimators": per_est}


def _span_text(seconds: float) -> str:
    """A time span in s, days or years, whichever reads best."""
    if seconds < 86400:
        return f"{seconds:.4g} s"
    days = seconds / 86400
    return f"{days:.4g} days" if days < 365.25 else f"{days / 365.25:.4g} years"


def check_recording_size(cfg: Config, recording: Recording, estimators: Sequence[str],
                         max_steps: Optional[int] = None) -> None:
    """ValueError naming the file when the sizes a recording implies (its time span in intervals
    of ``1 / camera.frame_rate_hz``, its W x H sensor) need more memory than
    :func:`dvsland.config.validate.memory_limit_bytes` (``simulation.max_memory_gb``): events
    31 years apart, a time of 2^62 µs or a coordinate of 40000 px are refused before anything
    is allocated (the CLI runs it before the run folder is made)."""
    from dvsland.config.validate import memory_limit_bytes

    parts, limit = recording_memory_parts(cfg, recording, estimators, max_steps), memory_limit_bytes(cfg)
    need = sum(parts.values())
    if need <= limit:
        return
    (t_first, t_last), (W, H) = recording.t_range_us, recording.sensor_size
    _, dt_us, K = _intervals(cfg, recording, max_steps)
    gib = {k: f"{v / 2 ** 30:.3g} GiB" for k, v in parts.items()}
    origin = recording.meta.get("sensor_size_from") or "given"
    raise ValueError(
        f"{recording.source}: the recording implies about {need / 2 ** 30:.3g} GiB, above the limit of "
        f"{limit / 2 ** 30:.3g} GiB (simulation.max_memory_gb): {gib['intervals']} for {K} intervals of "
        f"{dt_us / 1e3:g} ms (1 / camera.frame_rate_hz; events from t = {t_first} to {t_last} us, "
        f"{_span_text((t_last - t_first) / 1e6)}) and {gib['estimators']} for "
        f"{len(estimators)} estimator(s) on a {W}x{H} px sensor ({origin}); check the time unit "
        f"(t_unit / --t-unit) and the coordinates, evaluate fewer intervals (max_steps / --max-steps) or "
        f"raise simulation.max_memory_gb")


def _run_intervals(ests: dict, ev_all, cut: np.ndarray, edges: np.ndarray, truth: dict, device,
                   progress: bool, label: str) -> tuple:
    """Feed each estimator of ``ests`` ({label: estimator}) interval k's events (``ev_all[cut[k-1]:cut[k]]``)
    at ``edges[k]`` µs with the ground truth ``truth`` ({"divergence", "altitude_m", "velocity_mps"}:
    (K + 1,) arrays, NaN = unknown). Returns ``(d_hat, conf, times, walls, n_events, structure)``:
    {label: (1, K + 1) estimates, 1/s}, {label: (1, K + 1) confidence in [0, 1] (0 where there is no
    estimate)}, {label: [ms per update in the time base, :func:`.run.time_base`]}, {label: [wall ms per
    update]}, (1, K + 1) event counts (-1 at k = 0), {label: (1, K + 1) ``structure`` diagnostic} of the
    estimators whose diagnostics give one (``cmax``)."""
    K = len(edges) - 1
    d_true = truth["divergence"]
    d_hat = {n: np.full((1, K + 1), np.nan) for n in ests}
    conf = {n: np.zeros((1, K + 1)) for n in ests}
    cpu_base = time_base(device) == "CPU"
    times: Dict[str, List[float]] = {n: [] for n in ests}
    walls: Dict[str, List[float]] = {n: [] for n in ests}
    n_events = np.full((1, K + 1), -1, dtype=np.int64)
    structure: Dict[str, np.ndarray] = {}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=K, desc=f"evaluate {label}", unit="step")
    for est in ests.values():
        est.reset()
    for k in range(1, K + 1):
        ev = ev_all[int(cut[k - 1]):int(cut[k])]
        n_events[0, k] = len(ev)
        if np.isfinite(d_true[k]):
            z = truth["altitude_m"][k] if np.isfinite(truth["altitude_m"][k]) else 1.0
            v = truth["velocity_mps"][k] if np.isfinite(truth["velocity_mps"][k]) else d_true[k] * z
            tr = Truth(torch.tensor([z], dtype=torch.float64, device=device),
                       torch.tensor([v], dtype=torch.float64, device=device))
        else:
            tr = None
        for n, est in ests.items():
            _sync(device)
            t_start, c_start = time.perf_counter(), time.process_time()
            d = est.update(ev, int(edges[k]), tr)
            _sync(device)
            wall_ms = (time.perf_counter() - t_start) * 1e3
            times[n].append((time.process_time() - c_start) * 1e3 if cpu_base else wall_ms)
            walls[n].append(wall_ms)
            d_hat[n][:, k] = d.detach().double().cpu().numpy()
            conf[n][:, k] = np.nan_to_num(est.confidence().detach().double().cpu().numpy(), nan=0.0)
            diag = est.diagnostics() if callable(getattr(est, "diagnostics", None)) else None
            record_structure(structure, n, diag if isinstance(diag, dict) else None, k, (1, K + 1))
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return d_hat, conf, times, walls, n_events, structure


def evaluate_recording(cfg: Config, recording: Union[Recording, str, Path],
                       estimators: Sequence[str] = ("dpr", "cmax"), *, warmup_steps: int = 10,
                       max_steps: Optional[int] = None, device="cpu", name: Optional[str] = None,
                       progress: bool = True, **read_kwargs) -> EvaluationResult:
    """Run ``estimators`` on a recording and score them against its ground truth.

    Args:
        cfg: config (frame rate, estimator parameters, seed); the camera size is the recording's.
        recording: a :class:`~dvsland.events.Recording` or a path for
            :func:`~dvsland.events.read_recording` (``read_kwargs`` go there: ``ground_truth``,
            ``t_unit``, ``format``, ...).
        estimators: names or ``"name[key=value;...]"`` specs, as in :func:`dvsland.evaluate.evaluate`.
        warmup_steps: intervals at the start left out of the metrics.
        max_steps: truncate to this many intervals.
        device: torch device of the estimators.
        name: label of the recording in the tables (default: the file stem).
        progress: tqdm progress bar.

    Returns:
        :class:`EvaluationResult` for one "site" (the recording); without ground truth the
        estimates are kept and every metric is NaN.

    Raises:
        RecordingError: (a ValueError, one line) the file is empty, truncated, corrupt, not
            UTF-8, or holds values dvsland cannot use (see :func:`~dvsland.events.read_recording`).
    """
    if not isinstance(recording, Recording):
        recording = read_recording(recording, **read_kwargs)
    if not estimators:
        raise ValueError("estimators must name at least one estimator")
    if int(warmup_steps) < 0:
        raise ValueError(f"warmup_steps must be >= 0, got {warmup_steps}")
    if len(recording.events) == 0:
        raise ValueError(f"{recording.source}: the recording has no events")
    check_recording_size(cfg, recording, estimators, max_steps)  # before anything is allocated
    device = torch.device(device)
    ev_all = recording.events.to(device)
    W, H = recording.sensor_size
    cfg = _sized_config(cfg, recording)
    t0, dt_us, K = _intervals(cfg, recording, max_steps)
    gt = recording.ground_truth
    edges = t0 + dt_us * np.arange(K + 1, dtype=np.int64)  # edges[k] = end of interval k
    t_np = ev_all.t.cpu().numpy()
    cut = np.searchsorted(t_np, edges, side="right")  # events in (edges[k-1], edges[k]]
    truth = gt.at(edges) if gt is not None else {k: np.full(K + 1, np.nan) for k in
                                                   ("divergence", "altitude_m", "velocity_mps")}
    d_true = truth["divergence"]
    valid = np.isfinite(d_true) & (d_true != 0)
    valid[0] = False
    label = name or (Path(recording.source).stem if recording.source != "array" else "recording")
    desc = RecordingDescents(sites=[label], t_s=edges / 1e6, altitude_m=truth["altitude_m"][None],
                             velocity_mps=truth["velocity_mps"][None], valid=valid[None], d_true=d_true[None])

    B = 1  # one recording
    ests, checkpoints = {}, {}
    for lab, est_name, over in (parse_estimator_spec(e) for e in estimators):
        if lab in ests:
            raise ValueError(f"estimator label {lab!r} given twice")
        # as in evaluate(): built once from its variant config, here sized for the recording
        vcfg = variant_config(cfg, est_name, over, lab)
        ests[lab] = build_estimator(vcfg, B, device, name=est_name)
        ck = estimator_checkpoint(vcfg, est_name, ests[lab])
        if ck is not None:
            checkpoints[lab] = ck
    d_hat, conf, times, walls, n_events, structure = _run_intervals(ests, ev_all, cut, edges, truth, device,
                                                                     progress, label)
    scored = desc.valid & (np.arange(K + 1)[None] > warmup_steps)
    res = EvaluationResult(desc, d_hat, scored, {n: np.asarray(v) for n, v in times.items()}, n_events,
                           wall_ms_per_step={n: np.asarray(v) for n, v in walls.items()},
                           time_base=time_base(device), checkpoints=checkpoints, confidence=conf,
                           structure=structure)
    info = dict(trajectory="recording", recording=recording.source, recording_format=recording.format,
                sensor_size=[int(W), int(H)], sensor_size_from=recording.meta.get("sensor_size_from"),
                bin_factor=int(recording.meta.get("bin_factor", 1)),
                has_ground_truth=gt is not None, n_steps=K, steps_run=K,
                warmup_steps=int(warmup_steps), device=str(device), torch_threads=torch.get_num_threads(),
                estimators_run=list(ests), n_events_total=len(ev_all))
    res.summary = summarise(res, info)
    return res


__all__ = ["evaluate_recording", "RecordingDescents", "check_recording_size", "recording_memory_parts"]
