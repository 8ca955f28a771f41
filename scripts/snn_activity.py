#!/usr/bin/env python
"""Spikes and synaptic operations of the 'snn' estimator per control step on the rendered sites.

    python scripts/snn_activity.py [--checkpoint PATH] [--steps 160] [--sites A,...,I] [--threads 1]

Flies the closed-form descent of the paper's law (perfect sensing: s = 1 + c2 v0 t / z0,
z = z0 s^(1/c2)) of each site of configs/paper.yaml (one element per site, the first
controller setting's initial conditions) on ``loop_step`` with the thrust that tracks it
(:func:`dvsland.evaluate.reference.fly_profile`), renders it with the fast renderer, runs the
estimator inside the loop, and prints the mean and median over elements and steps (after the warm-up) of
``diagnostics()['spikes']`` and ``['synops']``, beside the neurons of the network and the
multiply-accumulates of the same network run densely.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch


def main(argv=None) -> int:
    from dvsland.config import load_config
    from dvsland.dynamics import closed_form_state
    from dvsland.estimators.snn import SpikingEstimator
    from dvsland.evaluate.reference import fly_profile
    from dvsland.evaluate.run import flight_config
    from dvsland.layout import build_layout
    from dvsland.stages import build_stages

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", default="")
    ap.add_argument("--steps", type=int, default=160)
    ap.add_argument("--sites", default=None, help="comma-separated subset (default: all of the config)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    if args.steps < 1:
        raise SystemExit("--steps must be >= 1")
    torch.set_num_threads(args.threads)
    cfg = load_config()
    cfg.render.threads = args.threads
    sites = args.sites.split(",") if args.sites else [s.name for s in cfg.simulation.sites]
    fcfg = flight_config(cfg, sites, args.steps)  # one element per site, the first setting
    fcfg.render.renderer = "fast"
    lay = build_layout(fcfg, sites)
    b, c2, dt = lay.batch_size, cfg.controller.c2, cfg.dt_s
    est = SpikingEstimator(b, (cfg.camera.width_px, cfg.camera.height_px), dt_s=dt, checkpoint=args.checkpoint)
    stages = build_stages(fcfg, lay, "cpu", estimator=est)
    t = np.arange(args.steps + 3) * dt
    z = np.stack([closed_form_state(t, z0, v0, c2)[0] for z0, v0 in zip(lay.z0_m, lay.v0_mps)])
    spikes, synops = [], []
    # the closed-form descent on loop_step (tracking thrust); step k >= 1 updates the estimator
    for k, out in enumerate(fly_profile(stages, np.maximum(z, 1e-3), lay.v0_mps)):
        if k > est.warmup_steps:
            dg = out.diagnostics()
            spikes.append(dg["spikes"].numpy())
            synops.append(dg["synops"].numpy())
    sp, so = np.concatenate(spikes), np.concatenate(synops)
    m = est.model
    c1, c2n = m.channels
    n1, n2 = c1 * m.n_rho * m.n_phi, c2n * m.n_rho2 * m.n_phi
    n_sub = est.encoder.n_sub
    macs = n_sub * (n1 * 2 * 15 + n2 * c1 * 15 + c2n * m.n_rho2)
    print(f"checkpoint {args.checkpoint or 'shipped'}: {b} sites x {len(spikes)} steps, {n_sub} slices per step")
    print(f"neurons {n1 + n2} (layer 1 {n1}, layer 2 {n2}); dense multiply-accumulates per step {macs:.3g}")
    print(f"spikes per step: mean {sp.mean():.0f}, median {np.median(sp):.0f} "
          f"({100 * sp.mean() / ((n1 + n2) * n_sub):.1f} % of the neurons per slice)")
    print(f"synaptic operations per step: mean {so.mean():.3g}, median {np.median(so):.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
