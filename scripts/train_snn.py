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

import torch


def main(argv=None) -> int:
    from dvsland.config import load_config
    from dvsland.estimators.snn import DEFAULT_CHECKPOINT, LogPolarEncoder, SpikingDivergenceNet, save_checkpoint
    from dvsland.estimators.snn.data import make_sequences, training_sites
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
    ap.add_argument("--warmup-steps", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--max-minutes", type=float, default=None, help="stop training after this long")
    ap.add_argument("--init", default=None, help="start from this checkpoint's weights (fine-tuning)")
    ap.add_argument("--out", default=str(DEFAULT_CHECKPOINT))
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    cfg = load_config(args.config)
    enc = LogPolarEncoder((cfg.camera.width_px, cfg.camera.height_px))
    sites = training_sites()
    t0 = time.perf_counter()
    data = make_sequences(cfg, enc, sites, args.n_seq, args.steps, seed=args.seed, c2_max=args.c2_max)
    t_data = time.perf_counter() - t0
    print(f"data: {args.n_seq} sequences x {args.steps} steps on {', '.join(sites)} in {t_data:.0f} s; "
          f"mean events/px/step {float(data['x'].float().mean()) * enc.n_sub:.3f}")
    model = SpikingDivergenceNet(enc.n_rho, enc.n_phi, dt_s=cfg.dt_s / enc.n_sub)
    prior = {}
    if args.init:
        ck = torch.load(args.init, map_location="cpu", weights_only=True)
        model.load_state_dict(ck["state_dict"])
        prior = ck.get("meta", {})
        print(f"starting from {args.init} ({prior.get('epochs_run', '?')} epochs)")
    hist = train(model, data, epochs=args.epochs, batch=args.batch, lr=args.lr, warmup_steps=args.warmup_steps,
                 seed=args.seed, max_minutes=args.max_minutes)
    meta = {"sites": sites, "n_seq": args.n_seq, "steps": args.steps, "c2_max": args.c2_max, "epochs_run": len(hist["epoch"]),
            "batch": args.batch, "lr": args.lr, "warmup_steps": args.warmup_steps, "seed": args.seed,
            "data_seconds": t_data, "train_seconds": hist["seconds"][-1] if hist["seconds"] else 0.0,
            "history": hist, "init": args.init, "prior": {k: v for k, v in prior.items() if k != "prior"}}
    save_checkpoint(args.out, model, enc, meta)
    print(f"wrote {args.out}")
    print(json.dumps({k: v for k, v in meta.items() if k != "history"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
