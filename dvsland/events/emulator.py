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
Gaussian, drawn per descent from its seed at its start, clamped to >= 1 % of the nominal
threshold), background activity ``background_rate_hz`` (Poisson events per pixel, uniform
time and polarity, independent of the pixel state: they neither move ``L_ref`` nor start a
refractory period), and the non-ideal pixel parts of :mod:`dvsland.events.pixel_model`
(photoreceptor low-pass, shot noise, leak, hot pixels; they need ``interpolation="log"`` except
shot noise). The low-pass replaces L by its filtered level and leak/hot pixels add a per-pixel
linear drift to it, so the crossing machinery above is unchanged; shot-noise events are drawn by
thinning and reset the reference of their pixel at the end of the step.

The stage contract (:mod:`dvsland.pytree`): the settings are an :class:`EmulatorParams` (frozen),
everything carried between steps an :class:`EmulatorState` (tensors, batch first: the reference,
the last level and event times, threshold maps, the low-pass and leak state, the denoiser's state,
and per descent its noise seed, step counter, time and irradiance range), and the step the pure
function :func:`emulator_step` (it writes into copies of the state's buffers, or into the state's
own with ``donate=True``). Random numbers are data: every draw is a counter-based hash of (descent
seed, descent step, pixel or event rank, stream tag) computed with torch ops on the state's device
(:mod:`dvsland.events.pixel_model`), so CPU and CUDA draw the same and a descent's noise does not
depend on its batch-mates. :func:`emulator_reset_where` restarts some descents and leaves the
others bit-identical. :class:`EventEmulator` offers the contract as methods (``init_state``,
``step_state``, ``reset_where``) and the object API (``reset``, ``step``) holding one state.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import NamedTuple, Optional, Tuple

import numpy as np
import torch

from dvsland.compiled import MODES as _COMPILE_MODES
from dvsland.compiled import CompiledFn, compile_on
from dvsland.pytree import check_state_like, tree_map, tree_where

from . import denoise as dn
from . import native
from . import pixel_model as pm
from .denoise import DenoiseState, EventDenoiser
from .emulator_dense import crossing_times, emitted_dense, pixel_step_dense, refractory_binds
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

_STAGE = "EventEmulator"


def _cpu_fast_path(t: torch.Tensor) -> bool:
    return CPU_FAST_PATHS and t.device.type == "cpu"


def _compiled_pixels(params: "EmulatorParams", state: "EmulatorState") -> bool:
    """Whether a step of ``state`` may run the compiled pixel kernel (CPU, log interpolation, float64)."""
    return _cpu_fast_path(state.lref) and params.interpolation == "log" and state.lref.dtype == torch.float64


def compiled_pixel_step(params: "EmulatorParams", state: "EmulatorState") -> bool:
    """Whether :func:`emulator_step` runs the compiled pixel kernel on ``state`` (:mod:`dvsland.events.native`:
    a CPU state, log interpolation, float64, the kernels built and switched on)."""
    return _compiled_pixels(params, state) and native.kernels() is not None


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


def _pos(name, v) -> float:
    v = float(v)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {v}")
    return v


def _nonneg(name, v) -> float:
    v = float(v)
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {v}")
    return v


# ------------------------------------------------------------------ params and state
@dataclasses.dataclass(frozen=True, eq=False)
class EmulatorParams:
    """The emulator's settings, frozen in flight (the constructor's arguments, checked; see
    :class:`EventEmulator`), plus the per-descent sensor values of
    :meth:`EventEmulator.set_element_params`: each a (B,) CPU tensor (float64; int64 for
    ``element_seeds``) or None (the scalar setting for every descent)."""

    threshold: float = 0.1
    threshold_off: float = 0.1
    refractory_us: float = 15.0
    log_eps: float = 1e-4
    interpolation: str = "log"
    mismatch_sigma: float = 0.0
    background_rate_hz: float = 0.0
    seed: int = 0
    pixel_model: pm.PixelModelParams = pm.PixelModelParams()
    max_events_per_step: Optional[int] = 20_000_000
    max_events_per_descent: int = 0
    device: Optional[torch.device] = None
    denoiser: Optional[EventDenoiser] = None
    threshold_scale: Optional[torch.Tensor] = None
    element_mismatch_sigma: Optional[torch.Tensor] = None
    element_background_rate_hz: Optional[torch.Tensor] = None
    element_refractory_us: Optional[torch.Tensor] = None
    element_seeds: Optional[torch.Tensor] = None
    compile: str = "false"

    def element_values(self) -> dict:
        """The per-descent values that are set, by field name."""
        return {k: getattr(self, k) for k in _ELEMENT_FIELDS if getattr(self, k) is not None}

    @property
    def threshold_maps(self) -> bool:
        """Per-pixel threshold maps (mismatch or any per-descent value), else the scalars."""
        return self.mismatch_sigma > 0 or bool(self.element_values())

    @property
    def background(self) -> bool:
        """Whether any descent has background activity (decided from the settings, no sync)."""
        r = self.element_background_rate_hz
        return bool((r > 0).any()) if r is not None else self.background_rate_hz > 0


_ELEMENT_FIELDS = ("threshold_scale", "element_mismatch_sigma", "element_background_rate_hz",
                   "element_refractory_us", "element_seeds")


class EmulatorState(NamedTuple):
    """Everything the emulator carries from one step to the next; batch first (B descents),
    (B, H, W) maps on the emulator's device. Optional fields are None where the part is off.

    Attributes:
        lref: (B, H, W) float64, reference log level L_ref of each pixel.
        l_prev: (B, H, W) float64, level of the last frame (low-pass filtered and drifting where on).
        t_last: (B, H, W) float64 µs, time of each pixel's last emitted event (-inf = none).
        seed: (B,) int64, each descent's noise seed (keys of its draws).
        step: (B,) int64, steps since each descent's start (keys of the step's draws).
        t_us: (B,) int64 µs, time of each descent's last frame (equal across the batch).
        irr_lo, irr_hi: (B,) float64, irradiance range of each descent's last frame.
        t_reset_us: (B,) int64 µs, time of each descent's start (the leak drift's origin).
        i_prev: (B, H, W) float64 irradiance of the last frame (``interpolation="linear"`` only).
        th_on, th_off: (B, H, W) float64 per-pixel thresholds (threshold maps only, else None).
        th_min: (B,) float64, each descent's smallest threshold (threshold maps only).
        l_lp: (B, H, W) float64 low-pass filtered log level without drift (photoreceptor on).
        drift: (B, H, W) float64 level drift, log units per µs (leak / hot pixels on).
        leak_rate_hz: (B, H, W) float64 leak rate, Hz (hot pixels included); hot_pixels: (B, H, W)
            bool; leak_phase: (B, H, W) float64 initial phase in thresholds (leak / hot pixels on).
        denoise: the front-end filters' :class:`DenoiseState` (denoising on).
    """

    lref: torch.Tensor
    l_prev: torch.Tensor
    t_last: torch.Tensor
    seed: torch.Tensor
    step: torch.Tensor
    t_us: torch.Tensor
    irr_lo: torch.Tensor
    irr_hi: torch.Tensor
    t_reset_us: torch.Tensor
    i_prev: Optional[torch.Tensor] = None
    th_on: Optional[torch.Tensor] = None
    th_off: Optional[torch.Tensor] = None
    th_min: Optional[torch.Tensor] = None
    l_lp: Optional[torch.Tensor] = None
    drift: Optional[torch.Tensor] = None
    leak_rate_hz: Optional[torch.Tensor] = None
    hot_pixels: Optional[torch.Tensor] = None
    leak_phase: Optional[torch.Tensor] = None
    denoise: Optional[DenoiseState] = None


