#!/usr/bin/env python
"""Train the spiking divergence estimator ('snn') and write its checkpoint.

    python scripts/train_snn.py [--n-seq 1280] [--steps 20] [--epochs 14] [--init CKPT] [--out PATH]

Data: constant-divergence descents on held-out terrain (site variants A~1 ... I~2, never the nine
evaluation sites), rendered by the fast renderer and turned into events by the configured emulator
(configs/paper.yaml). The checkpoint (default: the shipped dvsland/estimators/snn/snn_default.pt)
holds the weights, the encoder and model settings, the training settings and the history. Evaluate
it on the nine sites with ``dvsland evaluate --estimators snn,dpr``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch


def main(argv=None) -> int:
    from dvsland.config import load_config
    from dvsland.estimators.snn import DEFAULT_CHECKPOINT, LogPolarEncoder, SpikingDivergenceNet, save_checkpoint
    from dvsland.estimators.snn.data import SITE_TYPES, make_sequences, training_sites
    from dvsland.estimators.snn.train import train

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=None, help="config YAML (default configs/paper.yaml)")
    ap.add_argument("--n-seq", type=int, default=1280)
    ap.add_argument("--steps", type=int, default=20, help="control steps per sequence")
    ap.add_argument("--c2-max", type=float, default=0.0,
                    help="descents follow tau = tau0 - c2 t with c2 in [0, C2_MAX] (0 = constant D)")
    ap.add_argument("--epochs", type=int, default=14)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--crop-steps", type=int, default=None,
                    help="train on random windows of this many steps (validation on whole sequences)")
    ap.add_argument("--warmup-steps", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-seed", type=int, default=None,
                    help="seed of the weights and the batch order (default --seed; the data keep --seed)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--max-minutes", type=float, default=None, help="stop training after this long")
    ap.add_argument("--dispersion", default=None,
                    help="draw each sequence's sun elevation and sensor (threshold scale, mismatch, background "
                         "rate, refractory) from this config's dispersion section, e.g. configs/montecarlo.yaml")
    ap.add_argument("--sun-step", type=float, default=None,
                    help="round dispersed sun elevations to this step, deg (default: the config's sun_step_deg)")
    ap.add_argument("--hold-out-type", default=None, choices=sorted(SITE_TYPES),
                    help="leave every site of this type out of the training terrains")
    ap.add_argument("--channels", default="16,32", help="LIF channels of the two layers (new networks only)")
    ap.add_argument("--n-sub", type=int, default=4, help="network steps (time slices) per control step")
    ap.add_argument("--data-cache", default=None,
                    help="torch file of the generated sequences: loaded when it exists, else written")
    ap.add_argument("--init", default=None, help="start from this checkpoint's weights (fine-tuning)")
    ap.add_argument("--out", default=str(DEFAULT_CHECKPOINT))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    train_seed = args.seed if args.train_seed is None else args.train_seed
    torch.manual_seed(train_seed)
    cfg = load_config(args.config)
    cfg.render.threads = args.threads  # the fast renderer's sampling threads too
    prior = {}
    ck = None
    if args.init:
        ck = torch.load(args.init, map_location="cpu", weights_only=True)
        prior = ck.get("meta", {})
    n_sub = int(ck["encoder"]["n_sub"]) if ck else args.n_sub
    channels = tuple(ck["model"]["channels"]) if ck else tuple(int(c) for c in args.channels.split(","))
    enc = LogPolarEncoder((cfg.camera.width_px, cfg.camera.height_px), n_sub=n_sub)
    sites = training_sites(hold_out_type=args.hold_out_type)
    dispersion = load_config(args.dispersion).dispersion if args.dispersion else None
    t0 = time.perf_counter()
    key = {"n_seq": args.n_seq, "steps": args.steps, "seed": args.seed, "c2_max": args.c2_max, "sites": sites,
           "dispersion": args.dispersion, "sun_step": args.sun_step, "n_sub": n_sub}
    data = None
    if args.data_cache and Path(args.data_cache).is_file():
        cached = torch.load(args.data_cache, map_location="cpu", weights_only=False)
        if cached.get("key") == key:
            data = cached["data"]
            print(f"data: loaded {args.data_cache}")
        else:
            print(f"data: {args.data_cache} was made with other settings; regenerating")
    if data is None:
        data = make_sequences(cfg, enc, sites, args.n_seq, args.steps, seed=args.seed, c2_max=args.c2_max,
                              dispersion=dispersion, sun_step_deg=args.sun_step)
        if args.data_cache:
            torch.save({"key": key, "data": data}, args.data_cache)
    t_data = time.perf_counter() - t0
    print(f"data: {args.n_seq} sequences x {args.steps} steps on {', '.join(sites)} in {t_data:.0f} s; "
          f"mean events/px/step {float(data['x'].float().mean()) * enc.n_sub:.3f}")
    model = SpikingDivergenceNet(enc.n_rho, enc.n_phi, dt_s=cfg.dt_s / enc.n_sub, channels=channels)
    if ck:
        model.load_state_dict(ck["state_dict"])
        print(f"starting from {args.init} ({prior.get('epochs_run', '?')} epochs)")
    hist = train(model, data, epochs=args.epochs, batch=args.batch, lr=args.lr, warmup_steps=args.warmup_steps,
                 seed=train_seed, max_minutes=args.max_minutes,
                 crop_steps=args.crop_steps)
    meta = {"sites": sites, "hold_out_type": args.hold_out_type, "dispersion": args.dispersion,
            "sun_step": args.sun_step, "n_seq": args.n_seq, "steps": args.steps, "crop_steps": args.crop_steps, "c2_max": args.c2_max, "epochs_run": len(hist["epoch"]),
            "batch": args.batch, "lr": args.lr, "warmup_steps": args.warmup_steps, "seed": args.seed, "train_seed": train_seed,
            "data_seconds": t_data, "train_seconds": hist["seconds"][-1] if hist["seconds"] else 0.0,
            "history": hist, "init": args.init, "prior": {k: v for k, v in prior.items() if k != "prior"}}
    save_checkpoint(args.out, model, enc, meta)
    print(f"wrote {args.out}")
    print(json.dumps({k: v for k, v in meta.items() if k != "history"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
