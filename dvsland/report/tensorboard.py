"""TensorBoard output of a simulation, written incrementally while the loop runs.

Layout under ``<run_dir>/tb/``: one sub-folder per descent (``A_Kp5e6-n5``) holding its scalars
and images, so TensorBoard overlays the descents on one chart per tag; the top folder holds the
resolved config and the final results table as text.

Per-run scalar tags: ``altitude_m``, ``velocity_mps``, ``mass_kg``, ``thrust_n``,
``divergence/true``, ``divergence/estimated``, ``divergence/filtered``, ``ttc/true_s``,
``ttc/estimated_s``, ``ttc/target_s``, ``control/held``, ``control/n_used``, and
``tracking/n_centroids`` where the estimator reports centroids. The step axis is the control
step index (t = step * dt). Images (every ``image_every_s`` of flight, active descents only):
``images/frame`` and ``images/events`` with the tracked centroids drawn in green.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

SCALAR_TAGS = {
    "z_m": "altitude_m", "v_mps": "velocity_mps", "m_kg": "mass_kg", "thrust_n": "thrust_n",
    "d_true": "divergence/true", "d_est": "divergence/estimated", "d_filtered": "divergence/filtered",
    "tau_target_s": "ttc/target_s", "tau_hat_s": "ttc/estimated_s", "n_used": "control/n_used",
}


def run_folder_name(run_label: str) -> str:
    """File-system-safe folder name of a run label (``A/Kp5e6-n5`` -> ``A_Kp5e6-n5``); the config
    check refuses settings whose labels would collide here."""
    from dvsland.config.validate import folder_name

    return folder_name(run_label)


def draw_centroids(rgb: np.ndarray, centroids_xy: Optional[np.ndarray], color=(0, 255, 0)) -> np.ndarray:
    """Draw small crosses at ``centroids_xy`` (N, 2) px (x, y; NaN rows skipped) on ``rgb`` (H, W, 3) uint8."""
    if centroids_xy is None:
        return rgb
    h, w = rgb.shape[:2]
    pts = centroids_xy[np.isfinite(centroids_xy).all(axis=1)]
    for x, y in np.rint(pts).astype(int):
        for dx, dy in ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1), (-2, 0), (2, 0), (0, -2), (0, 2)):
            xx, yy = x + dx, y + dy
            if 0 <= xx < w and 0 <= yy < h:
                rgb[yy, xx] = color
    return rgb


def frame_to_rgb(frame: np.ndarray) -> np.ndarray:
    """(H, W) linear irradiance -> (H, W, 3) uint8, normalised by the 99.5th percentile, gamma 1/2.2."""
    f = np.asarray(frame, dtype=np.float64)
    hi = np.percentile(f, 99.5) if f.size else 1.0
    f = np.clip(f / (hi if hi > 0 else 1.0), 0, 1) ** (1 / 2.2)
    g = (f * 255).astype(np.uint8)
    return np.stack([g, g, g], axis=-1)


def counts_to_rgb(counts: np.ndarray) -> np.ndarray:
    """(2, H, W) event counts in the layout of :meth:`dvsland.events.Events.to_count_image`
    (channel 0 = ON, 1 = OFF) -> (H, W, 3) uint8: ON red, OFF blue (sqrt-scaled by the max count)."""
    c = np.asarray(counts, dtype=np.float64)
    hi = max(float(c.max()), 1.0)
    rgb = np.zeros(c.shape[1:] + (3,), dtype=np.uint8)
    rgb[..., 0] = (np.clip(c[0] / hi, 0, 1) ** 0.5 * 255).astype(np.uint8)
    rgb[..., 2] = (np.clip(c[1] / hi, 0, 1) ** 0.5 * 255).astype(np.uint8)
    return rgb


class TensorBoardLogger:
    """Writes a :class:`dvsland.sim.loop.ClosedLoop`'s traces and images as it flies.

    Args:
        log_dir: folder (``<run_dir>/tb``).
        run_labels: (B,) run labels.
        dt_s: control step, s.
        scalar_every_s: scalars every this many s of flight (>= dt: every step).
        image_every_s: images every this many s of flight.
        flush_every_s: write buffered scalars every this many s of flight.
    """

    def __init__(self, log_dir, run_labels: Sequence[str], dt_s: float, scalar_every_s: float = 0.5,
                 image_every_s: float = 5.0, flush_every_s: float = 5.0):
        from torch.utils.tensorboard.writer import FileWriter

        self.log_dir = Path(log_dir)
        self.run_labels = list(run_labels)
        self.dt_s = float(dt_s)
        self.scalar_every = max(1, int(round(scalar_every_s / dt_s)))
        self.image_every = max(1, int(round(image_every_s / dt_s)))
        self.flush_every = max(1, int(round(flush_every_s / dt_s)))
        # the writers' own threads flush every few wall seconds: a crash loses at most that much
        self.top = FileWriter(str(self.log_dir), flush_secs=5)
        self.writers = [FileWriter(str(self.log_dir / run_folder_name(r)), flush_secs=5) for r in self.run_labels]
        self._written_rows = 0
        self._closed = False

    # -------------------------------------------------------------- text
    def add_text(self, tag: str, text: str, step: int = 0) -> None:
        """Markdown text on the top writer (config, results table)."""
        from torch.utils.tensorboard.summary import text as text_summary

        self.top.add_summary(text_summary(tag, text), step, time.time())

    def add_config(self, cfg_yaml: str) -> None:
        """The resolved config, as a YAML code block."""
        self.add_text("config", "```yaml\n" + cfg_yaml + "\n```")
        self.top.flush()

    # -------------------------------------------------------------- scalars
    def write_rows(self, traces: Dict[str, np.ndarray], start_row: int, n_centroids: Optional[np.ndarray] = None) -> None:
        """Scalars of rows ``start_row + i`` of ``traces`` (each (n, B)), decimated, active rows only."""
        from tensorboard.compat.proto.summary_pb2 import Summary

        n = traces["z_m"].shape[0]
        wall = time.time()
        rows = [i for i in range(n) if (start_row + i) % self.scalar_every == 0]
        if not rows:
            return
        # plain Python lists once per chunk: indexing numpy scalars one by one is slow
        cols = {key: traces[key][rows].tolist() for key in SCALAR_TAGS}
        z_l, v_l = traces["z_m"][rows].tolist(), traces["v_mps"][rows].tolist()
        active_l, held_l = traces["active"][rows].tolist(), traces["held"][rows].tolist()
        Value = Summary.Value
        isfinite = math.isfinite
        for j, i in enumerate(rows):
            row = start_row + i
            for b, w in enumerate(self.writers):
                if not active_l[j][b]:
                    continue
                vals = [Value(tag=tag, simple_value=x) for key, tag in SCALAR_TAGS.items()
                        if isfinite(x := cols[key][j][b])]
                if v_l[j][b] < 0:
                    vals.append(Value(tag="ttc/true_s", simple_value=-z_l[j][b] / v_l[j][b]))
                vals.append(Value(tag="control/held", simple_value=float(held_l[j][b])))
                w.add_summary(Summary(value=vals), row, wall)

    def on_step(self, loop) -> None:
        """Call after each loop step: flushes scalars periodically, logs images every few seconds."""
        k = loop.step_index  # rows [0, k) are recorded
        if (k - 1) % self.image_every == 0:
            self._images(loop, k - 1)
        if k - self._written_rows >= self.flush_every:
            self._flush_rows(loop, k)

    def _flush_rows(self, loop, stop_row: int) -> None:
        if stop_row <= self._written_rows:
            return
        tr = loop.traces.numpy(self._written_rows, stop_row)
        self.write_rows(tr, self._written_rows)
        self._written_rows = stop_row

    def _images(self, loop, row: int) -> None:
        from torch.utils.tensorboard.summary import image as image_summary
        from tensorboard.compat.proto.summary_pb2 import Summary

        diag = {}
        try:
            diag = loop.estimator.diagnostics() or {}
        except Exception:  # diagnostics are optional; never break the run for them
            diag = {}
        cents = diag.get("centroids")
        cents = cents.detach().cpu().numpy() if isinstance(cents, torch.Tensor) else None
        active = loop.traces.flags["active"][row].cpu().numpy()
        frames = loop.last_frames.detach().float().cpu().numpy() if loop.last_frames is not None else None
        counts = None
        ev = loop.last_events
        if ev is not None and frames is not None and hasattr(ev, "to_count_image"):
            B, H, W = frames.shape
            counts = ev.to_count_image(B, H, W).detach().cpu().numpy()
        wall = time.time()
        for b, w in enumerate(self.writers):
            if not active[b]:
                continue
            c = cents[b] if cents is not None and b < len(cents) else None
            if cents is not None:
                n_c = int(np.isfinite(c).all(axis=1).sum()) if c is not None else 0
                w.add_summary(Summary(value=[Summary.Value(tag="tracking/n_centroids", simple_value=n_c)]), row, wall)
            if frames is not None:
                img = draw_centroids(frame_to_rgb(frames[b]), c)
                w.add_summary(image_summary("images/frame", img, dataformats="HWC"), row, wall)
            if counts is not None:
                img = draw_centroids(counts_to_rgb(counts[b]), c)
                w.add_summary(image_summary("images/events", img, dataformats="HWC"), row, wall)

    # -------------------------------------------------------------- end
    def close(self, loop=None, table_markdown: Optional[str] = None) -> None:
        """Write the remaining rows, the results table, and close every file (safe to call twice)."""
        if self._closed:
            return
        try:
            if loop is not None:
                self._flush_rows(loop, loop.traces.rows)
            if table_markdown:
                self.add_text("results", table_markdown)
        finally:
            for w in self.writers + [self.top]:
                w.flush()
                w.close()
            self._closed = True