def make_params(threshold: float = 0.1, threshold_off: Optional[float] = None, refractory_us: float = 15.0,
                log_eps: float = 1e-4, interpolation: str = "log", device=None, mismatch_sigma: float = 0.0,
                background_rate_hz: float = 0.0, seed: int = 0, max_events_per_step: Optional[int] = 20_000_000,
                denoiser: Optional[EventDenoiser] = None, max_events_per_descent: int = 0, compile: str = "false",
                **pixel_model) -> EmulatorParams:
    """Checked :class:`EmulatorParams` from the constructor's arguments (``pixel_model``: the fields of
    :class:`~dvsland.events.pixel_model.PixelModelParams`); ValueError naming a bad one."""
    if interpolation not in _INTERPOLATIONS:
        raise ValueError(f"interpolation must be one of {_INTERPOLATIONS}, got {interpolation!r}")
    if max_events_per_step is not None and not int(max_events_per_step) >= 1:
        raise ValueError(f"max_events_per_step must be an integer >= 1 or None, got {max_events_per_step}")
    if not int(max_events_per_descent) >= 0:
        raise ValueError(f"max_events_per_descent must be an integer >= 0, got {max_events_per_descent}")
    if str(compile).lower() not in _COMPILE_MODES:
        raise ValueError(f"compile must be one of {_COMPILE_MODES}, got {compile!r}")
    pmp = pm.PixelModelParams(**pixel_model)
    if interpolation != "log":
        for name, on in (("photoreceptor_cutoff_hz", pmp.lowpass), ("leak_rate_hz / hot_pixel_fraction", pmp.drift)):
            if on:
                raise ValueError(f"{name} needs interpolation='log' (the filtered or drifting level "
                                 f"is interpolated in log space), got interpolation={interpolation!r}")
    return EmulatorParams(
        threshold=_pos("threshold", threshold),
        threshold_off=_pos("threshold_off", threshold if threshold_off is None else threshold_off),
        refractory_us=_nonneg("refractory_us", refractory_us), log_eps=_pos("log_eps", log_eps),
        interpolation=interpolation, mismatch_sigma=_nonneg("mismatch_sigma", mismatch_sigma),
        background_rate_hz=_nonneg("background_rate_hz", background_rate_hz), seed=int(seed), pixel_model=pmp,
        max_events_per_step=None if max_events_per_step is None else int(max_events_per_step),
        max_events_per_descent=int(max_events_per_descent), device=None if device is None else torch.device(device),
        denoiser=denoiser if denoiser is not None and denoiser.active else None, compile=str(compile).lower())


def with_element_params(params: EmulatorParams, threshold_scale=None, mismatch_sigma=None,
                        background_rate_hz=None, refractory_us=None, element_seeds=None) -> EmulatorParams:
    """``params`` with per-descent sensor values (each (B,) or None; see
    :meth:`EventEmulator.set_element_params`); ValueError naming a bad one."""
    vals = {}
    for name, field, v in (("threshold_scale", "threshold_scale", threshold_scale),
                           ("mismatch_sigma", "element_mismatch_sigma", mismatch_sigma),
                           ("background_rate_hz", "element_background_rate_hz", background_rate_hz),
                           ("refractory_us", "element_refractory_us", refractory_us)):
        if v is None:
            continue
        a = np.asarray(v.cpu() if isinstance(v, torch.Tensor) else v, dtype=np.float64).reshape(-1)
        lo = 0.0 if name != "threshold_scale" else 1e-9
        if not (np.isfinite(a).all() and (a >= lo).all()):
            raise ValueError(f"{name} must be finite and >= {lo} per element, got {a}")
        vals[field] = torch.from_numpy(a.copy())
    if "element_refractory_us" in vals and params.interpolation != "log":
        raise ValueError("per-element refractory_us needs interpolation='log'")
    if element_seeds is not None:
        s = element_seeds.cpu() if isinstance(element_seeds, torch.Tensor) else element_seeds
        vals["element_seeds"] = torch.from_numpy(np.asarray(s, dtype=np.int64).reshape(-1).copy())
    sizes = {int(a.numel()) for a in vals.values()}
    if len(sizes) > 1:
        raise ValueError(f"per-element values must all have the batch size, got sizes {sorted(sizes)}")
    return dataclasses.replace(params, **{k: vals.get(k) for k in _ELEMENT_FIELDS})


def _default_seeds(params: EmulatorParams, B: int, device) -> torch.Tensor:
    """(B,) int64: ``element_seeds`` where set, else ``(seed * 1000003 + b) mod 2^63`` (b the index)."""
    if params.element_seeds is not None:
        return params.element_seeds.to(device)
    base = (params.seed * 1_000_003) % (2 ** 63)
    return (torch.arange(B, dtype=torch.int64, device=device) + base) & (2 ** 63 - 1)


def _check_elements(params: EmulatorParams, B: int) -> None:
    for a in params.element_values().values():
        if a.numel() != B:
            raise ValueError(f"per-element values are for B={a.numel()}, the frames have B={B}")


def _frames_f64(frames, device) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A private float64 copy of ``frames`` (B, H, W) on ``device`` (None = theirs), and each
    descent's irradiance range (B,) float64 (min, max; NaN where a NaN is). Checks type and rank."""
    if not isinstance(frames, torch.Tensor):
        frames = torch.as_tensor(frames)
    frames = frames.detach()
    if not frames.is_floating_point():
        raise ValueError(f"frames must be a floating-point tensor (linear irradiance), got {frames.dtype}")
    if frames.dim() != 3:
        raise ValueError(f"frames must have shape (B, H, W), got {tuple(frames.shape)}")
    if min(frames.shape) < 1:
        raise ValueError(f"frames must have B, H, W >= 1, got {tuple(frames.shape)}")
    dev = torch.device(device) if device is not None else frames.device
    mod = native.kernels() if frames.dtype == torch.float32 and dev.type == "cpu" and _cpu_fast_path(frames) else None
    if mod is not None:  # the copy and both ranges in one compiled pass (the same values)
        return mod.widen_range(frames.contiguous())
    f = frames.to(device=dev, dtype=torch.float64, copy=True)
    # the range of the narrower input where it is on that device (the same values: every float
    # widens to float64 exactly); amin and amax apart: on a CPU thread ~10x cheaper than aminmax
    src = frames.reshape(f.shape[0], -1) if frames.device == f.device else f.view(f.shape[0], -1)
    return f, src.amin(1).to(torch.float64), src.amax(1).to(torch.float64)


def _check_range(lo: float, hi: float) -> None:
    """ValueError when the frames' (min, max) irradiance holds NaN, inf or a negative value."""
    if not (lo >= 0 and hi < math.inf):
        if math.isnan(lo) or math.isnan(hi):
            raise ValueError("frames contain NaN; irradiance must be finite and >= 0")
        if hi == math.inf or lo == math.inf:
            raise ValueError("frames contain inf; irradiance must be finite and >= 0")
        raise ValueError(f"frames contain negative irradiance (min {lo}); irradiance must be >= 0")


def _threshold_maps(params: EmulatorParams, seeds: torch.Tensor, shape):
    """(th_on, th_off (B, H, W), th_min (B,)) float64 per-pixel thresholds, or Nones (scalars):
    relative maps :func:`pixel_model.draw_mismatch` times ``threshold_scale``."""
    if not params.threshold_maps:
        return None, None, None
    dev = seeds.device
    sig = params.element_mismatch_sigma
    sig = torch.full((shape[0],), params.mismatch_sigma, dtype=torch.float64) if sig is None else sig
    maps = pm.draw_mismatch(seeds, sig.to(dev), shape)
    if params.threshold_scale is not None:
        maps *= params.threshold_scale.to(dev)[:, None, None, None]
    th_on, th_off = params.threshold * maps[:, 0], params.threshold_off * maps[:, 1]
    return th_on, th_off, torch.minimum(th_on.amin(dim=(1, 2)), th_off.amin(dim=(1, 2)))


