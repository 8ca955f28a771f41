"""The DVS pixel model: exact, batched conversion of frames to events (docs/events.md).

Model, per pixel (all arithmetic in float64):

- ``L = log(I + log_eps)``; a reference level ``L_ref`` set at :meth:`EventEmulator.reset`.
- Between two frames at t0 < t1 the pixel follows a straight line in time: in L
  (``interpolation="log"``, ESIM's model) or in I (``interpolation="linear"``, the paper's wording).
- Every crossing of ``L_ref + k θ_on`` (ON) or ``L_ref - k θ_off`` (OFF), k = 1, 2, ..., is one
  crossing at its own interpolated time; ``L_ref`` moves by one threshold per crossing. The number
  of crossings in a step is ``floor((L1 - L_ref) / θ_on + tol)`` (ON) or
  ``floor((L_ref - L1) / θ_off + tol)`` (OFF), with ``tol = 1e-9`` (:data:`LEVEL_TOL`): a change of
  exactly θ (up to 1e-9 θ of float rounding) emits. Within one step all crossings of a pixel have
  the same polarity (the path is monotone and ``L_ref`` always ends within one threshold of L).
- Refractory period: a crossing at time t is emitted only when ``t - t_last >= refractory_us``,
  ``t_last`` being the (float64) time of the pixel's last *emitted* event; a dropped crossing still
  moves ``L_ref``.
- Timestamps: computed in float64 relative to the step start, returned as int64 µs rounded to
  nearest (``floor(t + 0.5)``) and clamped into ``(t0, t1]`` (so a crossing within 0.5 µs after
  t0 is stamped t0 + 1). ``t_last`` keeps the unrounded time.

Vectorisation: per pixel the crossing count is a floor; with ``interpolation="log"`` the crossing
times of a step are equally spaced (spacing ``Δt θ / |ΔL|``), so the emitted ones are the first
crossing ``j0`` at or after ``t_last + r`` and then every ``m``-th with ``m = ceil(r / spacing)``:
closed form per pixel. With ``interpolation="linear"`` the spacing is not uniform; the refractory
rule is then resolved exactly by a loop over the crossing index k = 1..max crossings per pixel in
this step (not over pixels or events), each iteration vectorised over the pixels having >= k
crossings. Events are generated with ``repeat_interleave`` and sorted once by a packed int64 key
(batch, µs offset from the step start, pixel, polarity) from which all fields are decoded, so no
permutation gathers are needed.

Options off by default (the ideal model): per-pixel threshold mismatch ``mismatch_sigma`` (relative
Gaussian, drawn per batch element from ``seed`` at :meth:`reset`, clamped to >= 1 % of the nominal
threshold), background activity ``background_rate_hz`` (Poisson events per pixel, uniform
time and polarity, independent of the pixel state: they neither move ``L_ref`` nor start a
refractory period), and the non-ideal pixel parts of :mod:`dvsland.events.pixel_model`
(photoreceptor low-pass, shot noise, leak, hot pixels; they need ``interpolation="log"`` except
shot noise). The low-pass replaces L by its filtered level and leak/hot pixels add a per-pixel
linear drift to it, so the crossing machinery above is unchanged; shot-noise events are drawn by
thinning and reset the reference of their pixel at the end of the step.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from typing import Optional, Tuple

import numpy as np
import torch

from . import native
from . import pixel_model as pm
from .denoise import EventDenoiser
from .events import Events

_DENOISE_KEYS = ("denoise", "denoise_baf_time_us", "denoise_baf_neighbours", "denoise_refractory_us",
                 "denoise_hot_pixel_rate_hz")

#: Tolerance, in units of the threshold, when counting level crossings.
LEVEL_TOL = 1e-9

_INTERPOLATIONS = ("log", "linear")

#: Candidate pixels processed per block on CPU (cache blocking; the result does not depend on it).
#: 2^16 (512 KiB per float64 temporary) beat 2^17 on dense 128x128 frames at B = 18, one thread,
#: on a loaded 2-core machine (median 0.44-0.47 against 0.69 ms/frame in one session; the gain
#: varies with the load, from none to that).
_CPU_BLOCK = 1 << 16

#: Use the CPU-only fast paths (numpy scan/sort, blocking) on CPU tensors. Tests switch it off
#: to run the device-generic torch paths (those used on CUDA) on CPU.
CPU_FAST_PATHS = True


def _cpu_fast_path(t: torch.Tensor) -> bool:
    return CPU_FAST_PATHS and t.device.type == "cpu"


def _check_t_us(t_us, name: str = "t_us") -> int:
    if isinstance(t_us, torch.Tensor):
        if t_us.numel() != 1:
            raise ValueError(f"{name} must be a scalar, got shape {tuple(t_us.shape)}")
        t_us = t_us.item()
    try:
        tf = float(t_us)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an integer number of microseconds, got {t_us!r}") from None
    if not math.isfinite(tf) or tf != int(t_us) or abs(tf) > 2 ** 53:
        raise ValueError(f"{name} must be a finite integer number of microseconds (|t| <= 2^53), "
                         f"got {t_us!r}")
    return int(t_us)


class EventEmulator:
    """Batched DVS emulator: frames (B, H, W) of linear irradiance -> :class:`Events`.

    Args:
        threshold: ON contrast threshold θ_on in log intensity, > 0.
        threshold_off: OFF threshold θ_off, > 0; None = ``threshold``.
        refractory_us: refractory period r, µs, >= 0.
        log_eps: ε in L = log(I + ε), > 0.
        interpolation: "log" (interpolate L in time) or "linear" (interpolate I).
        device: device of the state and the output; None = device of the frames given to reset.
        mismatch_sigma: relative std. dev. of per-pixel threshold mismatch, >= 0 (0 = ideal).
        background_rate_hz: background events per pixel per second, >= 0 (0 = ideal).
        seed: seed of mismatch, background activity and the pixel-model noise (per-element CPU
            generators, results moved).
        photoreceptor_cutoff_hz: with full_irradiance, shot_noise_rate_hz, shot_noise_bright_factor,
            leak_rate_hz, leak_rate_sigma, hot_pixel_fraction and hot_pixel_rate_hz: the non-ideal
            pixel parts, see :class:`dvsland.events.pixel_model.PixelModelParams` (all off by default).
        max_events_per_step: most events one :meth:`step` may emit (all cameras together); a
            step that would emit more raises ValueError naming ``emulator.max_events_per_step``
            before its events are allocated (about 48 bytes each at the peak). None = no cap.
            After that error the emulator must be reset.

    Usage::

        emu = EventEmulator(threshold=0.1, refractory_us=15.0)
        emu.reset(frames0, t_us=0)            # (B, H, W), no events
        ev = emu.step(frames1, t_us=100_000)  # events in (0, 100000]
    """

    def __init__(self, threshold: float = 0.1, threshold_off: Optional[float] = None,
                 refractory_us: float = 15.0, log_eps: float = 1e-4, interpolation: str = "log",
                 device=None, mismatch_sigma: float = 0.0, background_rate_hz: float = 0.0,
                 seed: int = 0, photoreceptor_cutoff_hz: float = 0.0, full_irradiance: float = 1.0,
                 shot_noise_rate_hz: float = 0.0, shot_noise_bright_factor: float = 0.25,
                 leak_rate_hz: float = 0.0, leak_rate_sigma: float = 0.1,
                 hot_pixel_fraction: float = 0.0, hot_pixel_rate_hz: float = 100.0,
                 max_events_per_step: Optional[int] = 20_000_000, denoise: str = "none",
                 denoise_baf_time_us: float = 10_000.0, denoise_baf_neighbours: int = 4,
                 denoise_refractory_us: float = 1_000.0, denoise_hot_pixel_rate_hz: float = 50.0):
        def pos(name, v):
            v = float(v)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")
            return v

        def nonneg(name, v):
            v = float(v)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v}")
            return v

        self.threshold = pos("threshold", threshold)
        self.threshold_off = pos("threshold_off", threshold if threshold_off is None else threshold_off)
        self.refractory_us = nonneg("refractory_us", refractory_us)
        self.log_eps = pos("log_eps", log_eps)
        if interpolation not in _INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {_INTERPOLATIONS}, got {interpolation!r}")
        self.interpolation = interpolation
        self.mismatch_sigma = nonneg("mismatch_sigma", mismatch_sigma)
        self.background_rate_hz = nonneg("background_rate_hz", background_rate_hz)
        self.seed = int(seed)
        if max_events_per_step is not None and not int(max_events_per_step) >= 1:
            raise ValueError(f"max_events_per_step must be an integer >= 1 or None, got {max_events_per_step}")
        self.max_events_per_step = None if max_events_per_step is None else int(max_events_per_step)
        self._n_step = 0.0
        self.device = torch.device(device) if device is not None else None
        self.pixel_model = pm.PixelModelParams(
            photoreceptor_cutoff_hz=photoreceptor_cutoff_hz, full_irradiance=full_irradiance,
            shot_noise_rate_hz=shot_noise_rate_hz, shot_noise_bright_factor=shot_noise_bright_factor,
            leak_rate_hz=leak_rate_hz, leak_rate_sigma=leak_rate_sigma,
            hot_pixel_fraction=hot_pixel_fraction, hot_pixel_rate_hz=hot_pixel_rate_hz)
        if interpolation != "log":
            for name, on in (("photoreceptor_cutoff_hz", self.pixel_model.lowpass),
                             ("leak_rate_hz / hot_pixel_fraction", self.pixel_model.drift)):
                if on:
                    raise ValueError(f"{name} needs interpolation='log' (the filtered or drifting level "
                                     f"is interpolated in log space), got interpolation={interpolation!r}")
        self._shape: Optional[Tuple[int, int, int]] = None
        self.t_us: Optional[int] = None
        self._elem: dict = {}  # per-element values (set_element_params), numpy (B,)
        self._r_elem = self._bg_elem = None
        #: the front-end denoising stage applied to every step's events (None = off; .denoise)
        self.denoiser = EventDenoiser(denoise, denoise_baf_time_us, denoise_baf_neighbours,
                                      denoise_refractory_us, denoise_hot_pixel_rate_hz)
        if not self.denoiser.active:
            self.denoiser = None

    def set_element_params(self, threshold_scale=None, mismatch_sigma=None, background_rate_hz=None,
                           refractory_us=None, element_seeds=None) -> None:
        """Per-element sensor values (a Monte Carlo batch's dispersions), each (B,) or None (the
        scalar of the constructor). ``threshold_scale`` multiplies both thresholds;
        ``element_seeds`` (B,) int seed each element's mismatch map (default: ``seed``, index).
        Takes effect at the next :meth:`reset`; per-element refractory periods need
        ``interpolation="log"``."""
        import numpy as np

        vals = {}
        for name, v in (("threshold_scale", threshold_scale), ("mismatch_sigma", mismatch_sigma),
                        ("background_rate_hz", background_rate_hz), ("refractory_us", refractory_us)):
            if v is None:
                continue
            a = np.asarray(v, dtype=np.float64).reshape(-1)
            lo = 0.0 if name != "threshold_scale" else 1e-9
            if not (np.isfinite(a).all() and (a >= lo).all()):
                raise ValueError(f"{name} must be finite and >= {lo} per element, got {a}")
            vals[name] = a
        if "refractory_us" in vals and self.interpolation != "log":
            raise ValueError("per-element refractory_us needs interpolation='log'")
        if element_seeds is not None:
            vals["element_seeds"] = np.asarray(element_seeds, dtype=np.int64).reshape(-1)
        sizes = {len(a) for a in vals.values()}
        if len(sizes) > 1:
            raise ValueError(f"per-element values must all have the batch size, got sizes {sorted(sizes)}")
        self._elem = vals

    @classmethod
    def from_config(cls, cfg, device=None, seed: int = 0) -> "EventEmulator":
        """Build from a :class:`dvsland.config.schema.EmulatorConfig`."""
        return cls(threshold=cfg.threshold, threshold_off=cfg.threshold_off,
                   refractory_us=cfg.refractory_us, log_eps=cfg.log_eps,
                   interpolation=cfg.interpolation, device=device,
                   mismatch_sigma=cfg.mismatch_sigma, background_rate_hz=cfg.background_rate_hz,
                   seed=seed, **{f.name: getattr(cfg, f.name) for f in dataclasses.fields(pm.PixelModelParams)
                                 if hasattr(cfg, f.name)},
                   max_events_per_step=getattr(cfg, "max_events_per_step", 20_000_000),
                   **{k: getattr(cfg, k) for k in _DENOISE_KEYS if hasattr(cfg, k)})

    # ------------------------------------------------------------------ state
    @property
    def batch_size(self) -> int:
        return self._shape[0] if self._shape else 0

    @property
    def sensor_hw(self) -> Tuple[int, int]:
        """(H, W) of the frames given to :meth:`reset`."""
        return (self._shape[1], self._shape[2]) if self._shape else (0, 0)

    @property
    def reference(self) -> torch.Tensor:
        """(B, H, W) float64: per-pixel reference log level L_ref."""
        return self._lref

    @property
    def photoreceptor_level(self) -> torch.Tensor:
        """(B, H, W) float64: the low-pass filtered log level (without leak drift); the plain
        log level of the last frame when the photoreceptor is ideal."""
        if self._l_lp is not None:
            return self._l_lp
        if self._drift is not None:
            return self._l_prev - self._drift * float(self.t_us - self._t_reset)
        return self._l_prev

    def _check_frames(self, frames, reset: bool) -> torch.Tensor:
        if not isinstance(frames, torch.Tensor):
            frames = torch.as_tensor(frames)
        frames = frames.detach()
        if not frames.is_floating_point():
            raise ValueError(f"frames must be a floating-point tensor (linear irradiance), got {frames.dtype}")
        if frames.dim() != 3:
            raise ValueError(f"frames must have shape (B, H, W), got {tuple(frames.shape)}")
        if reset:
            if min(frames.shape) < 1:
                raise ValueError(f"frames must have B, H, W >= 1, got {tuple(frames.shape)}")
            if self.device is None:
                self.device = frames.device
        elif tuple(frames.shape) != self._shape:
            what = "batch size" if frames.shape[0] != self._shape[0] else "sensor size"
            raise ValueError(f"frames {what} changed: got shape {tuple(frames.shape)}, reset with "
                             f"{self._shape}")
        lo, hi = torch.aminmax(frames)
        lo, hi = torch.stack((lo, hi)).tolist()  # one sync
        if not (lo >= 0 and hi < math.inf):
            if math.isnan(lo) or math.isnan(hi):
                raise ValueError("frames contain NaN; irradiance must be finite and >= 0")
            if hi == math.inf or lo == math.inf:
                raise ValueError("frames contain inf; irradiance must be finite and >= 0")
            raise ValueError(f"frames contain negative irradiance (min {lo}); irradiance must be >= 0")
        self._range_new = (lo, hi)
        # always a private float64 copy: it becomes state, and may be modified in place
        spare = None if reset else self._take_spare(frames)
        if spare is not None:
            return spare.copy_(frames)
        return frames.to(device=self.device, dtype=torch.float64, copy=True)

    def _take_spare(self, frames: torch.Tensor) -> Optional[torch.Tensor]:
        """The level buffer of two steps ago, for the new frames' copy, when nothing outside the
        emulator holds it (no reference, no view, no numpy array) and it fits; else None. On CPU a
        fresh (B, H, W) float64 tensor per step costs more in page faults than the copy itself."""
        spare, self._spare = getattr(self, "_spare", None), None
        if spare is None or tuple(spare.shape) != tuple(frames.shape):
            return None
        try:  # 2 = the tensor's own reference + the temporary storage object
            free = sys.getrefcount(spare) == 2 and torch._C._storage_Use_Count(spare.untyped_storage()._cdata) == 2
        except Exception:  # private API missing: never reuse
            free = False
        return spare if free else None

    def _draw_mismatch(self, B: int, H: int, W: int) -> None:
        self._r_elem = self._bg_elem = None
        if self._elem:
            return self._draw_elements(B, H, W)
        if self.mismatch_sigma == 0:
            self._th_scalar = True
            self._th_on = self.threshold
            self._th_off = self.threshold_off
            self._th_min = min(self.threshold, self.threshold_off)
            return
        sig = torch.full((B,), self.mismatch_sigma, dtype=torch.float64)
        self._set_threshold_maps(self._mismatch_maps(B, H, W, sig, None))

    def _mismatch_maps(self, B: int, H: int, W: int, sig: torch.Tensor, seeds) -> torch.Tensor:
        """(B, 2, H, W) float64 CPU relative ON/OFF threshold maps, 1 + sig[b] N(0, 1) clamped at
        0.01, element b drawn from its own seed (``seeds[b]``, or one derived from ``self.seed``
        and b), so its map does not depend on B; all ones where sig[b] is 0. Reset only."""
        maps = torch.ones(B, 2, H, W, dtype=torch.float64)
        for b in range(B):
            if float(sig[b]) > 0:
                sd = int(seeds[b]) if seeds is not None else (self.seed * 1_000_003 + b) % (2 ** 63)
                g = torch.Generator(device="cpu").manual_seed(sd)
                maps[b] = (1.0 + float(sig[b]) * torch.randn(2, H, W, generator=g, dtype=torch.float64)).clamp_(min=0.01)
        return maps

    def _set_threshold_maps(self, maps: torch.Tensor) -> None:
        """Per-pixel thresholds from relative maps (B, 2, H, W): ON/OFF maps, their minimum and
        the candidate bounds of _candidates (computed once)."""
        maps = maps.to(self.device)
        self._th_scalar = False
        self._th_on = self.threshold * maps[:, 0]
        self._th_off = self.threshold_off * maps[:, 1]
        self._th_min = min(float(self._th_on.min()), float(self._th_off.min()))
        shrink = 1.0 - 2 * LEVEL_TOL
        self._cand_bounds = (self._th_on * shrink, self._th_off * -shrink)

    def _draw_elements(self, B: int, H: int, W: int) -> None:
        """Threshold maps (B, H, W) from per-element scale, mismatch sigma and seeds; per-element
        refractory periods and background rates."""
        e = self._elem
        n = next(len(a) for a in e.values())
        if n != B:
            raise ValueError(f"per-element values are for B={n}, the frames have B={B}")
        sig = e.get("mismatch_sigma")
        sig = torch.full((B,), self.mismatch_sigma, dtype=torch.float64) if sig is None else torch.from_numpy(sig)
        maps = self._mismatch_maps(B, H, W, sig, e.get("element_seeds"))
        scale = e.get("threshold_scale")
        if scale is not None:
            maps *= torch.from_numpy(scale)[:, None, None, None]
        self._set_threshold_maps(maps)
        r = e.get("refractory_us")
        self._r_elem = None if r is None else torch.from_numpy(r).to(self.device)
        bg = e.get("background_rate_hz")
        self._bg_elem = None if bg is None else bg

    def _bg_active(self) -> bool:
        return bool((self._bg_elem > 0).any()) if self._bg_elem is not None else self.background_rate_hz > 0

    def reset(self, frames: torch.Tensor, t_us: int) -> None:
        """Start (or restart) all pixels: L_ref = log(frames + eps) at time ``t_us``; no events.

        Args:
            frames: (B, H, W) floating, linear irradiance, finite, >= 0.
            t_us: int, µs.
        """
        t_us = _check_t_us(t_us)
        f = self._check_frames(frames, reset=True)
        self._shape = tuple(int(s) for s in f.shape)
        self._range = self._range_new  # (min, max) irradiance of the previous frame
        B, H, W = self._shape
        self._lref = torch.log(f + self.log_eps)
        self._l_prev = self._lref.clone()
        self._i_prev = f if self.interpolation == "linear" else None
        self._t_last = torch.full(self._shape, -math.inf, dtype=torch.float64, device=self.device)
        self._draw_mismatch(B, H, W)
        self._layout = _KeyLayout(B, H, W, self.device)
        self.t_us = t_us
        self._reset_pixel_model(B, H, W, t_us)
        if self.denoiser is not None:
            self.denoiser.reset(B, H, W, t_us, self.device)

    def _reset_pixel_model(self, B: int, H: int, W: int, t_us: int) -> None:
        """Per-element noise streams and the low-pass / drift state (see :mod:`.pixel_model`)."""
        pmp = self.pixel_model
        self._bg_gens = pm.element_rngs(self.seed, B, pm.TAG_BACKGROUND) if self._bg_active() else None
        self._shot_gens = pm.element_rngs(self.seed, B, pm.TAG_SHOT) if pmp.shot else None
        # the filtered log level (without drift); None = ideal photoreceptor
        self._l_lp = self._lref.clone() if pmp.lowpass else None
        self._t_reset = t_us
        self._drift = None  # (B, H, W) float64 drift of the level, log units per µs
        #: (B, H, W): per-pixel leak rate (Hz, hot pixels included), hot-pixel mask, initial phase
        self.leak_rate_hz_map, self.hot_pixels, self.leak_phase = None, None, None
        if pmp.drift:
            rate, hot, phase = pm.draw_leak_state(pm.element_generators(self.seed, B, pm.TAG_LEAK),
                                                  (B, H, W), pmp)
            rate, hot, phase = rate.to(self.device), hot.to(self.device), phase.to(self.device)
            self.leak_rate_hz_map, self.hot_pixels, self.leak_phase = rate, hot, phase
            self._drift = rate.mul(self._th_on).mul_(1e-6)
            self._lref.sub_(phase.mul(self._th_on))  # start u_i thresholds below the level

    # ------------------------------------------------------------------- step
    def step(self, frames: torch.Tensor, t_us: int) -> Events:
        """Advance to ``t_us`` with new frames; return the events in (t_prev, t_us], sorted by (b, t).

        Args:
            frames: (B, H, W) floating, linear irradiance, finite, >= 0, same shape as at reset.
            t_us: int µs, > the previous time.

        Returns:
            :class:`Events` on the emulator's device, sorted by (b, t), ties by row-major pixel
            (exact ties of background events with pixel events: by pixel, then OFF after ON).
        """
        if self._shape is None:
            raise RuntimeError("EventEmulator.step called before reset(frames, t_us)")
        t1 = _check_t_us(t_us)
        if t1 <= self.t_us:
            raise ValueError(f"t_us must increase: got {t1} after {self.t_us}")
        f1 = self._check_frames(frames, reset=False)
        t0 = self.t_us
        dt = float(t1 - t0)
        layout = self._layout
        b_shift = layout.b_shift(t1 - t0)  # ValueError if the key would overflow
        dev = self.device
        self._n_step = 0.0
        # crossings are spaced dt θ / |L1 - L0| apart; |L1 - L0| is at most the log range of
        # both frames, so when dt θ_min / r exceeds it the spacing alone never drops a crossing
        lo = min(self._range[0], self._range_new[0])
        hi = max(self._range[1], self._range_new[1])
        l_span = math.log(hi + self.log_eps) - math.log(lo + self.log_eps)
        r = self.refractory_us if self._r_elem is None else float(self._r_elem.max())
        self._spacing_may_bind = r > 0 and dt * self._th_min <= r * l_span * (1 + 1e-6)
        pmp = self.pixel_model
        if pmp.lowpass or pmp.drift:  # the frame range no longer bounds the level's change
            self._spacing_may_bind = r > 0
        alpha = shot = None
        if pmp.lowpass:
            alpha = pm.photoreceptor_alpha(f1, dt * 1e-6, pmp.photoreceptor_cutoff_hz, pmp.full_irradiance)
        if pmp.shot:  # drawn now: the rate needs the irradiance (f1 becomes L1 below)
            shot = self._shot_noise(f1, t1 - t0, b_shift)

        if self.interpolation == "log":
            l1 = f1.add_(self.log_eps).log_()  # f1 is a private copy
        else:
            l1 = torch.log(f1 + self.log_eps)
        if alpha is not None:  # new state, written over L1 (a private copy); shared with l1
            # until the drift (out of place) below
            self._l_lp = torch.lerp(self._l_lp, l1, alpha, out=l1)
            del alpha
        if self._drift is not None:
            el = float(t1 - self._t_reset)
            l1 = l1.add(self._drift, alpha=el) if pmp.lowpass else l1.add_(self._drift, alpha=el)
        # per event int64 sort keys (see _KeyLayout) of the pixels; updates L_ref and t_last
        pixel_order = self._native_pixel_path(l1)
        if pixel_order:  # the compiled one-pass kernel (when built): the same keys and state, in pixel order
            keys = self._native_pixel_events(l1, t0, dt, b_shift)
        else:
            keys = self._scene_keys(l1, f1, t0, dt, b_shift)

        # the old level buffer becomes the next step's frame copy where nothing else can hold it
        recycle = self.interpolation == "log" and not (pmp.lowpass or pmp.drift)
        self._spare = self._l_prev if recycle else None
        self._l_prev = l1
        self._range = self._range_new
        if self.interpolation == "linear":
            self._i_prev = f1
        self.t_us = t1

        if self._bg_active():
            bg = self._background(b_shift, dt)
            keys, pixel_order = (bg if keys is None else torch.cat((keys, bg))), False
        shot_keys = None
        if shot is not None:
            flat, shot_keys = shot
            if flat.numel():
                # a shot event resets its pixel's reference to the current level (as v2e)
                self._lref.view(-1).index_copy_(0, flat, l1.view(-1).index_select(0, flat))
        if keys is None or keys.numel() == 0:
            keys, shot_keys = shot_keys, None
        if keys is None or keys.numel() == 0:
            ev = Events.empty(dev)
        else:
            ev = layout.sort_decode(keys, b_shift, t0, sorted_keys=shot_keys, pixel_order=pixel_order)
        return ev if self.denoiser is None else self.denoiser(ev, t1)

    def _shot_noise(self, f1: torch.Tensor, dt_us: int, b_shift: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """This step's shot-noise events (:func:`pixel_model.draw_shot_noise`, irradiance ``f1``
        (B, H, W) float64): flat pixel indices (N,) int64 and sort keys (N,) int64 (see _KeyLayout),
        both in (b, t, pixel) order, so the keys come sorted (merged into the scene's by the compiled
        kernels, sorted with them by :func:`_sort_values` otherwise). On CPU with the compiled
        kernels, thinned and keyed in one pass (the same events)."""
        lay, pmp = self._layout, self.pixel_model
        xb, yb = lay.y_shift - 1, lay.t_shift - lay.y_shift
        mod = native.kernels() if _cpu_fast_path(f1) else None
        if mod is not None:
            B, H, W = self._shape
            k = pmp.shot_noise_bright_factor
            r_max = pmp.shot_noise_rate_hz * max(1.0, k)
            slot, elem, u = pm.sorted_candidates(self._shot_gens, r_max, H, W, dt_us, xb, yb)
            a = pmp.shot_noise_rate_hz / r_max  # as draw_shot_noise: q = a + a (k - 1) min(1, I / I_full)
            flat, keys = mod.shot_keys(slot, elem, u, f1.reshape(-1), H, W, xb, yb,
                                                 1.0 / pmp.full_irradiance, a, a * (k - 1.0),
                                                 a * min(1.0, k) < 1.0, lay.t_shift, b_shift)
            return flat, keys
        flat, slot, elem, off = pm.draw_shot_noise(self._shot_gens, f1, dt_us, pmp, xb, yb)
        # slot = t_rel - 1 | y | x (see _KeyLayout): drawn in (b, t, pixel) order, so the keys are sorted
        keys = slot.add_(1 << (lay.t_shift - 1)).bitwise_left_shift_(1).bitwise_or_(
            elem.bitwise_left_shift_(b_shift)).bitwise_or_(off.to(torch.int64))
        return flat, keys

    def _scene_keys(self, l1: torch.Tensor, f1: torch.Tensor, t0: int, dt: float, b_shift: int
                    ) -> Optional[torch.Tensor]:
        """Keys of the pixels' events (None if none): candidate scan, then :meth:`_pixel_events`
        per block of candidates; moves L_ref and t_last."""
        d = torch.sub(l1, self._lref, out=self._scratch(l1))  # scratch, overwritten below
        # candidate pixels (A,): a superset of those with >= 1 crossing (exact counts follow)
        if self._th_scalar:
            act = _candidates(d, self._th_on, self._th_off, 1.0 - 2 * LEVEL_TOL)  # sync
        else:
            act = _candidates_map(d, *self._cand_bounds)
        del d
        if act.numel() == 0:
            return None
        # on CPU, blocks of candidates small enough to keep the ~40 per-pixel temporaries in
        # cache (faster at large B); one block on other devices
        block = _CPU_BLOCK if _cpu_fast_path(act) else act.numel()
        parts = [self._pixel_events(act[i:i + block], l1, f1, t0, dt, b_shift)
                 for i in range(0, act.numel(), block)]
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def _native_pixel_path(self, l1: torch.Tensor) -> bool:
        """Whether this step's pixels go through the compiled kernel: built (DVSLAND_NATIVE_SORT,
        :mod:`.native`), CPU, log interpolation (scalar or per-pixel thresholds, scalar or
        per-element refractory periods)."""
        return (_cpu_fast_path(l1) and self.interpolation == "log" and l1.dtype == torch.float64
                and native.kernels() is not None)

    def _native_pixel_events(self, l1: torch.Tensor, t0: int, dt: float, b_shift: int) -> torch.Tensor:
        """Keys of the pixels' events from :func:`dvsland.events.native` ``pixel_events``; moves
        L_ref and t_last (the same as the candidate scan and :meth:`_pixel_events`)."""
        layout = self._layout
        table = layout.pixel_table(b_shift)
        n_out = torch.zeros(1, dtype=torch.float64)
        cap = -1 if self.max_events_per_step is None else int(self.max_events_per_step)
        none = l1.new_empty(0)
        if self._th_scalar:
            th_on, th_off, on_map, off_map = float(self._th_on), float(self._th_off), none, none
        else:
            th_on, th_off = 0.0, 0.0
            on_map, off_map = self._th_on.reshape(-1).contiguous(), self._th_off.reshape(-1).contiguous()
        r_elem = none if self._r_elem is None else self._r_elem.to(torch.float64).contiguous()
        keys = native.load().pixel_events(l1.reshape(-1), self._lref.view(-1), self._l_prev.reshape(-1),
                                          self._t_last.view(-1), table, th_on, th_off, on_map, off_map,
                                          float(self.refractory_us), r_elem, layout.H * layout.W, float(t0),
                                          float(dt), bool(self._spacing_may_bind), layout.t_shift, cap, n_out)
        self._count_events(n_out)  # ValueError above the cap (the kernel then emitted nothing)
        return keys

    def _scratch(self, like: torch.Tensor) -> torch.Tensor:
        """A (B, H, W) float64 work buffer kept across steps: a fresh full-size tensor per step
        costs more in page faults (on CPU, above glibc's mmap threshold) than the arithmetic."""
        buf = getattr(self, "_scratch_buf", None)
        if buf is None or buf.shape != like.shape or buf.device != like.device:
            buf = self._scratch_buf = torch.empty_like(like)
        return buf

    def _pixel_events(self, act, l1, f1, t0: int, dt: float, b_shift: int) -> torch.Tensor:
        """Events of the candidate pixels ``act`` (A,) as sort keys; moves L_ref and t_last.
        A method of its own so that its (A,)- and (N,)-sized temporaries die on return."""
        layout = self._layout
        th_on, th_off = self._th_on, self._th_off
        r = self.refractory_us
        if self._r_elem is not None:  # per element: (A,) gathered per pixel
            r = self._r_elem.index_select(0, torch.div(act, l1[0].numel(), rounding_mode="floor"))
        lref_flat = self._lref.view(-1)
        lref_a = lref_flat.index_select(0, act)
        l1_a = l1.view(-1).index_select(0, act)
        d_a = l1_a - lref_a  # bit-identical to d[act], cheaper than a gather
        if self._th_scalar and th_on == th_off:
            n_a = torch.floor((d_a / th_on).abs_().add_(LEVEL_TOL))
            th_a = torch.sign(d_a).mul_(th_on)  # d_a != 0 for candidates
        else:
            th_on_a, th_off_a = _take(th_on, act), _take(th_off, act)
            n_on = torch.floor(d_a / th_on_a + LEVEL_TOL).clamp_(min=0)
            n_off = torch.floor(-d_a / th_off_a + LEVEL_TOL).clamp_(min=0)
            n_a = n_on + n_off  # at most one of them > 0
            th_a = torch.where(d_a > 0, th_on_a, -th_off_a)  # signed step of L_ref
        tl_flat = self._t_last.view(-1)
        tl_a = tl_flat.index_select(0, act).sub_(t0)  # relative, <= 0 or -inf
        code_a = layout.pixel_key(act, torch.signbit(th_a), b_shift)
        t_shift = layout.t_shift
        if self.interpolation == "log":
            cnt, first, step_us, tlast_new = _emitted_log(
                n_a, th_a, lref_a, self._l_prev.view(-1).index_select(0, act), l1_a, dt, tl_a, r,
                self._spacing_may_bind)
            self._count_events(cnt)  # before any per-event allocation
            # cnt holds whole numbers: compared as float64, converted only for the multi pixels
            sel = _nonzero_1d(cnt > 0)  # pixels with >= 1 emitted event (sync)
            all_sel = sel.numel() == act.numel()
            # the first event of every pixel with cnt >= 1 (no per-event gather) ...
            f_sel = first if all_sel else first.index_select(0, sel)
            t_first = f_sel.add(0.5).floor_().clamp_(1.0, dt).to(torch.int64)
            parts = [t_first.bitwise_left_shift_(t_shift).add_(code_a if all_sel else code_a.index_select(0, sel))]
            # ... then the further events of the pixels with cnt >= 2
            multi = _nonzero_1d(cnt > 1)
            if multi.numel() > 0:
                parts.append(_extra_keys(multi, cnt, first, step_us, code_a, dt, t_shift))
            keys = torch.cat(parts) if len(parts) > 1 else parts[0]
        else:
            self._count_events(n_a)  # upper bound (refractory only drops), before the per-crossing loop
            seg, tau, cnti, tlast_new = _emitted_linear(
                n_a, th_a, lref_a, self._i_prev.view(-1).index_select(0, act),
                f1.view(-1).index_select(0, act), dt, tl_a, r, self.log_eps)
            sel = _nonzero_1d(cnti > 0)
            all_sel = sel.numel() == act.numel()
            t_rel = torch.floor(tau.add_(0.5)).clamp_(1.0, dt).to(torch.int64)
            keys = code_a.index_select(0, seg).add_(t_rel << t_shift)
        # state: the reference moves by one threshold per crossing (emitted or dropped);
        # the last emitted time where >= 1 event was emitted
        lref_flat.scatter_(0, act, lref_a.addcmul_(n_a, th_a))
        if all_sel:
            tl_flat.scatter_(0, act, tlast_new.add_(t0))
        else:
            tl_flat.scatter_(0, act.index_select(0, sel), tlast_new.index_select(0, sel).add_(t0))
        return keys

    def _count_events(self, counts: torch.Tensor) -> None:
        """Add (A,) per-pixel event counts to this step's total; ValueError above the cap."""
        if self.max_events_per_step is None:
            return
        self._n_step += float(counts.sum())  # one sync per block
        if self._n_step > self.max_events_per_step:
            raise ValueError(
                f"emulator.max_events_per_step: this step would emit at least {self._n_step:.4g} events, above "
                f"the cap of {self.max_events_per_step} (about {self._n_step * 48 / 2 ** 30:.3g} GiB at 48 B per "
                f"event); raise emulator.threshold or lower the batch / sensor size, or raise the cap if the "
                f"memory is there. The emulator must be reset after this error")

    def _background(self, b_shift: int, dt: float) -> torch.Tensor:
        """Sort keys of background events: Poisson count per element, uniform pixel, time
        (integer µs in [1, dt]) and polarity; drawn on CPU from each element's generator."""
        B, H, W = self._shape
        if self._bg_elem is not None:  # per-element rates: each element's own stream and rate
            parts = [pm.draw_background([self._bg_gens[b]], float(self._bg_elem[b]), H * W, int(dt), self.device)
                     for b in range(B)]
            flat = torch.cat([p[0] + b * H * W for b, p in enumerate(parts)])
            t_rel = torch.cat([p[1] for p in parts])
            off = torch.cat([p[2] for p in parts])
        else:
            flat, t_rel, off = pm.draw_background(self._bg_gens, self.background_rate_hz, H * W, int(dt), self.device)
        self._count_events(torch.tensor([float(flat.numel())]))
        return self._layout.pixel_key(flat, off, b_shift).add_(t_rel << self._layout.t_shift)


# ---------------------------------------------------------------------------- helpers
def _emitted_log(n_a, th_a, lref_a, l0_a, l1_a, dt, tl_a, r, spacing_may_bind: bool = True):
    """Log interpolation: the emitted crossings of each pixel in closed form.

    Args (A candidate pixels, (A,) float64): crossing count n_a (may be 0), signed threshold
    th_a (+θ_on or -θ_off), L_ref, L0, L1; dt step length (µs); tl_a last emitted time relative
    to the step start (<= 0, -inf = never); r refractory period (µs); ``spacing_may_bind``
    False when the caller knows every spacing is >= r (skips that test).

    Returns (A,) float64: cnt emitted events, first the time of the first one and step the
    time between consecutive ones (µs after the step start), tlast the time of the last one
    (first, step and tlast are meaningful where cnt > 0).

    Crossing j (1..n) is at ``tau_j = base + j * spacing`` (equally spaced). Emitted: the first
    j0 >= 1 with tau_j0 >= tl + r, then every m-th, m = max(1, ceil(r / spacing)); so
    cnt = max(0, floor((n - j0) / m) + 1). (j0 and m stay float64: no overflow for huge values.)
    """
    # whenever n > 0, L moved in the direction of th_a (dl != 0); candidates with n = 0 may have
    # dl = 0 and produce inf/NaN below, which the nan_to_num on cnt turns into cnt = 0
    dl = l1_a - l0_a
    scale = dt / dl
    spacing = th_a * scale  # µs between crossings, > 0
    base = (lref_a - l0_a).mul_(scale)
    # without refractory: all n crossings
    cnt = n_a
    first = base + spacing
    step = spacing
    r_t = r if isinstance(r, torch.Tensor) else None  # per-pixel refractory (A,) or a scalar
    if r_t is not None or r > 0:
        # the refractory rule can only bind where crossings are closer than r, or the first
        # one is within r of the last emitted event: apply the closed form there only
        near = first < tl_a + r
        need = _nonzero_1d((spacing < r) | near if spacing_may_bind else near)
        if need.numel() > 0:
            cnt, first, step = cnt.clone(), first.clone(), step.clone()
            sp, bs = spacing.index_select(0, need), base.index_select(0, need)
            nn = n_a.index_select(0, need)
            if r_t is not None:
                r = r_t.index_select(0, need)
            j0 = torch.ceil(tl_a.index_select(0, need).sub_(bs).add_(r).div_(sp)).clamp_(min=1.0)
            m = torch.ceil(r / sp).clamp_(min=1.0)
            c = torch.floor((nn - j0).div_(m)).add_(1.0).clamp_(min=0.0).nan_to_num_(0.0, 0.0, 0.0)
            cnt.index_copy_(0, need, c)
            first.index_copy_(0, need, bs.addcmul_(j0, sp))
            step.index_copy_(0, need, m.mul_(sp))
    tlast = first.addcmul(cnt - 1, step)
    return cnt, first, step, tlast


def _emitted_linear(n_a, th_a, lref_a, i0_a, i1_a, dt, tl_a, r, eps):
    """Linear irradiance interpolation: crossing times are not equally spaced.

    Same arguments and returns as :func:`_emitted_log`, with I0, I1 in place of L0, L1 and the
    log epsilon ``eps``. Crossing j is at ``tau_j = dt (exp(L_ref + j θ) - eps - I0) / (I1 - I0)``.
    Without refractory every crossing is emitted (closed form). With refractory the greedy rule
    is applied exactly by a loop over the crossing index k (1..max crossings of a pixel in this
    step), vectorised over the pixels having >= k crossings (pixels sorted by count, so those
    are a prefix).
    """
    di = i1_a - i0_a
    dev = n_a.device

    def tau_of(s, jj):
        x = dt * (torch.exp(lref_a[s] + jj * th_a[s]) - eps - i0_a[s]) / di[s]
        return torch.nan_to_num(x, nan=dt, posinf=dt, neginf=0.0)

    ni = n_a.to(torch.int64)
    A = ni.numel()
    if r == 0:
        seg, i = _segments(ni)
        tau = tau_of(seg, (i + 1).to(torch.float64))
        return seg, tau, ni, tau_of(torch.arange(A, device=dev), n_a)
    order = torch.sort(ni, descending=True, stable=True).indices
    n_sorted = ni[order]
    kmax = int(n_sorted[0])
    # prefix sizes P_k = #(n >= k), k = 1..kmax
    sizes = torch.bincount(n_sorted, minlength=kmax + 1).flip(0).cumsum(0).flip(0)[1:].tolist()
    tl = tl_a[order].clone()
    emit_parts, seg_parts, tau_parts = [], [], []
    for k, P in enumerate(sizes, start=1):
        s = order[:P]
        tau_k = tau_of(s, torch.full((P,), float(k), dtype=torch.float64, device=dev))
        e = tau_k >= tl[:P] + r
        tl[:P] = torch.where(e, tau_k, tl[:P])
        emit_parts.append(e)
        seg_parts.append(s)
        tau_parts.append(tau_k)
    if not emit_parts:
        empty = torch.empty(0, dtype=torch.int64, device=dev)
        return empty, empty.to(torch.float64), torch.zeros_like(ni), tl_a
    emit = torch.cat(emit_parts)
    seg = torch.cat(seg_parts)[emit]
    tau = torch.cat(tau_parts)[emit]
    cnt = torch.bincount(seg, minlength=A)
    tlast = torch.empty(A, dtype=torch.float64, device=dev)
    tlast[order] = tl
    return seg, tau, cnt, tlast


def _take(th, idx):
    """Threshold of the pixels ``idx``: a float, or a (B, H, W) map gathered."""
    if isinstance(th, torch.Tensor):
        return th.reshape(-1)[idx]
    return torch.full(idx.shape, th, dtype=torch.float64, device=idx.device)


def _extra_keys(multi, cnt, first, step_us, code_a, dt: float, t_shift: int) -> torch.Tensor:
    """Keys of the 2nd, 3rd, ... events of the pixels ``multi`` (indices into the candidates):
    event i of pixel a is at first[a] + i * step_us[a], i = 1..cnt[a]-1. A function of its own
    so that its per-event temporaries are freed on return; in-place ops keep the number of
    fresh (N,) allocations (page faults dominate at tens of millions of events) low."""
    reps = cnt.index_select(0, multi).to(torch.int64).sub_(1)  # cnt: (A,) float64 whole numbers
    seg = multi.repeat_interleave(reps)  # candidate index per event
    start = torch.cumsum(reps, 0).sub_(reps)
    i = torch.arange(1, seg.numel() + 1, device=seg.device).sub_(start.repeat_interleave(reps))
    del start, reps
    tau = step_us.index_select(0, seg).mul_(i)
    del i
    t_rel = tau.add_(first.index_select(0, seg)).add_(0.5).floor_().clamp_(1.0, dt).to(torch.int64)
    del tau
    return t_rel.bitwise_left_shift_(t_shift).add_(code_a.index_select(0, seg))


def _candidates(d: torch.Tensor, th_on, th_off, shrink: float) -> torch.Tensor:
    """Flat indices (int64) of pixels with d >= th_on * shrink or d <= -th_off * shrink.

    ``th_on``/``th_off`` are floats or (B, H, W) maps. On CPU with scalar thresholds this runs
    in numpy (several times faster than the torch comparison + nonzero on 2 cores) and may
    overwrite ``d`` (a scratch buffer)."""
    scalar = not isinstance(th_on, torch.Tensor)
    if scalar and _cpu_fast_path(d):
        dn = d.numpy().reshape(-1)
        lo_on, lo_off = th_on * shrink, th_off * shrink
        if lo_on == lo_off:
            mask = np.greater_equal(np.abs(dn, out=dn), lo_on)  # d is scratch: abs in place
        else:
            mask = (dn >= lo_on) | (dn <= -lo_off)
        return torch.from_numpy(np.flatnonzero(mask))
    mask = (d >= th_on * shrink) | (d <= -th_off * shrink) if not scalar or th_on != th_off \
        else d.abs() >= th_on * shrink
    return _nonzero_1d(mask.reshape(-1))


def _candidates_map(d: torch.Tensor, lo_on: torch.Tensor, hi_off: torch.Tensor) -> torch.Tensor:
    """Flat indices of pixels with d >= lo_on or d <= hi_off (per-pixel bound maps, (B, H, W))."""
    if _cpu_fast_path(d):
        dn = d.numpy().reshape(-1)
        mask = np.greater_equal(dn, lo_on.numpy().reshape(-1))
        mask |= np.less_equal(dn, hi_off.numpy().reshape(-1))
        return torch.from_numpy(np.flatnonzero(mask))
    return _nonzero_1d(((d >= lo_on) | (d <= hi_off)).reshape(-1))


def _nonzero_1d(mask: torch.Tensor) -> torch.Tensor:
    """Indices (int64) of the True entries of a 1-D bool tensor. On CPU numpy's flatnonzero is
    about 6x faster than torch.nonzero (measured on 295k elements)."""
    if _cpu_fast_path(mask):
        return torch.from_numpy(np.flatnonzero(mask.numpy()))
    return torch.nonzero(mask).squeeze(1)


def _merge_sorted(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Merge two sorted 1-D int64 CPU tensors into one sorted tensor (O(len(a) log len(b)) searches
    and two scatters instead of a sort of both; equal keys are equal values, so order among them
    does not matter)."""
    an, bn = a.numpy(), b.numpy()
    n = an.size + bn.size
    pos_a = np.searchsorted(bn, an)
    pos_a += np.arange(an.size)
    out = np.empty(n, dtype=np.int64)
    from_b = np.ones(n, dtype=bool)
    from_b[pos_a] = False
    out[pos_a] = an
    out[from_b] = bn
    return torch.from_numpy(out)


def _sort_values(keys: torch.Tensor) -> torch.Tensor:
    """The int64 keys sorted (a new tensor, or ``keys`` sorted in place). On CPU with one torch
    thread torch.sort (a radix sort: 182 k keys 2.7 against numpy's 8.3 ms of CPU); with more
    threads numpy's single-threaded sort in place, because torch's parallel sort of one 1-D
    tensor took 275 ms wall (186 ms CPU) against 7 ms with one thread on this shared 2-core
    machine (load 6.6)."""
    if _cpu_fast_path(keys) and torch.get_num_threads() > 1:
        keys.numpy().sort()
        return keys
    return torch.sort(keys).values


def _segments(cnt: torch.Tensor):
    """For counts (A,) int64: segment id (N,) and index within the segment (N,), N = sum(cnt)."""
    seg = torch.repeat_interleave(cnt)
    start = torch.cumsum(cnt, 0).sub_(cnt)
    return seg, torch.arange(seg.numel(), device=cnt.device).sub_(start.index_select(0, seg))


class _KeyLayout:
    """The int64 sort key of an event: | b | t_rel | y | x | off |, most significant first.

    t_rel = t - t0 in [1, dt] µs, off = 1 for OFF events. Sorting the keys orders events by
    (b, t), then row-major pixel, and every field decodes with shifts and masks, so the sort is
    of values only (no permutation, no gathers) and its result is unique, hence the same on any
    device. The sort is :func:`_sort_values` (torch.sort, or numpy's with several CPU threads),
    or with the compiled kernels (:mod:`.native`) their radix sort fused with the decoding
    and the merge of the already sorted shot-noise keys. The (b, y, x) bits come from a table of
    B * H * W codes built at reset.
    """

    def __init__(self, B: int, H: int, W: int, device):
        self.B, self.H, self.W = B, H, W
        xb = max(1, (W - 1).bit_length())
        yb = max(1, (H - 1).bit_length())
        self.bb = max(1, (B - 1).bit_length())
        self.y_shift = 1 + xb
        self.t_shift = 1 + xb + yb
        self.x_mask, self.y_mask = (1 << xb) - 1, (1 << yb) - 1
        if self.t_shift + self.bb > 62:
            raise ValueError(f"sensor and batch too large for the packed event key: B={B}, H={H}, W={W}")
        yy = torch.arange(H, device=device).view(1, H, 1)
        xx = torch.arange(W, device=device).view(1, 1, W)
        bb = torch.arange(B, device=device).view(B, 1, 1)
        # per flat pixel (b, y, x): b in the high 31 bits, (y << y_shift) | (x << 1) in the low 32
        self.code = ((bb << 32) | (yy << self.y_shift) | (xx << 1)).reshape(-1)
        self._table, self._table_shift = None, None

    def b_shift(self, dt_us: int) -> int:
        """Bit position of b for a step of ``dt_us``; ValueError if the key needs > 63 bits."""
        shift = self.t_shift + int(dt_us).bit_length()
        if shift + self.bb > 63:
            raise ValueError(f"frame interval too long for the packed event key: B={self.B}, "
                             f"H={self.H}, W={self.W}, dt_us={dt_us} need more than 63 bits")
        return shift

    def pixel_table(self, b_shift: int) -> torch.Tensor:
        """(B * H * W,) int64: the key bits (b, y, x) of every flat pixel, OFF bit 0."""
        if b_shift != self._table_shift:  # rebuilt only when the step length's bit width changes
            self._table = ((self.code >> 32) << b_shift) | (self.code & 0xFFFFFFFF)
            self._table_shift = b_shift
        return self._table

    def pixel_key(self, pix: torch.Tensor, off: torch.Tensor, b_shift: int) -> torch.Tensor:
        """Key bits (b, y, x, off) of flat pixel indices ``pix`` and OFF flags (bool)."""
        return self.pixel_table(b_shift).index_select(0, pix) | off.to(torch.int64)

    def sort_decode(self, keys: torch.Tensor, b_shift: int, t0: int,
                    sorted_keys: Optional[torch.Tensor] = None, pixel_order: bool = False) -> Events:
        """Sort the keys (in place on CPU), merge in ``sorted_keys`` (already sorted, or None) and
        unpack into :class:`Events` (t = t0 + t_rel). ``pixel_order``: the keys come in flat pixel
        order (those of the compiled pixel kernel alone), so the compiled radix sort only needs
        their (b, t) bits (a stable sort by those keeps the pixel order among equal times)."""
        mod = native.kernels() if _cpu_fast_path(keys) else None
        if mod is not None:
            # compiled: sorted, merged and decoded in one pass; the same result
            more = sorted_keys if sorted_keys is not None else keys.new_empty(0)
            b, x, y, t, p = mod.sort_decode(keys, b_shift + self.bb, self.t_shift if pixel_order else 0,
                                                      more.contiguous(), b_shift, self.t_shift, self.y_shift,
                                                      self.x_mask, self.y_mask, int(t0))
            return Events(b=b, x=x, y=y, t=t, p=p)
        if sorted_keys is not None and sorted_keys.numel():
            if _cpu_fast_path(keys) and sorted_keys.numel() > keys.numel():
                # mostly shot noise (dim scenes): sort the scene's keys and merge (descent frames,
                # B = 18: 2.4 against 4.8 ms for sorting all); else one sort of all is cheaper
                keys = _merge_sorted(_sort_values(keys), sorted_keys)
            else:
                keys = _sort_values(torch.cat((keys, sorted_keys)))
        else:
            keys = _sort_values(keys)
        # in-place where possible: every field is one fresh allocation, b reuses the keys
        if _cpu_fast_path(keys):  # the int64 -> int8 cast keeps the low byte (with the OFF bit)
            p = keys.to(torch.int8).bitwise_and_(1).mul_(-2).add_(1)
        else:
            p = (keys & 1).to(torch.int8).mul_(-2).add_(1)
        x = (keys >> 1).bitwise_and_(self.x_mask)
        y = (keys >> self.y_shift).bitwise_and_(self.y_mask)
        t = (keys >> self.t_shift).bitwise_and_((1 << (b_shift - self.t_shift)) - 1).add_(t0)
        b = keys.bitwise_right_shift_(b_shift)
        return Events(b=b, x=x, y=y, t=t, p=p)
