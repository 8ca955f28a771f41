"""TensorBoard output of a simulation, written with :class:`torch.utils.tensorboard.SummaryWriter`
while the loop runs.

Layout under ``<run_dir>/tb/``: one sub-folder per descent (``A_Kp5e6-n5``), each with exactly one
event file holding that descent's scalars, histograms, images and HParams session, so TensorBoard
overlays the descents on one chart per tag and lists them as rows of the HParams table. The top
folder holds the resolved config and the results table as text, the HParams experiment (the
columns of the HParams table) and a custom-scalars layout. A folder that already holds TensorBoard
files (a run folder reused on purpose) is never appended to: :func:`fresh_log_dir` picks ``tb-2/``,
``tb-3/``, ...

**x-axis = flight time.** TensorBoard's x-axis is a step, a relative time or a wall time. Every
per-descent entry is written with ``global_step = round(t_s * 1000)``, the flight time in
milliseconds (a step of 93 100 is t = 93.1 s), and with ``walltime = start + t_s``, so the
RELATIVE axis also reads flight time (and the WALL axis shows start + flight time, not the
computer's clock).

Per-descent scalar tags: ``altitude_m``, ``velocity_mps``, ``mass_kg``, ``thrust_n``,
``divergence/true``, ``divergence/estimated``, ``divergence/filtered`` (1/s), ``ttc/true_s``,
``ttc/estimated_s``, ``ttc/target_s``, ``control/held``, ``control/n_used``, and
``tracking/n_centroids`` where the estimator reports centroids. Histograms:
``divergence/rel_error`` (D̂ − D)/|D| of the estimates in each flush window (every
``flush_every_s`` of flight), clipped to ±2, in bins of 0.1. Images (every ``image_every_s`` of flight, active descents only):
``images/frame`` and ``images/events`` (ON red, OFF blue) with the tracked centroids in green.
HParams (written when the run ends): site, setting, Kp, n_bin, seed index, estimator, renderer (when frames are rendered) against
the outcome metrics ``outcome/success``, ``outcome/t_end_s``, ``outcome/lowest_altitude_m``,
``outcome/v_end_mps``, ``outcome/fuel_used_kg``, ``outcome/max_thrust_kN`` and
``outcome/median_abs_rel_err``.
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

#: the per-step fields the logger reads from a StepOutput (besides t_s)
TRACE_ROW_FIELDS = ("z_m", "v_mps", "m_kg", "thrust_n", "d_true", "d_est", "d_filtered", "tau_target_s", "tau_hat_s",
                    "n_used", "active", "held")

#: the HParams metrics of a closed-loop descent (scalar tag -> results.json key or a derived value)
OUTCOME_METRICS = ("outcome/success", "outcome/t_end_s", "outcome/lowest_altitude_m", "outcome/v_end_mps",
                   "outcome/fuel_used_kg", "outcome/max_thrust_kN", "outcome/median_abs_rel_err")


def run_folder_name(run_label: str) -> str:
    """File-system-safe folder name of a run label (``A/Kp5e6-n5`` -> ``A_Kp5e6-n5``); the config
    check refuses settings whose labels would collide here."""
    from dvsland.config.validate import folder_name

    return folder_name(run_label)


def flight_step(t_s: float) -> int:
    """TensorBoard ``global_step`` of flight time ``t_s``: milliseconds, rounded (93.1 s -> 93100)."""
    return int(round(float(t_s) * 1000.0))


def fresh_log_dir(path) -> Path:
    """``path`` if it holds no TensorBoard files yet, else the first free ``<path>-2``, ``-3``, ...

    A reused run folder (``--out``) must not append a second event file whose steps restart at 0
    to the first run's curves: the new run gets its own folder, which TensorBoard lists as its own run.
    """
    path = Path(path)

    def used(p: Path) -> bool:
        return p.exists() and any(p.rglob("events.out.tfevents.*"))

    if not used(path):
        return path
    k = 2
    while used(path.with_name(f"{path.name}-{k}")) or path.with_name(f"{path.name}-{k}").is_file():
        k += 1
    return path.with_name(f"{path.name}-{k}")


def _quiet_writer_thread_errors() -> None:
    """Keep an ``OSError`` in a TensorBoard writer's background thread (a full disk) from being
    printed as a thread traceback: the writer keeps the exception and raises it on its next call,
    where the caller turns it into one error naming the folder. Other threads' exceptions, and
    other exceptions, still go to the previous hook. Installed once."""
    import threading

    if getattr(threading.excepthook, "_dvsland_tb_filter", False):
        return
    previous = threading.excepthook

    def hook(args):
        if isinstance(args.exc_value, OSError) and type(args.thread).__name__ == "_AsyncWriterThread":
            return
        previous(args)

    hook._dvsland_tb_filter = True
    threading.excepthook = hook


def summary_writer(log_dir, flush_secs: int = 5):
    """A :class:`torch.utils.tensorboard.SummaryWriter` on ``log_dir`` (created)."""
    from torch.utils.tensorboard import SummaryWriter

    _quiet_writer_thread_errors()
    Path(log_dir).mkdir(parents=True, exist_ok=True)
    return SummaryWriter(log_dir=str(log_dir), flush_secs=flush_secs)


#: relative errors are clipped to +-this before their histogram (fixed bins of 0.1)
REL_ERROR_CLIP = 2.0
_REL_EDGES = np.linspace(-REL_ERROR_CLIP, REL_ERROR_CLIP, 41)


def add_histogram_fixed(writer, tag: str, values: np.ndarray, step: int, walltime: Optional[float] = None,
                        edges: np.ndarray = _REL_EDGES) -> None:
    """A histogram on fixed bucket ``edges`` (values outside are clipped in), written with
    ``SummaryWriter.add_histogram_raw``: about 10x cheaper than ``add_histogram``'s automatic bins."""
    v = np.clip(np.asarray(values, dtype=np.float64).ravel(), edges[0], edges[-1])
    if v.size == 0:
        return
    counts, _ = np.histogram(v, edges)
    writer.add_histogram_raw(tag, min=float(v.min()), max=float(v.max()), num=int(v.size), sum=float(v.sum()),
                             sum_squares=float((v * v).sum()), bucket_limits=edges[1:].tolist(),
                             bucket_counts=counts.tolist(), global_step=step, walltime=walltime)