def emulator_init(params: EmulatorParams, frames: torch.Tensor, t_us: int,
                  seed: Optional[torch.Tensor] = None) -> EmulatorState:
    """A fresh state: every pixel starts on ``frames`` at ``t_us``, no events.

    Args:
        params: the settings.
        frames: (B, H, W) floating, linear irradiance, finite, >= 0.
        t_us: int µs.
        seed: (B,) int64 noise seeds of the descents; None = ``params.element_seeds`` where set,
            else derived from ``params.seed`` and the descent's index.

    Returns:
        the :class:`EmulatorState` on ``params.device`` (None = the frames' device).
    """
    t_us = _check_t_us(t_us)
    f, lo, hi = _frames_f64(frames, params.device)
    _check_range(*torch.stack((lo.min(), hi.max())).tolist())  # one sync
    B, H, W = (int(s) for s in f.shape)
    dev = f.device
    _check_elements(params, B)
    seeds = _default_seeds(params, B, dev) if seed is None else _checked_seed(seed, B, dev)
    lref = torch.log(f + params.log_eps)
    th_on, th_off, th_min = _threshold_maps(params, seeds, (B, H, W))
    pmp = params.pixel_model
    st = EmulatorState(
        lref=lref, l_prev=lref.clone(), t_last=torch.full((B, H, W), -math.inf, dtype=torch.float64, device=dev),
        seed=seeds, step=torch.zeros(B, dtype=torch.int64, device=dev),
        t_us=torch.full((B,), t_us, dtype=torch.int64, device=dev), irr_lo=lo, irr_hi=hi,
        t_reset_us=torch.full((B,), t_us, dtype=torch.int64, device=dev),
        i_prev=f if params.interpolation == "linear" else None, th_on=th_on, th_off=th_off, th_min=th_min,
        l_lp=lref.clone() if pmp.lowpass else None,
        denoise=dn.init_state(B, H, W, t_us, dev) if params.denoiser is not None else None)
    if pmp.drift:
        rate, hot, phase = pm.draw_leak_state(seeds, (B, H, W), pmp)
        th = th_on if th_on is not None else params.threshold
        # the reference starts u_i thresholds below the level
        st = st._replace(drift=rate.mul(th).mul_(1e-6), leak_rate_hz=rate, hot_pixels=hot, leak_phase=phase,
                         lref=lref.sub(phase.mul(th)))
    return st


def _checked_seed(seed, B: int, device) -> torch.Tensor:
    seed = torch.as_tensor(seed)
    if seed.shape != (B,) or seed.dtype != torch.int64:
        raise ValueError(f"{_STAGE}: seed must be a (B,) = ({B},) int64 tensor, got shape {tuple(seed.shape)} "
                         f"{seed.dtype}")
    return seed.to(device)


@functools.lru_cache(maxsize=16)
def _state_reference(params: EmulatorParams, shape, device) -> EmulatorState:
    """A state of the expected structure, shapes, dtypes and device (expanded scalars: no memory),
    for :func:`dvsland.pytree.check_state_like` (cached: params are frozen, compared by identity)."""
    B, H, W = shape

    def t(dtype, *s):
        return torch.zeros((), dtype=dtype, device=device).expand(*s)

    f8, i8 = torch.float64, torch.int64
    pix = (B, H, W)
    maps, pmp = params.threshold_maps, params.pixel_model
    den = None
    if params.denoiser is not None:
        den = DenoiseState(t(i8, *pix), t(i8, *pix), t(i8, *pix), t(i8, B))
    return EmulatorState(
        lref=t(f8, *pix), l_prev=t(f8, *pix), t_last=t(f8, *pix), seed=t(i8, B), step=t(i8, B), t_us=t(i8, B),
        irr_lo=t(f8, B), irr_hi=t(f8, B), t_reset_us=t(i8, B),
        i_prev=t(f8, *pix) if params.interpolation == "linear" else None,
        th_on=t(f8, *pix) if maps else None, th_off=t(f8, *pix) if maps else None, th_min=t(f8, B) if maps else None,
        l_lp=t(f8, *pix) if pmp.lowpass else None, drift=t(f8, *pix) if pmp.drift else None,
        leak_rate_hz=t(f8, *pix) if pmp.drift else None, hot_pixels=t(torch.bool, *pix) if pmp.drift else None,
        leak_phase=t(f8, *pix) if pmp.drift else None, denoise=den)


def check_state(params: EmulatorParams, state: EmulatorState, frames_shape=None) -> None:
    """ValueError naming the field when ``state`` does not fit ``params`` (structure, shapes, dtypes,
    devices); ``frames_shape``: the (B, H, W) of the frames it is stepped with (a state that is
    consistent in itself but of another shape gives the frames' error: batch or sensor size changed)."""
    if not isinstance(state, EmulatorState):
        raise ValueError(f"{_STAGE}: state must be an EmulatorState, got {type(state).__name__}")
    lref = state.lref
    own = tuple(lref.shape) if isinstance(lref, torch.Tensor) and lref.dim() == 3 else None
    shape = tuple(frames_shape) if frames_shape is not None else own
    if shape is None:
        raise ValueError(f"{_STAGE}: state field 'lref' must be a (B, H, W) tensor, got {lref!r:.80}")
    device = lref.device if isinstance(lref, torch.Tensor) else None
    try:
        check_state_like(_STAGE, state, _state_reference(params, shape, device))
    except ValueError as err:
        if own is None or own == shape:
            raise
        try:  # consistent in itself: the frames' shape is what changed
            check_state_like(_STAGE, state, _state_reference(params, own, device))
        except ValueError:
            raise err from None
        what = "batch size" if shape[0] != own[0] else "sensor size"
        raise ValueError(f"frames {what} changed: got shape {shape}, reset with {own}") from None


def emulator_reset_where(params: EmulatorParams, state: EmulatorState, mask: torch.Tensor, frames: torch.Tensor,
                         t_us: int, seed: Optional[torch.Tensor] = None) -> EmulatorState:
    """``state`` with the descents of ``mask`` (B,) bool restarted on ``frames`` (B, H, W) at ``t_us``
    (their reference the new frame's level, their step counter 0, their seed ``seed[mask]`` where
    ``seed`` (B,) int64 is given, else their own); the other descents bit-identical. ``t_us`` should
    be the state's time (the batch steps at shared instants): a restarted descent emits its first
    events at the next step."""
    check_state(params, state)
    B = state.lref.shape[0]
    mask = torch.as_tensor(mask, device=state.lref.device)
    if mask.shape != (B,) or mask.dtype != torch.bool:
        raise ValueError(f"{_STAGE}: mask must be a (B,) = ({B},) bool tensor, got shape {tuple(mask.shape)} "
                         f"{mask.dtype}")
    seeds = state.seed if seed is None else torch.where(mask, _checked_seed(seed, B, state.seed.device), state.seed)
    p = dataclasses.replace(params, device=state.lref.device)
    rows = mask.nonzero().squeeze(1)  # one sync: a restart, not the step's path
    if rows.numel() == B:
        fresh = emulator_init(p, frames, t_us, seeds)
        check_state(params, fresh, tuple(state.lref.shape))
        return tree_where(mask, fresh, state)
    if rows.numel() == 0:
        return state
    # only the restarted rows are initialised (their draws are keyed by their own seeds: the bits
    # of a whole batch's init at those rows); a fleet restarts a few of 8,192 descents at a time
    fresh = emulator_init(params_rows(p, rows), frames.index_select(0, rows.to(frames.device)), t_us,
                          seeds.index_select(0, rows))
    return put_rows(state, rows, fresh)


def params_rows(params: EmulatorParams, rows: torch.Tensor) -> EmulatorParams:
    """``params`` of the descents ``rows`` (K,) int64: the per-descent values (B,) taken at those rows."""
    vals = params.element_values()
    if not vals:
        return params
    r = rows.to("cpu")  # the per-descent values are CPU tensors
    return dataclasses.replace(params, **{k: v.index_select(0, r) for k, v in vals.items()})


