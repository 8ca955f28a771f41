"""Fly the hard scenarios (:mod:`.scenarios`) for every estimator and score them per phase.

All scenarios form one batch (one element per scenario, each over its own configured site), flown
like the evaluation descents: :func:`.reference.fly_profile` on ``loop_step`` with the thrust that
tracks the scenario's altitude profile, every estimator in its own loop over the same frames and
events. The truth is the loop's ``v / z``.
"""

from __future__ import annotations

import copy
from typing import Dict, Optional, Sequence

import numpy as np
import torch

from dvsland.config import Config

from .metrics import divergence_metrics
from .scenarios import DustyFrames, NoisyEmulator, Scenario, resolve_scenarios, scenario_profiles


def _scenario_config(cfg: Config, scs: Sequence[Scenario], n_steps: int) -> Config:
    """One element per scenario over its site, no end but the profile's (success altitude 1 m)."""
    from .flight import flight_config

    sites = [s.site for s in scs]
    if len(set(sites)) != len(sites):
        raise ValueError(f"scenarios flown together need distinct sites, got {sites}")
    fc = flight_config(cfg, sites, n_steps)
    fc.simulation.success_altitude_m = 1.0
    return fc


def _wrap_stages(stages, scs: Sequence[Scenario], seed: int):
    """Put the scenarios' dust layers and noise bursts around the stages' renderer and emulator."""
    from dvsland.stages import EventSource

    B = len(scs)
    if not torch.equal(stages.scene_idx.cpu(), torch.arange(B)):
        raise ValueError("scenario batch: element i must be scene i")
    band = torch.tensor([s.poor_band_m if s.poor_band_m else (float("nan"),) * 2 for s in scs], dtype=torch.float64)
    k = torch.tensor([float(s.poor_contrast) for s in scs], dtype=torch.float32)
    win = torch.tensor([[round(a * 1e6), round(b * 1e6)] if s.noise_s else [0, 0]
                        for s in scs for a, b in [s.noise_s or (0.0, 0.0)]], dtype=torch.int64)
    rate = torch.tensor([float(s.noise_hz) for s in scs], dtype=torch.float64)
    ev = stages.events
    W, H = stages.cfg.camera.width_px, stages.cfg.camera.height_px
    stages.events = EventSource(DustyFrames(ev.renderer, band, k), NoisyEmulator(ev.emulator, win, rate, (W, H), seed))
    return stages


def score_phases(scs: Sequence[Scenario], t_s: np.ndarray, d_hat: np.ndarray, d_true: np.ndarray) -> dict:
    """{scenario: {phase: divergence_metrics}} over the steps with t in each phase's [from, to).

    Args:
        t_s: (N,) step times, s; d_hat, d_true: (S, N) estimates and truth, 1/s.
    """
    out = {}
    for i, sc in enumerate(scs):
        out[sc.name] = {}
        for label, a, b in sc.phases:
            m = (t_s >= a - 1e-9) & (t_s < b - 1e-9)
            out[sc.name][label] = divergence_metrics(d_hat[i][m], d_true[i][m])
    return out