def write_hparams(top_writer, run_writers: Sequence, hparams: Sequence[dict], metrics: Sequence[dict],
                  walltime: Optional[float] = None, step: Optional[int] = None) -> None:
    """HParams: one experiment on ``top_writer`` (the table's columns) and one session per run on ``run_writers[i]`` with its metrics as
    scalars, so each run is one row of TensorBoard's HParams table, next to its own curves.

    Args:
        top_writer: SummaryWriter of the parent folder.
        run_writers: one SummaryWriter per run (its own sub-folder).
        hparams: per run, {name: bool | int | float | str}.
        metrics: per run, {scalar tag: float}; NaN values are left out of that run.
        walltime, step: of the metric scalars (default: now, 0); a list gives one per run.
    """
    from torch.utils.tensorboard.summary import hparams as hparams_summary

    if not hparams:
        return
    names = list(dict.fromkeys(k for h in hparams for k in h))
    tags = list(dict.fromkeys(k for m in metrics for k in m))
    union = {k: next(h[k] for h in hparams if k in h) for k in names}
    # no discrete domains: with --logdir over several runs TensorBoard uses one run's experiment,
    # and a domain listing only that run's values would filter the other runs' rows out
    exp, _, _ = hparams_summary(union, {t: 0.0 for t in tags})
    top_writer._get_file_writer().add_summary(exp)
    for i, (w, h, m) in enumerate(zip(run_writers, hparams, metrics)):
        _, ssi, sei = hparams_summary(h, {t: 0.0 for t in tags})
        fw = w._get_file_writer()
        fw.add_summary(ssi)
        fw.add_summary(sei)
        st = step[i] if isinstance(step, (list, tuple)) else (step or 0)
        wt = walltime[i] if isinstance(walltime, (list, tuple)) else walltime
        for tag, val in m.items():
            if val is not None and math.isfinite(float(val)):
                w.add_scalar(tag, float(val), st, walltime=wt)


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