def put_rows(state: EmulatorState, rows: torch.Tensor, part: EmulatorState) -> EmulatorState:
    """``state`` with every batch-first leaf's rows ``rows`` (K,) int64 replaced by ``part``'s (K, ...)
    (a new state; ``state`` is not written). Both must have the same fields set."""
    B = state.lref.shape[0]
    out = {}
    for name, full, new in zip(EmulatorState._fields, state, part):
        if (full is None) != (new is None):
            raise ValueError(f"{_STAGE}: state field {name!r} is set in one state and not the other")
        out[name] = None if full is None else tree_map(lambda f, n: rows_into(f, rows, n, B), full, new)
    return EmulatorState(**out)


def rows_into(full: torch.Tensor, rows: torch.Tensor, part: torch.Tensor, batch_size: int) -> torch.Tensor:
    """A copy of the leaf ``full`` with its rows ``rows`` (K,) int64 set to ``part`` (K, ...) when it is
    batch first ((batch_size, ...)); else ``part`` itself (a leaf shared by the batch)."""
    return full.index_copy(0, rows, part) if full.dim() >= 1 and full.shape[0] == batch_size else part


# ------------------------------------------------------------------------ the pure step
class _Step:
    """One step's working values (local to :func:`emulator_step`, never kept): the settings, the
    key layout, the interval, the pixels' working reference and last-event times (copies of the
    state's, or the state's own buffers when donated), thresholds and the event count so far."""

    def __init__(self, params: EmulatorParams, state: EmulatorState, t0: int, t1: int, donate: bool):
        B, H, W = state.lref.shape
        self.params, self.state, self.t0, self.dt = params, state, t0, float(t1 - t0)
        self.layout = _layout(B, H, W, state.lref.device)
        self.b_shift = self.layout.b_shift(t1 - t0)  # ValueError if the key would overflow
        # the compiled pixel kernel (or None: the torch path) reads the state's buffers and writes
        # fresh ones (its pass is the copy)
        self.native = native.kernels() if _compiled_pixels(params, state) else None
        # emulator.compile: every pixel's step in one traced function (new buffers: nothing to copy first)
        self.dense = (_dense_fn() if self.native is None and params.interpolation == "log"
                      and compile_on(params.compile, state.lref.device) else None)
        if donate or self.dense is not None:
            self.lref, self.t_last = state.lref, state.t_last
        elif self.native is not None:
            self.lref, self.t_last = torch.empty_like(state.lref), torch.empty_like(state.t_last)
        else:
            self.lref, self.t_last = state.lref.clone(), state.t_last.clone()
        self.th_scalar = state.th_on is None
        self.th_on = params.threshold if self.th_scalar else state.th_on
        self.th_off = params.threshold_off if self.th_scalar else state.th_off
        r = params.element_refractory_us
        self.r_elem = None if r is None else r.to(state.lref.device)
        self.r_max = params.refractory_us if r is None else float(r.max())  # a CPU tensor: no sync
        self.spacing_may_bind = self.r_max > 0
        self.n_step = 0.0
        self.cap = event_cap(params, B)

    def count(self, counts: torch.Tensor) -> Optional[float]:
        """Add (A,) per-pixel event counts to this step's total; ValueError above the cap. Returns
        their sum (a host float: one sync per block), or None without a cap (no sync)."""
        if self.cap is None:
            return None
        return self.add(float(counts.sum()))  # one sync per block

    def add(self, n: float) -> float:
        """Add ``n`` events (a count already on the host) to this step's total; ValueError above the
        cap (:func:`event_cap`); returns ``n``."""
        cap = self.cap
        if cap is None:
            return n
        self.n_step += n
        if self.n_step > cap:
            p, B = self.params, self.state.lref.shape[0]
            raise ValueError(
                f"emulator.max_events_per_step: this step would emit at least {self.n_step:.4g} events, above "
                f"the cap of {cap} (about {self.n_step * 48 / 2 ** 30:.3g} GiB at 48 B per event; the larger "
                f"of emulator.max_events_per_step = {p.max_events_per_step} and emulator.max_events_per_descent "
                f"= {p.max_events_per_descent} x {B} descents); raise emulator.threshold or lower the batch / "
                f"sensor size, or raise the cap if the memory is there. The state given to the step is unchanged")
        return n


def event_cap(params: EmulatorParams, batch_size: int) -> Optional[int]:
    """The most events one step of ``batch_size`` descents may emit: the larger of
    ``max_events_per_step`` and ``max_events_per_descent`` x ``batch_size`` (None: no cap)."""
    cap = params.max_events_per_step
    if cap is None:
        return None
    return max(int(cap), int(params.max_events_per_descent) * int(batch_size))


_LAYOUTS: dict = {}


def _layout(B: int, H: int, W: int, device) -> "_KeyLayout":
    """The key layout of (B, H, W) on ``device`` (a deterministic table, built once and cached)."""
    key = (B, H, W, str(device))
    lay = _LAYOUTS.get(key)
    if lay is None:
        if len(_LAYOUTS) >= 8:
            _LAYOUTS.clear()
        lay = _LAYOUTS[key] = _KeyLayout(B, H, W, device)
    return lay


def _step_inputs(params: EmulatorParams, state: EmulatorState, frames, t_us):
    """The checked inputs of a step: (t0, t1, the frames' float64 copy (B, H, W), their range (B,) x 2,
    the spacing bound's inputs) with one host sync for every scalar the step needs."""
    t1 = _check_t_us(t_us)
    if not isinstance(state, EmulatorState):
        raise ValueError(f"{_STAGE}: state must be an EmulatorState, got {type(state).__name__}")
    ok = isinstance(frames, torch.Tensor) and frames.is_floating_point() and frames.dim() == 3
    if ok:  # else _frames_f64 names what is wrong with the frames first
        check_state(params, state, tuple(frames.shape))
    f, lo, hi = _frames_f64(frames, state.lref.device)
    if not ok:
        check_state(params, state, tuple(f.shape))
    th_min = state.th_min.min() if state.th_min is not None else lo.new_tensor(min(params.threshold,
                                                                                    params.threshold_off))
    bg = _background_counts(params, state, t1) if params.background else None
    vals = torch.stack((lo.min(), hi.max(), state.irr_lo.min(), state.irr_hi.max(), th_min,
                        state.t_us.min().to(torch.float64), state.t_us.max().to(torch.float64),
                        *(() if bg is None else (bg[1].sum().to(torch.float64),)))).tolist()
    _check_range(vals[0], vals[1])
    t0, t0_max = int(vals[5]), int(vals[6])
    if t0 != t0_max:
        raise ValueError(f"{_STAGE}: state field 't_us' must be equal across the batch (the descents step at "
                         f"shared instants), got {t0} to {t0_max}")
    if t1 <= t0:
        raise ValueError(f"t_us must increase: got {t1} after {t0}")
    return t0, t1, f, lo, hi, vals, (None if bg is None else (*bg, int(vals[7])))


def _background_counts(params: EmulatorParams, state: EmulatorState, t1: int):
    """This step's background draw (keys, Poisson counts (B,)) of :func:`pixel_model.uniform_counts`,
    with the interval read on the device (t1 - each descent's time), so that the total joins the
    step's one read of its inputs."""
    B, H, W = state.lref.shape
    rate = params.element_background_rate_hz
    rate = params.background_rate_hz if rate is None else rate.to(state.seed.device)
    lam = pm.background_lam(state.seed, rate, H * W, (t1 - state.t_us).clamp_min(0))  # < 0: refused after the read
    return pm.uniform_counts(state.seed, state.step + 1, lam, pm.TAG_BACKGROUND)


