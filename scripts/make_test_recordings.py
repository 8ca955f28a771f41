"""Make the tiny recordings under tests/data/ (one per format) with dvsland itself.

Site A along its closed-form oracle descent (the evaluation trajectory), a 64 x 48 sensor at
10 Hz, 40 frame intervals from about 1 km, the ideal emulator (threshold 0.1, refractory 15 µs);
written as descent_A.{h5,npz,npy,csv,aedat4} plus the ground truth (altitude and vertical
velocity per frame) embedded in h5/npz and as descent_A_gt.csv beside the others.

    python scripts/make_test_recordings.py [--out tests/data]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="tests/data")
    ap.add_argument("--steps", type=int, default=40)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from dvsland.config import load_config
    from dvsland.evaluate import closed_form_descents
    from dvsland.events import Events, GroundTruth, write_ground_truth, write_recording
    from dvsland.stages import build_event_source

    cfg = load_config("paper", ["camera.width_px=64", "camera.height_px=48"])
    desc = closed_form_descents(cfg, ["A"])
    k0 = int(np.argmax(desc.altitude_m[0] <= 1000.0))
    ks = list(range(k0, k0 + args.steps + 1))
    alt = torch.as_tensor(desc.altitude_m[0, ks], dtype=torch.float32)
    t_us = np.round(desc.t_s[ks] * 1e6).astype(np.int64)
    src = build_event_source(cfg, ["A"], "cpu", renderer="fast", seed=0)
    idx = torch.zeros(1, dtype=torch.long)
    src.reset(alt[:1], idx, int(t_us[0]))
    evs = [src.step(alt[i:i + 1], idx, int(t_us[i]))[1] for i in range(1, len(ks))]
    ev = Events.cat(evs)
    gt = GroundTruth.from_altitude(t_us, desc.altitude_m[0, ks], desc.velocity_mps[0, ks])
    out = Path(args.out)
    W, H = cfg.camera.width_px, cfg.camera.height_px
    for suffix, pol in (("h5", "01"), ("npz", "pm1"), ("npy", "01"), ("csv", "pm1"), ("aedat4", "01")):
        p = write_recording(out / f"descent_A.{suffix}", ev, (W, H), ground_truth=gt, polarity=pol)
        print(f"{p}: {len(ev)} events, {p.stat().st_size / 1024:.1f} KiB")
    write_ground_truth(out / "descent_A_gt.csv", gt)
    print(f"altitude {desc.altitude_m[0, ks[0]]:.1f} -> {desc.altitude_m[0, ks[-1]]:.1f} m, "
          f"t {t_us[0]} -> {t_us[-1]} us")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