def image_summary(tag: str, rgb: np.ndarray):
    """A TensorBoard image ``Summary`` of ``rgb`` (H, W, 3) uint8: the pixels ``add_image`` would
    store (it converts uint8 HWC unchanged), PNG-encoded at zlib level 1 instead of 6 (about half
    the encoding time, ~10 % larger files; PNG is lossless, so TensorBoard shows the same image)."""
    import io

    from PIL import Image
    from tensorboard.compat.proto.summary_pb2 import Summary

    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG", compress_level=1)
    img = Summary.Image(height=int(rgb.shape[0]), width=int(rgb.shape[1]), colorspace=3,
                        encoded_image_string=buf.getvalue())
    return Summary(value=[Summary.Value(tag=tag, image=img)])


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


def descent_layout() -> dict:
    """Custom-scalars layout (TensorBoard's CUSTOM SCALARS tab): D true / estimated / filtered on
    one chart, τ true / estimated / target on another, and the state, for every descent."""
    return {
        "descent (x = flight time, ms)": {
            "divergence D [1/s]: true, estimated, filtered": ["Multiline", [r"divergence/(true|estimated|filtered)"]],
            "time to contact [s]: true, estimated, target": ["Multiline", [r"ttc/.*"]],
            "altitude [m]": ["Multiline", [r"altitude_m"]],
            "velocity [m/s]": ["Multiline", [r"velocity_mps"]],
            "thrust [N]": ["Multiline", [r"thrust_n"]],
        }
    }