def emulator_step(params: EmulatorParams, state: EmulatorState, frames: torch.Tensor, t_us: int,
                  donate: bool = False) -> Tuple[EmulatorState, Events]:
    """Advance every descent to ``t_us`` with new frames: (new state, events in (t_prev, t_us]).

    Args:
        params: the settings.
        state: the state after the previous frame (every descent at the same time t_prev < t_us).
        frames: (B, H, W) floating, linear irradiance, finite, >= 0, the state's shape.
        t_us: int µs, > the state's time.
        donate: hand the state's buffers over (JAX's donated arguments): the reference and the
            last-event times are then worked on in place (no copy of them), so ``state`` must not be
            used again. Off by default: ``state`` is never written.

    Returns:
        the new :class:`EmulatorState` and the :class:`Events` on the state's device, sorted by (b, t),
        ties by row-major pixel (exact ties of noise events with pixel events: by pixel, then OFF
        after ON), denoised where the params say so.
    """
    t0, t1, f1, lo, hi, vals, bg_counts = _step_inputs(params, state, frames, t_us)
    ctx = _Step(params, state, t0, t1, donate)
    pmp = params.pixel_model
    if ctx.r_max > 0 and not (pmp.lowpass or pmp.drift):
        # crossings are spaced dt θ / |L1 - L0| apart; |L1 - L0| is at most the log range of both
        # frames, so when dt θ_min / r exceeds it the spacing alone never drops a crossing (with a
        # filtered or drifting level the frame range no longer bounds the level's change)
        l_span = math.log(max(vals[1], vals[3]) + params.log_eps) - math.log(min(vals[0], vals[2]) + params.log_eps)
        ctx.spacing_may_bind = ctx.dt * vals[4] <= ctx.r_max * l_span * (1 + 1e-6)
    step = state.step + 1
    alpha = shot = None
    if pmp.lowpass:
        alpha = pm.photoreceptor_alpha(f1, ctx.dt * 1e-6, pmp.photoreceptor_cutoff_hz, pmp.full_irradiance)
    if pmp.shot:  # drawn now: the rate needs the irradiance (f1 becomes L1 below)
        shot = _shot_noise(ctx, f1, step)
    l1, l_lp = _level(params, state, f1, alpha, t1)
    keys, pixel_order = _pixel_keys(ctx, l1, f1)
    if bg_counts is not None:  # params.background
        bg = _background(ctx, step, bg_counts)
        keys, pixel_order = (bg if keys is None else torch.cat((keys, bg))), False
    if shot is not None:
        flat, shot_keys = shot
        if flat.numel():
            # a shot event resets its pixel's reference to the current level (as v2e)
            ctx.lref.view(-1).index_copy_(0, flat, l1.view(-1).index_select(0, flat))
            keys, pixel_order = (shot_keys if keys is None else torch.cat((keys, shot_keys))), False
    if keys is None or keys.numel() == 0:
        ev = Events.empty(state.lref.device)
    else:
        ev = ctx.layout.sort_decode(keys, ctx.b_shift, t0, pixel_order=pixel_order)
    den = state.denoise
    if params.denoiser is not None:
        den, ev = dn.denoise(ev, den, t1, params.denoiser)
    B, H, W = state.lref.shape
    ev = ev.marked_checked(B, W, H)  # sorted and in range by construction: estimators need not read them
    new = state._replace(lref=ctx.lref, l_prev=l1, t_last=ctx.t_last, step=step,
                         t_us=torch.full_like(state.t_us, t1), irr_lo=lo, irr_hi=hi, l_lp=l_lp, denoise=den,
                         i_prev=f1 if params.interpolation == "linear" else None)
    return new, ev


def _level(params: EmulatorParams, state: EmulatorState, f1: torch.Tensor, alpha, t1: int):
    """The pixels' new level L1 (B, H, W) float64 (low-pass filtered and drifting where on; written
    over ``f1``, a private copy, in log interpolation) and the new filtered level (or None)."""
    if params.interpolation == "log":
        l1 = f1.add_(params.log_eps).log_()
    else:
        l1 = torch.log(f1 + params.log_eps)
    l_lp = None
    if alpha is not None:  # the new filtered level, written over L1; shared with l1 until the drift
        l_lp = l1 = torch.lerp(state.l_lp, l1, alpha, out=l1)
    if state.drift is not None:
        el = (t1 - state.t_reset_us).to(torch.float64).view(-1, 1, 1)  # µs since each descent's start
        l1 = l1.add(state.drift * el) if l_lp is not None else l1.add_(state.drift * el)
    return l1, l_lp


def _pixel_keys(ctx: _Step, l1: torch.Tensor, f1: torch.Tensor):
    """(keys of the pixels' events or None, whether they come in pixel order); moves the working
    L_ref and t_last: the compiled one-pass kernel where built (CPU, log interpolation), else the
    candidate scan and :func:`_pixel_events` per block of candidates."""
    if ctx.native is not None:
        return _native_pixel_events(ctx, l1), True
    if ctx.dense is not None:
        return _dense_pixel_events(ctx, l1), False
    d = torch.sub(l1, ctx.lref)  # a temporary: the CPU scan may overwrite it
    # candidate pixels (A,): a superset of those with >= 1 crossing (exact counts follow)
    if ctx.th_scalar:
        act = _candidates(d, ctx.th_on, ctx.th_off, 1.0 - 2 * LEVEL_TOL)  # sync
    else:
        shrink = 1.0 - 2 * LEVEL_TOL
        act = _candidates_map(d, ctx.th_on * shrink, ctx.th_off * -shrink)
    del d
    if act.numel() == 0:
        return None, False
    # on CPU, blocks of candidates small enough to keep the ~40 per-pixel temporaries in
    # cache (faster at large B); one block on other devices
    block = _CPU_BLOCK if _cpu_fast_path(act) else act.numel()
    parts = [_pixel_events(ctx, act[i:i + block], l1, f1) for i in range(0, act.numel(), block)]
    return (parts[0] if len(parts) == 1 else torch.cat(parts)), False


def _native_pixel_events(ctx: _Step, l1: torch.Tensor) -> torch.Tensor:
    """Keys of the pixels' events from :mod:`dvsland.events.native` ``pixel_events``, in pixel order;
    writes the working L_ref and t_last (from the state's, in the same pass)."""
    layout, state = ctx.layout, ctx.state
    n_out = torch.zeros(1, dtype=torch.float64)
    cap = ctx.cap
    none = l1.new_empty(0)
    if ctx.th_scalar:
        th_on, th_off, on_map, off_map = float(ctx.th_on), float(ctx.th_off), none, none
    else:
        th_on, th_off = 0.0, 0.0
        on_map, off_map = ctx.th_on.reshape(-1).contiguous(), ctx.th_off.reshape(-1).contiguous()
    r_elem = none if ctx.r_elem is None else ctx.r_elem.to(torch.float64).contiguous()
    keys = ctx.native.pixel_events(
        l1.reshape(-1), state.lref.reshape(-1), state.l_prev.reshape(-1), state.t_last.reshape(-1),
        state.lref.shape, ctx.b_shift, layout.y_shift, th_on, th_off, on_map, off_map,
        float(ctx.params.refractory_us), r_elem, float(ctx.t0), ctx.dt, bool(ctx.spacing_may_bind),
        layout.t_shift, -1 if cap is None else int(cap), n_out, lref_out=ctx.lref.view(-1),
        tlast_out=ctx.t_last.view(-1))
    ctx.count(n_out)  # ValueError above the cap (the kernel then emitted nothing)
    return keys


_DENSE: Optional[CompiledFn] = None


def _dense_fn() -> CompiledFn:
    """The process's traced :func:`~dvsland.events.emulator_dense.pixel_step_dense` (emulator.compile)."""
    global _DENSE
    if _DENSE is None:
        _DENSE = CompiledFn(pixel_step_dense, "emulator.compile", "the pixels' step")
    return _DENSE


