"""Callbacks around the closed loop: what :func:`dvsland.simulate` does besides flying.

A callback is any object with some of these methods (all optional, see :class:`Callback`):

- ``on_start(loop)``: once, before the first step (the run folder and config.yaml exist);
- ``on_step(loop, out)``: after every step (timed as the loop's ``logging`` stage), with the step's
  typed :class:`dvsland.sim.StepOutput`; ``loop.state`` is the :class:`dvsland.sim.LoopState`
  after the step;
- ``on_end(loop, result)``: once, after results.json and traces.npz are written, also when the
  run was interrupted (``result.status``); it may add entries to ``result.timings_s``;
- ``close()``: always, last (also after an exception), to release files.

The built-in ones are TensorBoard (:class:`TensorBoardCallback`), the progress bar
(:class:`ProgressCallback`), the figures (:class:`FiguresCallback`) and the printed summary
(:class:`SummaryCallback`); :func:`default_callbacks` picks them from ``logging``. Pass your own
to ``simulate(callbacks=[...])``.
"""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path
from typing import Callable, List, Optional, Sequence

from dvsland.config import Config, dump_config
from dvsland.report.results import RunWriteError, writes_under


class Callback:
    """Base class with no-op hooks (subclassing it is optional)."""

    def on_start(self, loop) -> None:
        pass

    def on_step(self, loop, out) -> None:
        pass

    def on_end(self, loop, result) -> None:
        pass

    def close(self) -> None:
        pass


class StepFunction(Callback):
    """Calls ``fn(loop, out)`` after every step (``simulate(on_step=fn)``)."""

    def __init__(self, fn: Callable):
        self.fn = fn

    def on_step(self, loop, out) -> None:
        self.fn(loop, out)


class TensorBoardCallback(Callback):
    """TensorBoard event files under ``run_dir/tb``: the config at the start, scalars and images
    while flying (``logging.scalar_every_s``, ``logging.image_every_s``), the summary table at the end.

    A failed write (full disk, read-only folder) is one :class:`RunWriteError` naming the folder;
    the records flushed before it stay readable, and the run's other outputs are still attempted."""

    def __init__(self, cfg: Config, run_dir: Path, run_labels: Sequence[str]):
        from dvsland.report.tensorboard import TensorBoardLogger

        lg = cfg.logging
        self.log_dir = Path(run_dir) / "tb"
        self.failed = False
        with self._writes():
            self.tb = TensorBoardLogger(self.log_dir, run_labels, cfg.dt_s, scalar_every_s=lg.scalar_every_s,
                                        image_every_s=lg.image_every_s)
            self.tb.add_config(dump_config(cfg))
        self.renderer = cfg.render.renderer

    @contextlib.contextmanager
    def _writes(self):
        try:
            with writes_under(self.log_dir):
                yield
        except RunWriteError:
            self.failed = True
            raise

    def on_step(self, loop, out) -> None:
        with self._writes():
            self.tb.on_step(out)

    def on_end(self, loop, result) -> None:
        from dvsland.report import format_table

        rend = self.renderer if result.runs and loop.stages.events is not None else None
        with self._writes():
            self.tb.close(result, format_table(result.runs, markdown=True), renderer=rend)

    def close(self) -> None:
        tb = getattr(self, "tb", None)
        if tb is None:
            return
        try:
            with self._writes():
                tb.close()
        except RunWriteError:
            if not self.failed:
                raise  # the first failure is reported; a second one while closing adds nothing


class ProgressCallback(Callback):
    """A tqdm progress bar on stderr (steps, flight time, active descents)."""

    def __init__(self, total_steps: int, batch_size: int):
        self.total, self.batch_size = int(total_steps), int(batch_size)
        self.bar = None

    def on_start(self, loop) -> None:
        from tqdm.auto import tqdm

        self.bar = tqdm(total=self.total, unit="step", desc=f"simulate B={self.batch_size}", leave=False,
                        file=sys.stderr)

    def on_step(self, loop, out) -> None:
        self.bar.update(1)
        if (out.step + 1) % 10 == 0:
            self.bar.set_postfix(t=f"{out.t_s:.1f}s", active=int(out.active.sum()))

    def on_end(self, loop, result) -> None:
        if self.bar is not None and getattr(result, "status", None) == "complete" and self.bar.n < self.total:
            self.bar.total = self.bar.n  # every descent ended before t_max: the run is done, the bar full
            self.bar.refresh()
        self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


