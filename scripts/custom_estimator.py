#!/usr/bin/env python
"""A user-written divergence estimator, registered by name and flown in the closed loop.

The estimator ("zoomcorr") compares the event count image of the last step with the one before,
zoomed about the image centre by a grid of candidate scales, and picks the scale that correlates
best: features seen at scale s = exp(-D dt) larger give D = -ln(s) / dt. It is short on purpose:
everything an estimator needs is ``reset(mask)``, ``update(events, t_us, truth)`` returning (B,)
D_hat (1/s, NaN = none) and, optionally, ``diagnostics()``.

Usage:
    python scripts/custom_estimator.py                    # closed loop, sites D and F
    python scripts/custom_estimator.py --sites A,B,C,D    # other sites
    python scripts/custom_estimator.py --open-loop        # open-loop metrics instead (quick sample)

To ship such an estimator in a package instead, declare it under the entry-point group
``dvsland.estimators`` (pyproject.toml: ``[project.entry-points."dvsland.estimators"]
zoomcorr = "mypkg.zoomcorr:ZoomCorr"``) and select it with ``estimator.name: zoomcorr``.
"""

from __future__ import annotations

import argparse
import math

import torch
import torch.nn.functional as F

from dvsland.estimators import DivergenceEstimator, register_estimator


@register_estimator("zoomcorr")
class ZoomCorr(DivergenceEstimator):
    """D from the zoom that best maps the previous count image onto the current one.

    Args: batch_size, sensor_size (W, H), device, dt_s; d_min, d_max, n_grid: searched D (1/s);
    blur_px: Gaussian blur of the count images; min_events: fewer events -> NaN.
    """

    def __init__(self, batch_size, sensor_size, device="cpu", dt_s=0.1, d_min=-1.0, d_max=0.2, n_grid=49,
                 blur_px=2.0, min_events=200):  # dvsland passes seed only to constructors that take it
        super().__init__(batch_size, sensor_size, device, dt_s)
        self.d_grid = torch.linspace(d_min, d_max, n_grid, device=self.device)
        self.blur_px, self.min_events = float(blur_px), int(min_events)
        W, H = self.sensor_size
        self.prev = torch.zeros(self.batch_size, 1, H, W, device=self.device)
        self.has_prev = torch.zeros(self.batch_size, dtype=torch.bool, device=self.device)

    def reset(self, mask=None):
        mask = self._mask(mask)
        self.prev[mask] = 0.0
        self.has_prev[mask] = False

    def _image(self, events):
        from kornia.filters import gaussian_blur2d

        W, H = self.sensor_size
        img = torch.zeros(self.batch_size * H * W, device=self.device)
        if events is not None and len(events) > 0:
            idx = (events.b * H + events.y) * W + events.x
            img.index_add_(0, idx.to(self.device), torch.ones(len(events), device=self.device))
        k = 2 * math.ceil(3 * self.blur_px) + 1
        return gaussian_blur2d(img.view(self.batch_size, 1, H, W), (k, k), (self.blur_px, self.blur_px))

    def update(self, events, t_us, truth=None):
        B, G = self.batch_size, self.d_grid.numel()
        cur = self._image(events)
        # zoom the previous image by s = exp(-D dt) for every candidate: (B*G, 1, H, W) in one grid_sample
        s = torch.exp(-self.d_grid * self.dt_s)
        theta = torch.zeros(G, 2, 3, device=self.device)
        theta[:, 0, 0] = 1.0 / s
        theta[:, 1, 1] = 1.0 / s
        grid = F.affine_grid(theta, (G, 1) + cur.shape[-2:], align_corners=False)
        zoomed = F.grid_sample(self.prev.repeat_interleave(G, 0), grid.repeat(B, 1, 1, 1), align_corners=False)
        a = zoomed.view(B, G, -1)
        a = a - a.mean(-1, keepdim=True)
        c = (cur.view(B, 1, -1) - cur.view(B, 1, -1).mean(-1, keepdim=True))
        corr = (a * c).sum(-1) / (a.norm(dim=-1) * c.norm(dim=-1)).clamp_min(1e-9)
        d = self.d_grid[corr.argmax(1)]
        n = cur.view(B, -1).sum(1)
        ok = self.has_prev & (n >= self.min_events)
        self.prev = cur
        self.has_prev = torch.ones_like(self.has_prev)
        return torch.where(ok, d, torch.full_like(d, float("nan")))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=None, help="YAML config (default configs/paper.yaml)")
    ap.add_argument("--sites", default="D,F", help="sites to fly (default D,F)")
    ap.add_argument("--open-loop", action="store_true", help="open-loop evaluation instead of the closed loop")
    ap.add_argument("--out", default=None, help="run folder")
    ap.add_argument("--unbounded", action="store_true", help="the paper's unbounded thrust (default 100 kN max)")
    args = ap.parse_args()

    from dvsland.config import load_config

    # The paper's Eq. 2 with unbounded thrust has a loop gain of ~200 1/s at 10 Hz: any estimate a
    # few % too large fires a huge thrust pulse (ascent). Fly with the 100 kN engine of the
    # realistic preset unless --unbounded is given.
    over = ["estimator.name=zoomcorr"] + ([] if args.unbounded else ["controller.thrust_max_n=100000"])
    cfg = load_config(args.config, over)
    sites = [s for s in args.sites.split(",") if s]
    if args.open_loop:
        from dvsland.evaluate import evaluate, format_table

        res = evaluate(cfg, ["zoomcorr", "dpr"], sites, segment_steps=20, stride=8)
        print(format_table(res.summary))
        return 0
    import dvsland

    result = dvsland.simulate(cfg, sites=sites, out=args.out)
    for r in result.runs:
        print(f"site {r['site']} {r.get('label', '')}: {r['outcome']} at t = {r['t_end_s']:.1f} s, "
              f"lowest altitude {r['lowest_altitude_m']:.1f} m")
    print(f"run folder: {result.run_dir}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
