"""Generalisation check of divergence estimators on a scene that is not a terrain: random textures
(:class:`dvsland.evaluate.ZoomTextureFrames`, or with ``--scene textures`` the procedural ground of
the ``textures`` renderer) zoomed at a known constant divergence, through the
config's emulator, and each estimator's median |relative error| and time per update.

    python scripts/measure_learned_zoom.py --estimators learned,learned[checkpoint=spiking],cmax,snn \
        --d -0.1,-0.3 --batch 18 --steps 40

B textures per divergence (seeded); the descent starts at --z0 m and follows z = z0 exp(D t);
the first --warmup steps are not scored. One torch thread.

The textures are resolved to a finite texel (about 12 m), so a faster zoom from the same --z0 also
flies lower, onto blurrier ground with fewer events: the divergences are then not compared on the
same scene. ``--z-mid M`` starts each divergence where its scored steps are centred on altitude M
(z0 = M exp(-D t_mid)), so that every divergence sees the textures at the same scales.

Any camera of the config (``--set camera.sensor=davis346``); an off-centre principal point
(``--set "camera.principal_point_px=[140.5,150.5]"``) is recorded as the dataset build records it
(:mod:`dvsland.data.crop`): a larger centred sensor is rendered and emulated, and the events of the
off-centre window are kept, so the zoom's focus of expansion is at the principal point.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import torch


def _frames(cam, d: float, B: int, steps: int, z0: float, seed: int, scene: str = "blobs"):
    if scene == "textures":  # the renderer's procedural ground (dvsland.render.textures): no texel limit
        from dvsland.render import TextureRenderer

        src = TextureRenderer([f"A~{i + 1}" for i in range(B)], cam, seed=seed).render
    else:
        from dvsland.evaluate import ZoomTextureFrames

        src = ZoomTextureFrames(B, (cam.width_px, cam.height_px), cam.fov_deg, seed=seed)
    idx = torch.arange(B)
    return [src(torch.full((B,), z0 * float(torch.exp(torch.tensor(d * 0.1 * k)))), idx) for k in range(steps + 1)]


def _events(cfg, frames, crop=None):
    from dvsland.events import EventEmulator

    emu = EventEmulator.from_config(cfg.emulator)
    emu.reset(frames[0], 0)
    out = [emu.step(f, 100_000 * k) for k, f in enumerate(frames[1:], start=1)]
    return out if crop is None else [_crop(ev, crop) for ev in out]


def _crop(ev, crop):
    """The events of the window ``crop`` (a dvsland.data.crop.Crop), in its own pixels."""
    from dvsland.events import Events

    x, y = ev.x - crop.x0, ev.y - crop.y0
    k = (x >= 0) & (x < crop.width) & (y >= 0) & (y < crop.height)
    return Events(b=ev.b[k], x=x[k], y=y[k], t=ev.t[k], p=ev.p[k])


def _run(cfg, spec: str, events, B: int, d: float, warmup: int) -> dict:
    from dvsland.estimators.base import Truth

    import dataclasses

    from dvsland.estimators import get_estimator

    name, params = spec, {}
    if "[" in spec:
        name, rest = spec.split("[", 1)
        params = dict(kv.split("=", 1) for kv in rest.rstrip("]").split(";"))
    section = getattr(cfg.estimator, name, None)
    kw = dataclasses.asdict(section) if dataclasses.is_dataclass(section) else {}
    for k, v in params.items():  # typed by the config's field; keywords the config lacks stay strings
        kw[k] = type(kw[k])(v) if k in kw else v
    kw.update(dt_s=cfg.dt_s, seed=cfg.simulation.seed, principal_point_px=cfg.camera.principal_point_px)
    est = get_estimator(name, B, (cfg.camera.width_px, cfg.camera.height_px), **kw)
    est.reset()
    z = torch.full((B,), 1.0, dtype=torch.float64)
    errs, wall, cpu, act = [], 0.0, 0.0, {}
    for k, ev in enumerate(events, start=1):
        truth = Truth(z, z * d)
        w0, c0 = time.perf_counter(), time.process_time()
        dh = est.update(ev, 100_000 * k, truth)
        wall += time.perf_counter() - w0
        cpu += time.process_time() - c0
        if k > warmup:
            errs.append(((dh.double() - d).abs() / abs(d)))
            diag = est.diagnostics()
            for key in ("spikes", "synops"):
                if key in diag:
                    act.setdefault(key, []).append(float(diag[key].double().mean()))
    e = torch.stack(errs)
    fin = torch.isfinite(e)
    return {"estimator": spec, "d": d, "median_rel_error": float(e[fin].median()) if fin.any() else float("nan"),
            "finite_share": float(fin.double().mean()), "ms_per_update_wall": 1e3 * wall / len(events),
            "ms_per_update_cpu": 1e3 * cpu / len(events),
            **{f"{k}_per_update": sum(v) / len(v) for k, v in act.items()}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="montecarlo_efference")
    ap.add_argument("--estimators", default="learned,cmax")
    ap.add_argument("--d", default="-0.1,-0.3", help="divergences, 1/s")
    ap.add_argument("--batch", type=int, default=18)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--z0", type=float, default=1000.0)
    ap.add_argument("--z-mid", type=float, default=None, metavar="M",
                    help="start each divergence so that its scored steps are centred on altitude M, m (instead of --z0)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--scene", choices=("blobs", "textures"), default="blobs",
                    help="blobs: dvsland.evaluate.ZoomTextureFrames (random blobs, ~12 m texels); textures: the "
                         "'textures' renderer (1/f fields and ellipses, every scale resolved)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from dvsland.config import load_config

    from dvsland.data.crop import recording_camera

    cfg = load_config(a.config, a.set)
    cam, crop = recording_camera(cfg.camera)
    rows = []
    for d in (float(v) for v in a.d.split(",")):
        t_mid = 0.1 * (a.warmup + 1 + a.steps) / 2  # s: the middle of the scored steps
        z0 = a.z0 if a.z_mid is None else a.z_mid * math.exp(-d * t_mid)
        events = _events(cfg, _frames(cam, d, a.batch, a.steps, z0, a.seed, a.scene), crop)
        for spec in a.estimators.split(","):
            r = _run(load_config(a.config, a.set), spec, events, a.batch, d, a.warmup)
            rows.append(r)
            r["z0_m"] = z0
            print(f"D = {d:+.2f} 1/s  {spec:32s} median |rel err| {100 * r['median_rel_error']:6.2f} %  "
                  f"finite {100 * r['finite_share']:5.1f} %  {r['ms_per_update_wall']:6.2f} ms wall "
                  f"{r['ms_per_update_cpu']:6.2f} ms CPU per update (B = {a.batch})"
                  + "".join(f"  {k[:-11]} {r[k]:.0f}/update/row" for k in r if k.endswith("_per_update")), flush=True)
    print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
