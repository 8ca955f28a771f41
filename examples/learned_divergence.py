"""A learned divergence estimator, end to end: train a small CNN on a dvsland dataset, fly it.

This file is an example of the learning path of docs/learning.md, kept short on purpose:

    dvsland dataset build montecarlo_efference --n-seeds 2 --sites D,E,F,G --out data/mc --quiet
    python examples/learned_divergence.py train data/mc --minutes 5 --out logs/cnn.pt
    python examples/learned_divergence.py evaluate data/mc logs/cnn.pt
    dvsland simulate montecarlo_efference --sites D --estimator examples/learned_divergence.py:CNNEstimator \
        --set estimator.params.checkpoint=logs/cnn.pt

The model sees one control step's events as a polarity-signed voxel grid (4 time bins), plus two
coordinate channels (pixel position relative to the principal point: divergence is a radial
expansion about it) and the log of the window's event count. It predicts log|D| with a Gaussian
negative log-likelihood, so it also predicts its own uncertainty; the estimator returns
D_hat = -exp(mu) (descending) and a confidence 1 / (1 + sigma^2) that the loop's filter reads.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Optional

import torch
from torch import nn

from dvsland.estimators import DivergenceEstimator

N_BINS = 4


class DivergenceCNN(nn.Module):
    """(B, N_BINS, H, W) signed voxel grids and (B,) log event counts -> (mu, log_var) of log|D|, (B,) each."""

    def __init__(self, sensor_size=(128, 128), width: int = 16):
        super().__init__()
        W, H = sensor_size
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, H), torch.linspace(-1, 1, W), indexing="ij")
        self.register_buffer("coords", torch.stack([xs, ys])[None])  # (1, 2, H, W)
        c = width
        self.features = nn.Sequential(
            nn.Conv2d(N_BINS + 2, c, 5, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(c, 2 * c, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(2 * c, 2 * c, 3, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(2 * c, 2 * c, 3, stride=2, padding=1), nn.ReLU())
        self.head = nn.Sequential(nn.Linear(4 * c + 1, 32), nn.ReLU(), nn.Linear(32, 2))

    def forward(self, voxels: torch.Tensor, log_count: torch.Tensor):
        scale = voxels.abs().mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-3)
        x = torch.cat([voxels / scale, self.coords.expand(voxels.shape[0], -1, -1, -1)], dim=1)
        f = self.features(x)
        f = torch.cat([f.mean(dim=(2, 3)), f.amax(dim=(2, 3)), log_count[:, None]], dim=1)
        mu, log_var = self.head(f).unbind(1)
        return mu, log_var.clamp(-10, 5)


# ------------------------------------------------------------------ training
def _batches(dataset, batch_size: int, shuffle: bool, seed: int):
    loader = torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=shuffle,
                                         generator=torch.Generator().manual_seed(seed))
    for x, y in loader:
        yield x, torch.log1p(y["n_events"].float()), torch.log(-y["d_true"].double()).float()


def median_rel_error(model, dataset, max_batches: int = 40) -> float:
    """Median |D_hat - D| / |D| of ``model`` over (up to) ``max_batches`` batches of ``dataset``."""
    errs = []
    model.eval()
    with torch.no_grad():
        for i, (x, lc, y) in enumerate(_batches(dataset, 128, False, 0)):
            if i >= max_batches:
                break
            mu, _ = model(x, lc)
            errs.append((torch.exp(mu - y) - 1).abs())
    return float(torch.cat(errs).median())


def train(data_dir: str, minutes: float, out: str, seed: int = 0) -> dict:
    """Train on the ``train`` split for ``minutes`` of wall time, keep the best on ``val``; returns the history."""
    from dvsland.data import EventWindowDataset

    torch.manual_seed(seed)
    tr = EventWindowDataset(data_dir, representation="voxel", n_bins=N_BINS, split="train")
    va = EventWindowDataset(data_dir, representation="voxel", n_bins=N_BINS, split="val")
    model = DivergenceCNN(tr.sensor_size)
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3, weight_decay=1e-4)
    t_end, epoch, best, history = time.time() + 60 * minutes, 0, math.inf, []
    while time.time() < t_end:
        model.train()
        for x, lc, y in _batches(tr, 64, True, seed + epoch):
            mu, log_var = model(x, lc)
            loss = nn.functional.gaussian_nll_loss(mu, y, log_var.exp())
            opt.zero_grad()
            loss.backward()
            opt.step()
            if time.time() > t_end:
                break
        err = median_rel_error(model, va)
        history.append({"epoch": epoch, "loss": loss.item(), "val_median_rel_error": err})
        print(f"epoch {epoch}: loss {loss.item():.3f}, val median |rel err| {100 * err:.1f} %")
        if err < best:
            best = err
            torch.save({"state_dict": model.state_dict(), "sensor_size": tr.sensor_size, "history": history,
                        "data": str(data_dir)}, out)
        epoch += 1
    return {"best_val_median_rel_error": best, "history": history}


# ------------------------------------------------------------------ flying it
class CNNEstimator(DivergenceEstimator):
    """The trained :class:`DivergenceCNN` as a loop estimator (``checkpoint``: a file of :func:`train`).

    ``update`` returns (B,) float32 D_hat = -exp(mu) in 1/s, NaN where the window has no events;
    ``confidence()`` (B,) = 1 / (1 + sigma^2) of the predicted log|D|.
    """

    def __init__(self, batch_size, sensor_size, device="cpu", checkpoint: Optional[str] = None, **kw):
        super().__init__(batch_size, sensor_size, device, dt_s=kw.get("dt_s", 0.1))
        if not checkpoint or not Path(checkpoint).is_file():
            raise ValueError(f"estimator.params.checkpoint must name a file written by this example's train, "
                             f"got {checkpoint!r}")
        blob = torch.load(checkpoint, map_location="cpu", weights_only=False)
        if tuple(blob["sensor_size"]) != self.sensor_size:
            raise ValueError(f"checkpoint {checkpoint!r} is for sensor {blob['sensor_size']}, the camera is "
                             f"{self.sensor_size}")
        self.model = DivergenceCNN(self.sensor_size).to(self.device).eval()
        self.model.load_state_dict(blob["state_dict"])
        self._t_prev: Optional[int] = None
        self._conf = torch.zeros(self.batch_size, device=self.device)

    def reset(self, mask=None) -> None:
        if mask is None or bool(self._mask(mask).all()):
            self._t_prev = None

    def update(self, events, t_us: int, truth=None) -> torch.Tensor:
        B, (W, H) = self.batch_size, self.sensor_size
        t0 = int(t_us - round(self.dt_s * 1e6)) if self._t_prev is None else self._t_prev
        self._t_prev = int(t_us)
        vox = events.to_voxel_grid(N_BINS, t0, int(t_us), B, H, W)
        n = events.batch_counts(B).to(self.device)
        with torch.no_grad():
            mu, log_var = self.model(vox, torch.log1p(n.float()))
        self._conf = 1.0 / (1.0 + log_var.exp())
        d = -torch.exp(mu)
        return torch.where(n > 0, d, torch.full_like(d, float("nan"))).to(torch.float32)

    def confidence(self) -> torch.Tensor:
        return self._conf


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="train or evaluate the example CNN divergence estimator")
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("data")
    t.add_argument("--minutes", type=float, default=5.0)
    t.add_argument("--out", required=True)
    t.add_argument("--seed", type=int, default=0)
    e = sub.add_parser("evaluate")
    e.add_argument("data")
    e.add_argument("checkpoint")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.cmd == "train":
        res = train(a.data, a.minutes, a.out, a.seed)
        print(f"best val median |rel err| {100 * res['best_val_median_rel_error']:.1f} %; checkpoint {a.out}")
        return 0
    from dvsland.data import EventWindowDataset

    blob = torch.load(a.checkpoint, map_location="cpu", weights_only=False)
    model = DivergenceCNN(tuple(blob["sensor_size"]))
    model.load_state_dict(blob["state_dict"])
    for split in ("train", "val", "test"):
        ds = EventWindowDataset(a.data, representation="voxel", n_bins=N_BINS, split=split)
        print(f"{split}: median |rel err| {100 * median_rel_error(model, ds, 10_000):.1f} % over {len(ds)} samples")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
