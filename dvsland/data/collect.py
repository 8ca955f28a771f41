"""Fly a group of descents on :func:`dvsland.sim.loop_step` and cut every step into samples.

One sample = one active descent at one control step: the events of its window
``(t0_us, t_us]`` (the step's events: the emulator's output since the previous step) and the
true state at ``t_us``. Finished descents give no more samples. The build
(:mod:`dvsland.data.build`) and the stream (:mod:`dvsland.data.stream`) both read
:class:`Flight`, so they see the same samples in the same order (step-major, then the
batch element order of :class:`dvsland.layout.BatchLayout`).
"""

from __future__ import annotations

from typing import Dict, Iterator, NamedTuple

import numpy as np
from dvsland.config import Config

from .shardfile import DESCENT_FIELDS, SAMPLE_FIELDS

#: the estimator the build flies by default: the truth (no estimator cost; see docs/learning.md)
DEFAULT_ESTIMATOR = "oracle"


class StepSamples(NamedTuple):
    """The samples of one control step (n = active descents).

    Attributes:
        events: {x uint16, y uint16, dt_us int32, p int8} (sum(counts),), grouped by sample.
        counts: (n,) int64 events per sample.
        samples: {field: (n,)} of :data:`dvsland.data.shardfile.SAMPLE_FIELDS`.
    """

    events: Dict[str, np.ndarray]
    counts: np.ndarray
    samples: Dict[str, np.ndarray]


def build_loop_stages(cfg: Config, device="cpu"):
    """The loop's stages for ``cfg`` with events always on: an estimator that needs none (the
    oracle) gets them anyway, so every step is rendered and emulated."""
    from dvsland.layout import build_layout
    from dvsland.stages import build_estimator, build_stages, check_names

    check_names(cfg)
    layout = build_layout(cfg)
    est = build_estimator(cfg, layout.batch_size, device, seed=layout.noise_seed)
    # the camera records for the data set even when the estimator (oracle) needs no events
    return build_stages(cfg, layout, device, estimator=est, record_events=True)


def recording_stages(cfg: Config, device="cpu"):
    """(stages, crop): :func:`build_loop_stages` of ``cfg`` with the camera that records it and the
    :class:`~dvsland.data.crop.Crop` of its events (None for a centred principal point; an
    off-centre one renders a larger centred sensor, see :mod:`dvsland.data.crop`)."""
    import copy

    from .crop import recording_camera

    cam, crop = recording_camera(cfg.camera)
    if crop is not None:
        cfg = copy.deepcopy(cfg)
        cfg.camera = cam
    return build_loop_stages(cfg, device), crop


class Flight:
    """Flies ``stages`` to the end (every descent finished or ``t_max_s``); iterating yields each
    step's :class:`StepSamples`, and ``state`` is the :class:`dvsland.sim.LoopState` reached so far.

    Args:
        stages: from :func:`build_loop_stages`.
        state: start state (default :func:`dvsland.sim.init_state`).
        crop: keep only the events of this window, in its own pixel coordinates (from
            :func:`recording_stages`; None = every event).
    """

    def __init__(self, stages, state=None, crop=None):
        from dvsland.sim import init_state

        self.stages, self.crop = stages, crop
        self.state = init_state(stages) if state is None else state

    def __iter__(self) -> Iterator[StepSamples]:
        from dvsland.sim import loop_step

        n_max = self.stages.settings.n_steps_max
        dt_s = self.stages.settings.dt_s
        while not self.state.done and self.state.step < n_max:
            self.state, out = loop_step(self.stages, self.state)
            yield step_samples(out, dt_s, self.crop)


def step_samples(out, dt_s: float, crop=None) -> StepSamples:
    """Cut one :class:`dvsland.sim.StepOutput` into the samples of its active descents; the
    window starts at the previous step's time, rounded to the µs as the loop rounds it. ``crop``
    (a :class:`~dvsland.data.crop.Crop`): keep only its window's events, shifted to its pixels."""
    act = out.active.cpu().numpy()
    idx = np.flatnonzero(act)
    t0_us = int(round(max(out.step - 1, 0) * dt_s * 1e6))
    if out.events is None or len(out.events) == 0:
        counts = np.zeros(len(idx), np.int64)
        events = {k: np.zeros(0, dt) for k, dt in (("x", np.uint16), ("y", np.uint16), ("dt_us", np.int32),
                                                   ("p", np.int8))}
    else:
        ev = out.events.to("cpu")
        b, x, y = ev.b.numpy(), ev.x.numpy(), ev.y.numpy()
        keep = act[b]
        if crop is not None:
            x, y = x - crop.x0, y - crop.y0
            keep &= (x >= 0) & (x < crop.width) & (y >= 0) & (y < crop.height)
        counts = np.bincount(b[keep], minlength=len(act))[idx].astype(np.int64)
        events = {"x": x[keep].astype(np.uint16), "y": y[keep].astype(np.uint16),
                  "dt_us": (ev.t.numpy()[keep] - t0_us).astype(np.int32), "p": ev.p.numpy()[keep].astype(np.int8)}
    return StepSamples(events, counts, _targets(out, idx, t0_us))


def _targets(out, idx: np.ndarray, t0_us: int) -> Dict[str, np.ndarray]:
    z = out.z_m.cpu().numpy()[idx]
    v = out.v_mps.cpu().numpy()[idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        tau = np.where(v < 0, z / np.where(v < 0, -v, 1.0), np.inf)
    n = len(idx)
    s = {"descent": idx.astype(np.int32), "step": np.full(n, out.step, np.int32),
         "t0_us": np.full(n, t0_us, np.int64), "t_us": np.full(n, out.t_us, np.int64),
         "t_s": np.full(n, out.t_s, np.float64), "d_true": out.d_true.cpu().numpy()[idx], "tau_s": tau,
         "z_m": z, "v_mps": v, "d_est": out.d_est.cpu().numpy()[idx], "thrust_n": out.thrust_n.cpu().numpy()[idx],
         "valid": (out.step > 0) & np.isfinite(tau)}
    return {k: np.asarray(s[k], dtype=SAMPLE_FIELDS[k][0]) for k in SAMPLE_FIELDS}


def descent_table(layout, final_state=None) -> Dict[str, np.ndarray]:
    """One row per batch element of ``layout``: {field: (B,)} of :data:`DESCENT_FIELDS`
    (dispersed values NaN where not dispersed; outcome ``""`` without a final state)."""
    from dvsland.sim import OUTCOMES

    B = layout.batch_size
    d = layout.dispersed
    nan = np.full(B, np.nan)
    out = {"site": list(layout.site), "scene": list(layout.scene), "setting": list(layout.label),
           "variant": d.get("terrain_variant", np.zeros(B, np.int64)), "seed": layout.seed,
           "seed_index": layout.seed_idx, "z0_m": layout.z0_m, "v0_mps": layout.v0_mps}
    for k in ("sun_elevation_deg", "threshold_scale", "mismatch_sigma", "background_rate_hz", "refractory_us"):
        out[k] = np.asarray(d[k], np.float64) if k in d else nan
    codes = final_state.outcome.cpu().numpy() if final_state is not None else None
    out["outcome"] = [OUTCOMES[int(c)] for c in codes] if codes is not None else [""] * B
    return {k: (np.asarray(v, dtype=object) if DESCENT_FIELDS[k] is str else np.asarray(v, DESCENT_FIELDS[k]))
            for k, v in out.items()}