class TensorBoardLogger:
    """Writes a flight's scalars and images from its :class:`dvsland.sim.StepOutput` s as it flies.

    Args:
        log_dir: folder (``<run_dir>/tb``); if it already holds TensorBoard files the logger writes
            into a fresh sibling (:func:`fresh_log_dir`); the folder used is ``self.log_dir``.
        run_labels: (B,) run labels.
        dt_s: control step, s.
        scalar_every_s: scalars every this many s of flight (>= dt: every step).
        image_every_s: images every this many s of flight.
        flush_every_s: write buffered scalars (and one error histogram) every this many s of flight.
    """

    def __init__(self, log_dir, run_labels: Sequence[str], dt_s: float, scalar_every_s: float = 0.5,
                 image_every_s: float = 5.0, flush_every_s: float = 5.0):
        self.log_dir = fresh_log_dir(log_dir)
        self.run_labels = list(run_labels)
        self.dt_s = float(dt_s)
        self.scalar_every = max(1, int(round(scalar_every_s / dt_s)))
        self.image_every = max(1, int(round(image_every_s / dt_s)))
        self.flush_every = max(1, int(round(flush_every_s / dt_s)))
        self.start_wall = time.time()
        # the writers' own threads flush every few wall seconds: a crash loses at most that much
        self.top = summary_writer(self.log_dir)
        self.writers = [summary_writer(self.log_dir / run_folder_name(r)) for r in self.run_labels]
        self.top.add_custom_scalars(descent_layout())
        self._written_rows = 0
        self._rows: List[dict] = []  # buffered step rows, written every flush_every steps
        self._closed = False
        # images are converted and PNG-encoded on one background thread (zlib and most numpy work
        # release the GIL: on a machine with a free core the loop does not wait for them)
        self._image_pool = None
        self._image_jobs: list = []

    def _wall(self, t_s: float) -> float:
        return self.start_wall + float(t_s)

    # -------------------------------------------------------------- text
    def add_text(self, tag: str, text: str, step: int = 0) -> None:
        """Markdown text on the top writer (config, results table)."""
        self.top.add_text(tag, text, step)

    def add_config(self, cfg_yaml: str) -> None:
        """The resolved config, as a YAML code block."""
        self.add_text("config", "```yaml\n" + cfg_yaml + "\n```")
        self.top.flush()

    # -------------------------------------------------------------- scalars
    def write_rows(self, traces: Dict[str, np.ndarray], start_row: int, n_centroids: Optional[np.ndarray] = None) -> None:
        """Scalars of rows ``start_row + i`` of ``traces`` (each (n, B)), decimated, active rows only,
        at step = flight time in ms; plus one histogram per descent of the relative error of the
        estimates in these rows (all active rows, not decimated)."""
        from tensorboard.compat.proto.summary_pb2 import Summary

        n = traces["z_m"].shape[0]
        t_s = traces["t_s"] if "t_s" in traces else (start_row + np.arange(n))[:, None] * self.dt_s \
            + np.zeros((1, len(self.writers)))
        rows = [i for i in range(n) if (start_row + i) % self.scalar_every == 0]
        if rows:
            # plain Python lists once per chunk: indexing numpy scalars one by one is slow
            cols = {key: traces[key][rows].tolist() for key in SCALAR_TAGS}
            z_l, v_l = traces["z_m"][rows].tolist(), traces["v_mps"][rows].tolist()
            active_l, held_l = traces["active"][rows].tolist(), traces["held"][rows].tolist()
            t_l = np.asarray(t_s)[rows].tolist()
            Value = Summary.Value
            isfinite = math.isfinite
            file_writers = [w._get_file_writer() for w in self.writers]
            for j in range(len(rows)):
                for b, fw in enumerate(file_writers):
                    if not active_l[j][b]:
                        continue
                    vals = [Value(tag=tag, simple_value=x) for key, tag in SCALAR_TAGS.items()
                            if isfinite(x := cols[key][j][b])]
                    if v_l[j][b] < 0:
                        vals.append(Value(tag="ttc/true_s", simple_value=-z_l[j][b] / v_l[j][b]))
                    vals.append(Value(tag="control/held", simple_value=float(held_l[j][b])))
                    t = t_l[j][b]
                    # several tags in one Summary: one event per row, the cost of one add_scalar
                    fw.add_summary(Summary(value=vals), flight_step(t), self._wall(t))
        self._error_histograms(traces, np.asarray(t_s))

    def _error_histograms(self, traces: Dict[str, np.ndarray], t_s: np.ndarray) -> None:
        d_true, d_est, active = traces["d_true"], traces["d_est"], traces["active"].astype(bool)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = (d_est - d_true) / np.abs(d_true)
        ok = np.isfinite(rel) & active
        if not ok.any():
            return
        rel = np.clip(rel, -REL_ERROR_CLIP, REL_ERROR_CLIP)
        for b in np.nonzero(ok.any(axis=0))[0].tolist():
            r = rel[ok[:, b], b]
            last = np.nonzero(ok[:, b])[0][-1]
            add_histogram_fixed(self.writers[b], "divergence/rel_error", r, flight_step(t_s[last, b]),
                                self._wall(t_s[last, b]))

    def on_step(self, out) -> None:
        """Call after each loop step with its :class:`dvsland.sim.StepOutput`: buffers the step's
        scalars and writes them every ``flush_every`` steps; logs images every ``image_every`` steps."""
        if out.step % self.image_every == 0:
            self._images(out)
        z = out.z_m
        row = [z.new_full(z.shape, float(out.t_s))]
        for k in TRACE_ROW_FIELDS:
            v = getattr(out, k)
            row.append(v.to(z.dtype) if isinstance(v, torch.Tensor) else z.new_full(z.shape, float(v)))
        self._rows.append(torch.stack(row))  # (1 + fields, B): one small copy per step
        if len(self._rows) >= self.flush_every:
            self._flush_buffered()

    def _flush_buffered(self) -> None:
        if not self._rows:
            return
        block = torch.stack(self._rows, dim=1).cpu().numpy()  # (1 + fields, rows, B)
        tr = {"t_s": block[0]}
        for i, k in enumerate(TRACE_ROW_FIELDS, start=1):
            tr[k] = block[i] != 0 if k in ("active", "held") else block[i]
        self.write_rows(tr, self._written_rows)
        self._written_rows += len(self._rows)
        self._rows = []

    def _images(self, out) -> None:
        """Queue the step's frame and event images of every active descent (written by
        :meth:`_write_images` on the background thread; at most two steps wait)."""
        try:
            diag = out.diagnostics() or {}
        except Exception:  # diagnostics are optional; never break the run for them
            diag = {}
        cents = diag.get("centroids")
        cents = cents.detach().cpu().numpy() if isinstance(cents, torch.Tensor) else None
        active = out.active.cpu().numpy()
        frames = out.frames.detach().float().cpu().numpy() if out.frames is not None else None
        counts = None
        ev = out.events
        if ev is not None and frames is not None and hasattr(ev, "to_count_image"):
            B, H, W = frames.shape
            counts = ev.to_count_image(B, H, W).detach().cpu().numpy()
        t_s = out.step * self.dt_s  # the time of trace row `row` (t = row * dt)
        args = (cents, active, frames, counts, flight_step(t_s), self._wall(t_s))
        if self._image_pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._image_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dvsland-tb-images")
        while len(self._image_jobs) >= 2:
            self._finish_image_job(self._image_jobs.pop(0))
        self._image_jobs.append(self._image_pool.submit(self._write_images, *args))

    @staticmethod
    def _finish_image_job(job) -> None:
        try:
            job.result()
        except Exception as exc:  # images are optional; never lose the run over them
            import warnings

            warnings.warn(f"TensorBoard images not written: {type(exc).__name__}: {exc}")

    def _write_images(self, cents, active, frames, counts, step: int, wall: float) -> None:
        """Per active descent: ``tracking/n_centroids`` and the images ``images/frame`` and
        ``images/events`` (centroids drawn as crosses) at ``step``."""
        for b, w in enumerate(self.writers):
            if not active[b]:
                continue
            c = cents[b] if cents is not None and b < len(cents) else None
            if cents is not None:
                n_c = int(np.isfinite(c).all(axis=1).sum()) if c is not None else 0
                w.add_scalar("tracking/n_centroids", n_c, step, walltime=wall)
            fw = w._get_file_writer()
            if frames is not None:
                fw.add_summary(image_summary("images/frame", draw_centroids(frame_to_rgb(frames[b]), c)), step, wall)
            if counts is not None:
                fw.add_summary(image_summary("images/events", draw_centroids(counts_to_rgb(counts[b]), c)), step, wall)

    # -------------------------------------------------------------- hparams
    def add_hparams(self, runs: List[dict], traces: Optional[Dict[str, np.ndarray]] = None,
                    extra: Optional[dict] = None) -> None:
        """One HParams row per descent: its settings (site, setting, Kp, n_bin, seed, estimator and
        ``extra``, e.g. the renderer) against its outcome (:data:`OUTCOME_METRICS`).

        Args:
            runs: the ``runs`` of results.json, in the order of ``run_labels``.
            traces: optional traces (rows, B) for ``outcome/median_abs_rel_err`` (over the steps
                with an estimate while the descent flew).
            extra: hparams shared by every run.
        """
        med = [float("nan")] * len(runs)
        if traces is not None and "d_est" in traces:
            with np.errstate(divide="ignore", invalid="ignore"):
                rel = np.abs((traces["d_est"] - traces["d_true"]) / traces["d_true"])
            ok = np.isfinite(rel) & traces["active"].astype(bool)
            med = [float(np.median(rel[ok[:, b], b])) if ok[:, b].any() else float("nan") for b in range(len(runs))]
        hps, mets = [], []
        for r, m in zip(runs, med):
            h = {"site": str(r.get("site", "")), "setting": str(r.get("label", "")), "kp_n_per_s": float(r.get("kp", 0)),
                 # the seed's index (the 64-bit seed itself is in results.json: a float64 hparam rounds it)
                 "n_bin": int(r.get("n_bin", 0)), "seed_index": int(r.get("seed_index", 0)),
                 "estimator": _estimator_label(str(r.get("estimator", "")))}
            if r.get("checkpoint"):  # a trained estimator: which weights flew
                from .checkpoint import checkpoint_text

                h["checkpoint"] = checkpoint_text(r["checkpoint"])
            h.update(extra or {})
            hps.append(h)
            thrust = r.get("max_thrust_n")
            mets.append({"outcome/success": float(r.get("outcome") == "success"),
                         "outcome/t_end_s": r.get("t_end_s"), "outcome/lowest_altitude_m": r.get("lowest_altitude_m"),
                         "outcome/v_end_mps": r.get("v_end_mps"), "outcome/fuel_used_kg": r.get("fuel_used_kg"),
                         "outcome/max_thrust_kN": None if thrust is None else thrust / 1e3,
                         "outcome/median_abs_rel_err": m})
        t_end = [float(r.get("t_end_s") or 0.0) for r in runs]
        write_hparams(self.top, self.writers[:len(runs)], hps, mets, walltime=[self._wall(t) for t in t_end],
                      step=[flight_step(t) for t in t_end])

    # -------------------------------------------------------------- end
    def close(self, result=None, table_markdown: Optional[str] = None, renderer: Optional[str] = None) -> None:
        """Write the buffered rows, the rest of ``result.traces`` (the final state), the HParams of
        every descent (when ``result``, a :class:`dvsland.sim.SimulationResult`, is given), the
        results table, and close every file (safe to call twice)."""
        if self._closed:
            return
        try:
            for job in self._image_jobs:
                self._finish_image_job(job)
            self._image_jobs = []
            if self._image_pool is not None:
                self._image_pool.shutdown(wait=True)
                self._image_pool = None
            self._flush_buffered()
            if result is not None:
                traces = result.traces
                n = traces["z_m"].shape[0] if traces else 0
                if n > self._written_rows:
                    self.write_rows({k: v[self._written_rows:] for k, v in traces.items()
                                     if k in TRACE_ROW_FIELDS or k == "t_s"}, self._written_rows)
                    self._written_rows = n
                try:
                    self.add_hparams(result.runs, traces, {"renderer": renderer} if renderer else {})
                except Exception as exc:  # never lose the run's other outputs over its HParams
                    import warnings

                    warnings.warn(f"TensorBoard HParams not written: {type(exc).__name__}: {exc}")
            if table_markdown:
                self.add_text("results", table_markdown)
        finally:
            for w in self.writers + [self.top]:
                w.flush()
                w.close()
            self._closed = True