def _dense_pixel_events(ctx: _Step, l1: torch.Tensor) -> Optional[torch.Tensor]:
    """Keys of the pixels' events (or None without any) from the traced step of every pixel, in the
    candidate path's order and values; sets the working L_ref and t_last to the step's new ones.
    One host sync: the events' count (the cap) and the sizes of the compactions."""
    st, layout = ctx.state, ctx.layout
    r = ctx.params.refractory_us if ctx.r_elem is None else ctx.r_elem.to(torch.float64).view(-1, 1, 1)
    t0 = torch.tensor(float(ctx.t0), dtype=torch.float64, device=l1.device)
    same = ctx.th_scalar and ctx.th_on == ctx.th_off
    ctx.lref, ctx.t_last, cnt, first, step_us, off, sizes = ctx.dense(
        l1, st.lref, st.l_prev, st.t_last, ctx.th_on, ctx.th_off, r, t0, ctx.dt, bool(ctx.spacing_may_bind), same,
        LEVEL_TOL)
    n_cnt, n_sel, n_multi = sizes.tolist()
    ctx.add(n_cnt)  # before any per-event allocation
    if n_sel == 0:
        return None
    cnt = cnt.view(-1)
    sel = _nonzero_1d(cnt > 0) if _cpu_fast_path(cnt) else _compact(cnt > 0, int(n_sel))
    cnt, first, step_us = (v.view(-1).index_select(0, sel) for v in (cnt, first, step_us))
    code = layout.pixel_key(sel, off.view(-1).index_select(0, sel), ctx.b_shift)
    # the pixels with two or more events (indices into the selected ones)
    multi = _compact(cnt > 1, int(n_multi)) if n_multi else sel.new_empty(0)
    return _event_keys(first, code, multi, cnt, first, step_us, code, ctx.dt, layout.t_shift,
                       int(n_cnt) - int(n_sel))


def _pixel_events(ctx: _Step, act, l1, f1) -> torch.Tensor:
    """Events of the candidate pixels ``act`` (A,) as sort keys; moves the working L_ref and t_last.
    A function of its own so that its (A,)- and (N,)-sized temporaries die on return."""
    layout, params, t0, dt = ctx.layout, ctx.params, ctx.t0, ctx.dt
    th_on, th_off = ctx.th_on, ctx.th_off
    r = params.refractory_us
    if ctx.r_elem is not None:  # per element: (A,) gathered per pixel
        r = ctx.r_elem.index_select(0, torch.div(act, l1[0].numel(), rounding_mode="floor"))
    lref_flat = ctx.lref.view(-1)
    lref_a = lref_flat.index_select(0, act)
    l1_a = l1.view(-1).index_select(0, act)
    d_a = l1_a - lref_a  # bit-identical to d[act], cheaper than a gather
    if ctx.th_scalar and th_on == th_off:
        n_a = torch.floor((d_a / th_on).abs_().add_(LEVEL_TOL))
        th_a = torch.sign(d_a).mul_(th_on)  # d_a != 0 for candidates
    else:
        th_on_a, th_off_a = _take(th_on, act), _take(th_off, act)
        n_on = torch.floor(d_a / th_on_a + LEVEL_TOL).clamp_(min=0)
        n_off = torch.floor(-d_a / th_off_a + LEVEL_TOL).clamp_(min=0)
        n_a = n_on + n_off  # at most one of them > 0
        th_a = torch.where(d_a > 0, th_on_a, -th_off_a)  # signed step of L_ref
    tl_flat = ctx.t_last.view(-1)
    tl_a = tl_flat.index_select(0, act).sub_(t0)  # relative, <= 0 or -inf
    code_a = layout.pixel_key(act, torch.signbit(th_a), ctx.b_shift)
    if params.interpolation == "log":
        keys, sel, tlast_new = _log_keys(ctx, act, n_a, th_a, lref_a, l1_a, tl_a, r, code_a)
    else:
        ctx.count(n_a)  # upper bound (refractory only drops), before the per-crossing loop
        seg, tau, cnti, tlast_new = _emitted_linear(
            n_a, th_a, lref_a, ctx.state.i_prev.view(-1).index_select(0, act),
            f1.view(-1).index_select(0, act), dt, tl_a, r, params.log_eps)
        sel = _nonzero_1d(cnti > 0)
        t_rel = torch.floor(tau.add_(0.5)).clamp_(1.0, dt).to(torch.int64)
        keys = code_a.index_select(0, seg).add_(t_rel << layout.t_shift)
    # state: the reference moves by one threshold per crossing (emitted or dropped);
    # the last emitted time where >= 1 event was emitted
    lref_flat.scatter_(0, act, lref_a.addcmul_(n_a, th_a))
    if sel.numel() == act.numel():
        tl_flat.scatter_(0, act, tlast_new.add_(t0))
    else:
        tl_flat.scatter_(0, act.index_select(0, sel), tlast_new.index_select(0, sel).add_(t0))
    return keys


def _log_keys(ctx: _Step, act, n_a, th_a, lref_a, l1_a, tl_a, r, code_a):
    """Log interpolation: (keys, indices of the candidates with >= 1 event, their last event time
    relative to t0 (A,)) from the closed form :func:`_emitted_log`."""
    dt, t_shift = ctx.dt, ctx.layout.t_shift
    cnt, first, step_us, tlast_new = _emitted_log(
        n_a, th_a, lref_a, ctx.state.l_prev.view(-1).index_select(0, act), l1_a, dt, tl_a, r, ctx.spacing_may_bind)
    # cnt holds whole numbers: compared as float64, converted only for the multi pixels
    if _cpu_fast_path(cnt):
        n_cnt = ctx.count(cnt)  # before any per-event allocation
        sel = _nonzero_1d(cnt > 0)  # pixels with >= 1 emitted event
        multi = _nonzero_1d(cnt > 1)
    else:  # one host sync for the three sizes, then compactions of known size (no sync)
        n_cnt, n_sel, n_multi = torch.stack([cnt.sum(), (cnt > 0).sum(), (cnt > 1).sum()]).tolist()
        ctx.add(n_cnt)  # before any per-event allocation
        sel, multi = _compact(cnt > 0, int(n_sel)), _compact(cnt > 1, int(n_multi))
    all_sel = sel.numel() == act.numel()
    n_extra = None if n_cnt is None else int(n_cnt) - sel.numel()  # events beyond each pixel's first
    keys = _event_keys(first if all_sel else first.index_select(0, sel),
                       code_a if all_sel else code_a.index_select(0, sel), multi, cnt, first, step_us, code_a, dt,
                       t_shift, n_extra)
    return keys, sel, tlast_new


def _event_keys(first_sel, code_sel, multi, cnt, first, step_us, code, dt: float, t_shift: int,
                n_extra: Optional[int]) -> torch.Tensor:
    """Sort keys (N,) int64 of the events of the pixels with one or more: first the first event of each
    (its time ``first_sel`` µs after the step start, its key bits ``code_sel``, one per such pixel; no
    per-event gather), then the further events of the pixels ``multi`` (indices into ``cnt``, ``first``,
    ``step_us`` and ``code``; :func:`_extra_keys`, ``n_extra`` of them where known). Event times round
    to the nearest µs within (0, dt]."""
    t_first = first_sel.add(0.5).floor_().clamp_(1.0, dt).to(torch.int64)
    parts = [t_first.bitwise_left_shift_(t_shift).add_(code_sel)]
    if multi.numel() > 0:
        parts.append(_extra_keys(multi, cnt, first, step_us, code, dt, t_shift, n_extra))
    return torch.cat(parts) if len(parts) > 1 else parts[0]