def run_scenarios(cfg: Config, estimators: Dict[str, tuple], scenarios="all", *, device="cpu",
                  frame_source=None, progress: bool = False) -> dict:
    """Fly ``scenarios`` for every estimator.

    Args:
        cfg: the validated config (sites, camera, renderer, emulator, estimator sections, seed).
        estimators: {label: (name, overrides)} as :func:`.run.parse_estimator_spec` gives them.
        scenarios: names ("all", "none", "a,b") or :class:`Scenario` objects.
        device: torch device.
        frame_source: ``f(altitude_m, site_idx) -> (B, H, W)``; default the config's renderer.
        progress: tqdm bar.

    Returns:
        {"scenarios": {name: {"description", "site", "phases": {label: [from, to]}}},
         "t_s": (N,) list, "d_true": {name: list}, "d_hat": {label: {name: list}},
         "metrics": {label: {name: {phase: divergence_metrics}}}}; empty dict without scenarios.
    """
    from dvsland.layout import build_layout
    from dvsland.stages import build_estimator, build_stages

    from .reference import fly_profile
    from .flight import variant_config

    scs = resolve_scenarios(scenarios)
    if not scs:
        return {}
    device = torch.device(device)
    z_ref, v0, n = scenario_profiles(scs, float(cfg.dt_s))
    fcfg = _scenario_config(cfg, scs, n)
    layout = build_layout(fcfg, [s.site for s in scs])
    if frame_source is None:
        from dvsland.render import get_renderer

        frame_source = get_renderer(cfg.render.renderer, [s.site for s in scs], cfg.camera, cfg.render, device=device)
    f64 = dict(dtype=torch.float64, device=device)
    t_s = np.arange(n + 1) * float(cfg.dt_s)
    d_hat, d_true = {}, np.full((len(scs), n + 1), np.nan)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(estimators) * n, desc="scenarios", unit="step")
    for label, (name, over) in estimators.items():
        ecfg = copy.deepcopy(variant_config(fcfg, name, over, label))
        ecfg.estimator.name = name
        est = build_estimator(ecfg, len(scs), device, name=name)
        stages = build_stages(ecfg, layout, device, estimator=est, renderer=frame_source)
        if stages.events is not None:
            stages = _wrap_stages(stages, scs, int(cfg.simulation.seed))
        dh = np.full((len(scs), n + 1), np.nan)
        for k, out in enumerate(fly_profile(stages, torch.as_tensor(z_ref, **f64), torch.as_tensor(v0, **f64),
                                            keep_flying=True)):
            dh[:, k] = out.d_est.detach().cpu().numpy()
            d_true[:, k] = (out.v_mps / out.z_m).cpu().numpy()
            if bar is not None:
                bar.update(1)
        d_hat[label] = dh
    if bar is not None:
        bar.close()
    return dict(scenarios={s.name: dict(description=s.description, site=s.site,
                                        phases={p: [a, b] for p, a, b in s.phases}) for s in scs},
                t_s=t_s.tolist(), d_true={s.name: d_true[i].tolist() for i, s in enumerate(scs)},
                d_hat={lab: {s.name: dh[i].tolist() for i, s in enumerate(scs)} for lab, dh in d_hat.items()},
                metrics={lab: score_phases(scs, t_s, dh, d_true) for lab, dh in d_hat.items()})


def format_scenario_table(summary: dict) -> str:
    """Plain-text table of the hard scenarios: per estimator, scenario and phase, median |rel|,
    within 10 %, coverage and bias; "" without scenarios."""
    sc = summary.get("scenarios")
    if not sc:
        return ""

    def pct(x):
        return "-" if x is None or x != x else f"{100 * x:.1f}%"

    lines = ["Hard scenarios (dvsland.evaluate.scenarios): med|rel| over steps with an estimate, <10% over all steps",
             f"{'estimator':<12} {'scenario':<14} {'phase':<20} {'steps':>5} {'cover':>7} {'med|rel|':>9} "
             f"{'<10%':>7} {'bias':>8}"]
    for label, per in sc["metrics"].items():
        for name, phases in per.items():
            for phase, m in phases.items():
                lines.append(f"{label:<12} {name:<14} {phase:<20} {m['n_steps']:>5d} {pct(m['coverage']):>7} "
                             f"{pct(m['median_abs_rel_err']):>9} {pct(m['within_10']):>7} {pct(m['bias_rel']):>8}")
    lines.append("")
    lines += [f"  {n}: {d['description']} (site {d['site']})" for n, d in sc["scenarios"].items()]
    return "\n".join(lines)


def scenario_traces(scen: dict) -> dict:
    """The scenarios' traces as npz fields: scenario_t_s (N,), scenario_d_true_<name> (N,) and
    scenario_d_hat_<estimator>_<name> (N,), 1/s; {} without scenarios."""
    if not scen:
        return {}
    out = {"scenario_t_s": np.asarray(scen["t_s"])}
    out.update({f"scenario_d_true_{n}": np.asarray(v) for n, v in scen["d_true"].items()})
    out.update({f"scenario_d_hat_{lab}_{n}": np.asarray(v) for lab, per in scen["d_hat"].items()
                for n, v in per.items()})
    return out