class FiguresCallback(Callback):
    """Fig. 6-style plots per descent and the Fig. 7-style lowest-altitude chart under
    ``run_dir/figures`` after a complete run (time in ``timings_s["figures"]``)."""

    def __init__(self, cfg: Config, run_dir: Path):
        self.cfg, self.run_dir = cfg, Path(run_dir)

    def on_end(self, loop, result) -> None:
        if result.status != "complete":
            return
        from dvsland.report.figures import write_figures

        t0 = time.perf_counter()
        write_figures(self.run_dir, result.runs, result.traces, self.cfg.controller.c2,
                      self.cfg.simulation.success_altitude_m)
        from dvsland.report import paper_pattern

        if paper_pattern.applies(result.runs):  # the paper's nine sites: its Fig. 7 pattern beside this run's
            paper_pattern.paper_pattern_chart(result.runs, self.run_dir / "figures" / "paper_pattern.png",
                                              self.cfg.controller.c2, self.cfg.simulation.success_altitude_m)
        result.timings_s["figures"] = time.perf_counter() - t0


class SummaryCallback(Callback):
    """Prints the summary table, the held-step note and the wall time at the end."""

    def __init__(self, cfg: Config):
        self.cfg = cfg

    def on_end(self, loop, result) -> None:
        from dvsland.report import format_table

        runs = result.runs
        print(format_table(runs))
        from dvsland.report import paper_pattern

        if paper_pattern.applies(runs):  # the paper's nine sites: its reported pattern beside this run's
            print(paper_pattern.format_comparison(runs, self.cfg.controller.c2, self.cfg.simulation.success_altitude_m))
        held = [r for r in runs if r["held_steps"]]
        if held:
            policy = self.cfg.controller.missing_policy
            print(f"note: the filtered estimate was missing or non-negative on {sum(r['held_steps'] for r in held)} "
                  f"steps in {len(held)} of {len(runs)} runs; the controller applied missing_policy={policy!r} "
                  f"(column 'held')")
        print(f"{result.status}: {loop.B} descents, {result.n_steps} steps, wall {result.wall_time_s:.2f} s "
              f"(loop {result.timings_s.get('loop', 0.0):.2f} s; this process's CPU so far {time.process_time():.1f} s), "
              f"real-time factor {result.real_time_factor:.1f}; "
              f"output in {result.run_dir}")


def default_callbacks(cfg: Config, run_dir: Path, loop, on_step: Optional[Callable] = None) -> List[Callback]:
    """The callbacks ``logging`` asks for, in their order: TensorBoard, ``on_step``, progress bar,
    figures, summary printout (the last two only when not quiet / figures on)."""
    cbs: List[Callback] = []
    if cfg.logging.tensorboard:
        cbs.append(TensorBoardCallback(cfg, run_dir, loop.layout.run_label))
    if on_step is not None:
        cbs.append(StepFunction(on_step))
    if not cfg.logging.quiet:
        cbs.append(ProgressCallback(loop.n_steps_max, loop.B))
    if cfg.logging.figures:
        cbs.append(FiguresCallback(cfg, run_dir))
    if not cfg.logging.quiet:
        cbs.append(SummaryCallback(cfg))
    return cbs


class CallbackList(Callback):
    """Calls the hooks of several callbacks in order (missing hooks are skipped)."""

    def __init__(self, callbacks: Sequence):
        self.callbacks = list(callbacks)

    def _call(self, hook: str, *args) -> None:
        for cb in self.callbacks:
            fn = getattr(cb, hook, None)
            if fn is not None:
                fn(*args)

    def on_start(self, loop) -> None:
        self._call("on_start", loop)

    def on_step(self, loop, out) -> None:
        self._call("on_step", loop, out)

    def on_end(self, loop, result) -> None:
        self._call("on_end", loop, result)

    def close(self) -> None:
        errors = []
        for cb in self.callbacks:
            fn = getattr(cb, "close", None)
            if fn is None:
                continue
            try:
                fn()
            except Exception as exc:  # noqa: BLE001 - close them all, then report
                errors.append(exc)
        if errors:
            raise errors[0]


__all__ = ["Callback", "CallbackList", "StepFunction", "TensorBoardCallback", "ProgressCallback",
           "FiguresCallback", "SummaryCallback", "default_callbacks"]