def _noise_keys(ctx: _Step, flat: torch.Tensor, t_rel: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
    """Sort keys (see :class:`_KeyLayout`) of noise events: flat pixels, time offsets (µs), OFF flags."""
    return ctx.layout.pixel_key(flat, off, ctx.b_shift).add_(t_rel << ctx.layout.t_shift)


def _background(ctx: _Step, step: torch.Tensor, counts) -> torch.Tensor:
    """Sort keys of this step's background events (:func:`pixel_model.draw_background`: Poisson count
    per descent, uniform pixel, time and polarity, drawn from the descent's seed and step);
    ``counts`` the count draw of :func:`_background_counts` with its total, read already (the
    rate is in them)."""
    H, W = ctx.state.lref.shape[1:]
    flat, t_rel, off = pm.draw_background(ctx.state.seed, step, None, H * W, int(ctx.dt), counts)
    ctx.add(float(flat.numel()))  # a size already on the host
    return _noise_keys(ctx, flat, t_rel, off)


def _shot_noise(ctx: _Step, f1: torch.Tensor, step: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """This step's shot-noise events (:func:`pixel_model.draw_shot_noise`, irradiance ``f1`` (B, H, W)
    float64): flat pixel indices (N,) int64 and sort keys (N,) int64."""
    flat, t_rel, off = pm.draw_shot_noise(ctx.state.seed, step, f1, int(ctx.dt), ctx.params.pixel_model)
    return flat, _noise_keys(ctx, flat, t_rel, off)


# ------------------------------------------------------------------------ the object
class EventEmulator:
    """Batched DVS emulator: frames (B, H, W) of linear irradiance -> :class:`Events`.

    The stage contract (:mod:`dvsland.pytree`): :meth:`init_state`, :meth:`step_state` (pure: the
    module-level :func:`emulator_step`) and :meth:`reset_where` over an :class:`EmulatorState`, with
    the settings in :attr:`params` (:class:`EmulatorParams`). :meth:`reset` / :meth:`step` are the
    object API on top of it, holding one state (:attr:`state`).

    Args:
        threshold: ON contrast threshold θ_on in log intensity, > 0.
        threshold_off: OFF threshold θ_off, > 0; None = ``threshold``.
        refractory_us: refractory period r, µs, >= 0.
        log_eps: ε in L = log(I + ε), > 0.
        interpolation: "log" (interpolate L in time) or "linear" (interpolate I).
        device: device of the state and the output; None = device of the frames given to reset.
        mismatch_sigma: relative std. dev. of per-pixel threshold mismatch, >= 0 (0 = ideal).
        background_rate_hz: background events per pixel per second, >= 0 (0 = ideal).
        seed: seed of mismatch, background activity and the pixel-model noise: descent b's noise
            seed is ``(seed * 1000003 + b) mod 2^63`` unless ``element_seeds`` or ``init_state``'s
            ``seed`` give it (counter-based draws: :mod:`dvsland.events.pixel_model`).
        photoreceptor_cutoff_hz: with full_irradiance, shot_noise_rate_hz, shot_noise_bright_factor,
            leak_rate_hz, leak_rate_sigma, hot_pixel_fraction and hot_pixel_rate_hz: the non-ideal
            pixel parts, see :class:`dvsland.events.pixel_model.PixelModelParams` (all off by default).
        max_events_per_step: most events one :meth:`step` may emit (all cameras together); a
            step that would emit more raises ValueError naming ``emulator.max_events_per_step``
            before its events are allocated (about 48 bytes each at the peak); the state is then
            unchanged. None = no cap.
        max_events_per_descent: a step of B descents may emit up to this times B events when that is
            more than ``max_events_per_step`` (so the cap grows with a large batch); 0 = off.
        denoise, denoise_*: the front-end filters (:class:`dvsland.events.denoise.EventDenoiser`).
        compile: "auto", "true" or "false" (``emulator.compile``): the torch path's pixel step (log
            interpolation) over every pixel at once through ``torch.compile``
            (:mod:`dvsland.events.emulator_dense`); "auto" = on a CUDA device. The CPU's compiled kernel
            runs regardless where it is built.

    Usage::

        emu = EventEmulator(threshold=0.1, refractory_us=15.0)
        emu.reset(frames0, t_us=0)            # (B, H, W), no events
        ev = emu.step(frames1, t_us=100_000)  # events in (0, 100000]
        # or, as data:
        st = emu.init_state(frames0, 0)
        st, ev = emu.step_state(st, frames1, 100_000)
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
                 denoise_refractory_us: float = 1_000.0, denoise_hot_pixel_rate_hz: float = 50.0,
                 max_events_per_descent: int = 0, compile: str = "false"):
        denoiser = EventDenoiser(denoise, denoise_baf_time_us, denoise_baf_neighbours, denoise_refractory_us,
                                 denoise_hot_pixel_rate_hz)
        #: the settings (:class:`EmulatorParams`); per-element values of set_element_params join at reset
        self.params = make_params(
            threshold, threshold_off, refractory_us, log_eps, interpolation, device, mismatch_sigma,
            background_rate_hz, seed, max_events_per_step, denoiser, photoreceptor_cutoff_hz=photoreceptor_cutoff_hz,
            full_irradiance=full_irradiance, shot_noise_rate_hz=shot_noise_rate_hz,
            shot_noise_bright_factor=shot_noise_bright_factor, leak_rate_hz=leak_rate_hz,
            leak_rate_sigma=leak_rate_sigma, hot_pixel_fraction=hot_pixel_fraction,
            hot_pixel_rate_hz=hot_pixel_rate_hz, max_events_per_descent=max_events_per_descent, compile=compile)
        #: the state the object API holds (None before :meth:`reset`)
        self.state: Optional[EmulatorState] = None

    def set_element_params(self, threshold_scale=None, mismatch_sigma=None, background_rate_hz=None,
                           refractory_us=None, element_seeds=None) -> None:
        """Per-element sensor values (a Monte Carlo batch's dispersions), each (B,) or None (the
        scalar of the constructor). ``threshold_scale`` multiplies both thresholds;
        ``element_seeds`` (B,) int: each descent's noise seed (mismatch map, background, pixel
        noise; default: derived from ``seed`` and the index). They become part of ``params`` now:
        per-pixel maps (mismatch, thresholds) are drawn by the next :meth:`reset` /
        :meth:`init_state`, per-step values (refractory period, background rate) apply from the next
        step; per-element refractory periods need ``interpolation="log"``."""
        self.params = with_element_params(self.params, threshold_scale, mismatch_sigma, background_rate_hz,
                                          refractory_us, element_seeds)

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
                   max_events_per_descent=getattr(cfg, "max_events_per_descent", 0),
                   compile=getattr(cfg, "compile", "false"),
                   **{k: getattr(cfg, k) for k in _DENOISE_KEYS if hasattr(cfg, k)})

    # ------------------------------------------------------------------ the stage contract
    def init_state(self, frames: torch.Tensor, t_us: int, seed: Optional[torch.Tensor] = None) -> EmulatorState:
        """A fresh state on ``frames`` (B, H, W) at ``t_us`` (:func:`emulator_init`), drawing the
        per-element maps of :meth:`set_element_params`."""
        return emulator_init(self.params, frames, t_us, seed)

    def step_state(self, state: EmulatorState, frames: torch.Tensor, t_us: int,
                   donate: bool = False) -> Tuple[EmulatorState, Events]:
        """(new state, events in (t_prev, t_us]) (:func:`emulator_step`); ``state`` is not written
        unless ``donate``."""
        return emulator_step(self.params, state, frames, t_us, donate)

    def reset_where(self, state: EmulatorState, mask: torch.Tensor, frames: torch.Tensor, t_us: int,
                    seed: Optional[torch.Tensor] = None) -> EmulatorState:
        """``state`` with the descents of ``mask`` (B,) bool restarted on ``frames`` at ``t_us``, the
        others bit-identical (:func:`emulator_reset_where`)."""
        return emulator_reset_where(self.params, state, mask, frames, t_us, seed)

    # ------------------------------------------------------------------ the object API
    def reset(self, frames: torch.Tensor, t_us: int) -> None:
        """Start (or restart) all pixels: L_ref = log(frames + eps) at time ``t_us``; no events.

        Args:
            frames: (B, H, W) floating, linear irradiance, finite, >= 0.
            t_us: int, µs.
        """
        self.state = self.init_state(frames, t_us)

    def step(self, frames: torch.Tensor, t_us: int) -> Events:
        """Advance to ``t_us`` with new frames; return the events in (t_prev, t_us], sorted by (b, t).

        Args:
            frames: (B, H, W) floating, linear irradiance, finite, >= 0, same shape as at reset.
            t_us: int µs, > the previous time.

        Returns:
            :class:`Events` on the emulator's device, sorted by (b, t), ties by row-major pixel
            (exact ties of noise events with pixel events: by pixel, then OFF after ON).
        """
        if self.state is None:
            raise RuntimeError("EventEmulator.step called before reset(frames, t_us)")
        self.state, ev = emulator_step(self.params, self.state, frames, t_us)
        return ev

    # ------------------------------------------------------------------ settings and state, read
    def __getattr__(self, name):
        # the settings read as attributes (threshold, refractory_us, pixel_model, ...)
        if name not in ("params", "state") and name in _PARAM_NAMES:
            return getattr(self.params, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def __setattr__(self, name, value):
        if name in _PARAM_NAMES:
            raise AttributeError(f"EventEmulator.{name} is a setting, frozen in EventEmulator.params "
                                 f"(EmulatorParams): build a new emulator with it")
        object.__setattr__(self, name, value)

    @property
    def device(self) -> Optional[torch.device]:
        """The state's device (the constructor's, else that of the frames given to reset)."""
        return self.state.lref.device if self.state is not None else self.params.device

    @property
    def t_us(self) -> Optional[int]:
        """µs of the last frame (None before reset)."""
        return None if self.state is None else int(self.state.t_us.max())

    @property
    def batch_size(self) -> int:
        return int(self.state.lref.shape[0]) if self.state is not None else 0

    @property
    def sensor_hw(self) -> Tuple[int, int]:
        """(H, W) of the frames given to :meth:`reset`."""
        return tuple(self.state.lref.shape[1:]) if self.state is not None else (0, 0)

    @property
    def reference(self) -> torch.Tensor:
        """(B, H, W) float64: per-pixel reference log level L_ref."""
        return self.state.lref

    @property
    def photoreceptor_level(self) -> torch.Tensor:
        """(B, H, W) float64: the low-pass filtered log level (without leak drift); the plain
        log level of the last frame when the photoreceptor is ideal."""
        return photoreceptor_level(self.state)

    @property
    def leak_rate_hz_map(self) -> Optional[torch.Tensor]:
        """(B, H, W) float64 per-pixel leak rate, Hz, hot pixels included (None: leak off)."""
        return self.state.leak_rate_hz

    @property
    def hot_pixels(self) -> Optional[torch.Tensor]:
        """(B, H, W) bool hot-pixel mask (None: leak and hot pixels off)."""
        return self.state.hot_pixels

    @property
    def leak_phase(self) -> Optional[torch.Tensor]:
        """(B, H, W) float64 initial phase of the leak, in thresholds (None: off)."""
        return self.state.leak_phase

    # the state's fields under their former attribute names (benchmarks and tests read them)
    _lref = property(lambda self: self.state.lref)
    _l_prev = property(lambda self: self.state.l_prev)
    _t_last = property(lambda self: self.state.t_last)
    _th_on = property(lambda self: self.params.threshold if self.state.th_on is None else self.state.th_on)
    _th_off = property(lambda self: self.params.threshold_off if self.state.th_off is None else self.state.th_off)


_PARAM_NAMES = frozenset(f.name for f in dataclasses.fields(EmulatorParams)) - {"device"}


def photoreceptor_level(state: EmulatorState) -> torch.Tensor:
    """(B, H, W) float64: the low-pass filtered log level without the leak drift (the plain log level
    of the last frame when the photoreceptor is ideal)."""
    if state.l_lp is not None:
        return state.l_lp
    if state.drift is not None:
        el = (state.t_us - state.t_reset_us).to(torch.float64).view(-1, 1, 1)
        return state.l_prev - state.drift * el
    return state.l_prev


__all__ = ["EventEmulator", "EmulatorParams", "EmulatorState", "emulator_init", "emulator_step",
           "emulator_reset_where", "make_params", "with_element_params", "check_state", "photoreceptor_level",
           "compiled_pixel_step", "LEVEL_TOL"]

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
    if not _cpu_fast_path(n_a):  # the closed form everywhere, kept where it binds: no host sync
        return emitted_dense(n_a, th_a, lref_a, l0_a, l1_a, dt, tl_a, r, spacing_may_bind)
    base, spacing, first = crossing_times(th_a, lref_a, l0_a, l1_a, dt)
    cnt, step = n_a, spacing  # without refractory: all n crossings
    r_t = r if isinstance(r, torch.Tensor) else None  # per-pixel refractory (A,) or a scalar
    if r_t is not None or r > 0:
        # the refractory rule can only bind where crossings are closer than r, or the first one is
        # within r of the last emitted event: its closed form on those only (compacted)
        need = _nonzero_1d(refractory_binds(first, spacing, tl_a, r, spacing_may_bind))
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


def _extra_keys(multi, cnt, first, step_us, code_a, dt: float, t_shift: int,
                n_extra: Optional[int] = None) -> torch.Tensor:
    """Keys of the 2nd, 3rd, ... events of the pixels ``multi`` (indices into the candidates):
    event i of pixel a is at first[a] + i * step_us[a], i = 1..cnt[a]-1. A function of its own
    so that its per-event temporaries are freed on return; in-place ops keep the number of
    fresh (N,) allocations (page faults dominate at tens of millions of events) low. ``n_extra``,
    their number where the caller knows it, spares the host sync of sizing the output."""
    reps = cnt.index_select(0, multi).to(torch.int64).sub_(1)  # cnt: (A,) float64 whole numbers
    seg = multi.repeat_interleave(reps, output_size=n_extra)  # candidate index per event
    start = torch.cumsum(reps, 0).sub_(reps)
    i = torch.arange(1, seg.numel() + 1, device=seg.device).sub_(start.repeat_interleave(reps, output_size=seg.numel()))
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


def _compact(mask: torch.Tensor, n: int) -> torch.Tensor:
    """Indices (int64, ascending) of the ``n`` True entries of a 1-D bool ``mask``, ``n`` read by the
    caller already: the same as ``nonzero`` without its host sync. A prefix sum ranks the True
    entries first and the False ones after them, and one scatter of that permutation (every index
    written once) puts each entry at its rank."""
    csum = torch.cumsum(mask, 0)
    i = torch.arange(mask.numel(), device=mask.device)
    rank = torch.where(mask, csum - 1, n + i - csum)
    return torch.empty_like(i).scatter_(0, rank, i)[:n]


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


@functools.lru_cache(maxsize=None)
def _numpy_sorts_faster() -> bool:
    """Whether numpy's in-place sort of int64 beats torch.sort with one thread on this machine.

    Measured once per process on 65,536 random keys (about 1 ms). numpy >= 2 sorts int64 with
    x86-simd-sort where the CPU has AVX2 / AVX-512: 2.1 against torch's 14.5 ms of CPU for 295 k
    keys on this toolkit's 2-core Xeon; without those units its introsort is slower than torch's
    radix sort. The sorted values are the same either way (a sort of values, no permutation)."""
    keys = np.random.default_rng(0).integers(0, 1 << 50, size=1 << 16)
    t_np = t_torch = float("inf")
    for _ in range(3):
        a = keys.copy()
        t0 = time.perf_counter()
        a.sort()
        t1 = time.perf_counter()
        torch.sort(torch.from_numpy(keys))
        t2 = time.perf_counter()
        t_np, t_torch = min(t_np, t1 - t0), min(t_torch, t2 - t1)
    return t_np < t_torch


def _sort_values(keys: torch.Tensor) -> torch.Tensor:
    """The int64 keys sorted (a new tensor, or ``keys`` sorted in place). On CPU numpy's
    single-threaded sort in place where it is the faster (:func:`_numpy_sorts_faster`), and
    always with several torch threads, because torch's parallel sort of one 1-D tensor took
    275 ms wall (186 ms CPU) against 7 ms with one thread on a shared 2-core machine (load 6.6);
    else torch.sort (a radix sort)."""
    if _cpu_fast_path(keys) and (torch.get_num_threads() > 1 or _numpy_sorts_faster()):
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