# ------------------------------------------------------------------ other commands
def write_evaluation_tensorboard(log_dir, res, cfg_yaml: Optional[str] = None,
                                 table_text: Optional[str] = None) -> Path:
    """TensorBoard of an open-loop evaluation (``dvsland evaluate``), in a fresh ``log_dir``.

    One sub-folder per estimator and one ``truth``: tag ``divergence/site_<S>`` (1/s) at step =
    flight time in ms, so each site's chart overlays the truth and every estimator; a histogram
    ``divergence/rel_error`` of (D̂ − D)/|D| over the scored steps of sites A–G; one HParams row per
    estimator (``estimator``) with ``eval/median_abs_rel_err``, ``eval/rmse``, ``eval/coverage``,
    ``eval/within_10`` (sites A–G), ``eval/ms_per_step`` (median ms per update for the batch in the
    report's time base: process CPU time on the CPU, wall time on CUDA; hparam ``time_base``) and
    ``eval/wall_ms_per_step``, and hparam ``checkpoint`` (file and sha256 of a trained estimator's
    weights, ``-`` for none). The top folder holds the config and the printed table as text.

    Args:
        log_dir: folder (``<run_dir>/tb``).
        res: a :class:`dvsland.evaluate.EvaluationResult`.
        cfg_yaml: the resolved config as YAML.
        table_text: the printed table.

    Returns:
        The folder written (a fresh sibling if ``log_dir`` already held TensorBoard files).
    """
    log_dir = fresh_log_dir(log_dir)
    desc = res.descents
    d_true = desc.divergence
    steps = [flight_step(t) for t in desc.t_s]
    start = time.time()
    top = summary_writer(log_dir)
    writers = {}
    try:
        if cfg_yaml:
            top.add_text("config", "```yaml\n" + cfg_yaml + "\n```")
        if table_text:
            top.add_text("results", "```\n" + table_text + "\n```")
        series = {"truth": d_true, **res.d_hat}
        for name, dh in series.items():
            w = writers[name] = summary_writer(log_dir / run_folder_name(name))
            for i, site in enumerate(desc.sites):
                ok = np.nonzero(desc.valid[i] & np.isfinite(dh[i]))[0]
                for k in ok.tolist():
                    w.add_scalar(f"divergence/site_{site}", float(dh[i, k]), steps[k],
                                 walltime=start + float(desc.t_s[k]))
        hps, mets, ws = [], [], []
        from dvsland.estimators.metrics import TARGET_SITES  # below the evaluation, which fills ``res``

        from .checkpoint import checkpoint_text

        target = np.array([s in TARGET_SITES for s in desc.sites])
        for name, dh in res.d_hat.items():
            m = res.scored & target[:, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                rel = (dh[m] - d_true[m]) / np.abs(d_true[m])
            rel = rel[np.isfinite(rel)]
            if rel.size:
                add_histogram_fixed(writers[name], "divergence/rel_error", rel, 0, start)
            e = res.summary.get("estimators", {}).get(name, {})
            ag = e.get("sites_A_G", {})
            hps.append({"estimator": name, "batch_size": int(len(desc.sites)),
                        "time_base": str(e.get("time_base", res.summary.get("time_base", "CPU"))),
                        "checkpoint": checkpoint_text(e.get("checkpoint")) or "-"})
            mets.append({"eval/median_abs_rel_err": ag.get("median_abs_rel_err"), "eval/rmse": ag.get("rmse"),
                         "eval/coverage": ag.get("coverage"), "eval/within_10": ag.get("within_10"),
                         "eval/ms_per_step": e.get("ms_per_step_median"),
                         "eval/wall_ms_per_step": e.get("wall_ms_per_step_median")})
            ws.append(writers[name])
        write_hparams(top, ws, hps, mets, walltime=start, step=0)
    finally:
        for w in list(writers.values()) + [top]:
            w.close()
    return log_dir


def write_events_tensorboard(log_dir, t_us: np.ndarray, altitude_m: np.ndarray, events_per_step: Sequence[int],
                             event_frame: Optional[np.ndarray] = None, last_frame: Optional[np.ndarray] = None,
                             cfg_yaml: Optional[str] = None, summary: Optional[dict] = None) -> Path:
    """TensorBoard of ``dvsland events``, in a fresh ``log_dir``: scalars ``altitude_m`` and
    ``events/per_step`` (events per frame interval, by emission time) at step = flight time in
    ms, images ``events/frame`` (ON red, OFF blue) and ``frames/last`` (uint8, (H, W) or
    (H, W, 3)), and the config and summary as text.

    Args:
        t_us: (K + 1,) int64 frame times, µs of flight time.
        altitude_m: (K + 1,) altitudes, m.
        events_per_step: (K,) events emitted between frames k − 1 and k.

    Returns:
        The folder written.
    """
    log_dir = fresh_log_dir(log_dir)
    start = time.time()
    t_s = np.asarray(t_us, dtype=np.float64) * 1e-6
    with summary_writer(log_dir) as w:
        if cfg_yaml:
            w.add_text("config", "```yaml\n" + cfg_yaml + "\n```")
        if summary:
            import json

            w.add_text("summary", "```json\n" + json.dumps({k: v for k, v in summary.items()
                                                           if k != "events_per_step"}, indent=2) + "\n```")
        for k, (t, z) in enumerate(zip(t_s.tolist(), np.asarray(altitude_m, dtype=np.float64).tolist())):
            w.add_scalar("altitude_m", z, flight_step(t), walltime=start + t)
            if k >= 1 and k - 1 < len(events_per_step):
                w.add_scalar("events/per_step", float(events_per_step[k - 1]), flight_step(t), walltime=start + t)
        last = flight_step(t_s[-1]) if t_s.size else 0
        wall = start + (float(t_s[-1]) if t_s.size else 0.0)
        if event_frame is not None:
            w.add_image("events/frame", np.asarray(event_frame), last, walltime=wall, dataformats="HWC")
        if last_frame is not None:
            img = np.asarray(last_frame)
            w.add_image("frames/last", img, last, walltime=wall, dataformats="HWC" if img.ndim == 3 else "HW")
    return log_dir


def _estimator_label(name: str) -> str:
    """The estimator's alias where it has one (``mine`` for ``mine=pkg.mod:Class``)."""
    from dvsland.estimators.registry import estimator_label

    return estimator_label(name)

