"""Non-ideal parts of the DVS pixel model: photoreceptor bandwidth, shot noise, leak, hot pixels.

Each part is off at its default (the paper preset uses the ideal pixel) and is switched on by one
parameter of :class:`PixelModelParams` (the ``emulator`` section of the config carries the same
names). They follow v2e (Hu, Liu, Delbruck 2021) where it is stated, and say so where not:

- **Photoreceptor bandwidth** (``photoreceptor_cutoff_hz`` > 0): the log intensity seen by the
  change detector is a first-order low-pass of ``L = log(I + eps)`` whose cut-off is proportional
  to the irradiance, ``f_c(I) = f_max * min(1, I / full_irradiance)`` (darker pixels are slower;
  v2e makes the same proportionality). Discretised exactly for an input held over the frame
  interval: ``L_lp <- L_lp + alpha (L - L_lp)``, ``alpha = 1 - exp(-2 pi f_c(I1) dt)`` with I1 the
  new frame (v2e uses the Euler step ``alpha = 2 pi f_c dt`` clamped to 1). Between frames the
  filtered level is interpolated linearly, like the ideal model's L.
- **Shot noise** (``shot_noise_rate_hz`` > 0): Poisson events per pixel, ON and OFF equally
  likely, uniform time in the interval, at rate
  ``r(I) = r_dark * (1 + (k - 1) * min(1, I1 / full_irradiance))``, ``k = shot_noise_bright_factor``
  (v2e: k = 0.25, darker pixels are noisier). A shot event resets the pixel's reference to its
  current level at the end of the interval (as v2e does), so a static pixel does not answer it
  with an opposite event. Shot events are not subject to the refractory period and do not start
  one (as v2e). Drawn by thinning: candidates at the dark rate ``r_dark * max(1, k)`` over all
  pixels, each kept with probability ``r(I) / (r_dark max(1, k))``: cost proportional to the
  events, not to the pixels.
- **Leak** (``leak_rate_hz`` > 0): junction leakage lowers each pixel's reference at
  ``rho_i * theta_on_i`` per second, so a static pixel emits ON events at ``rho_i`` Hz;
  ``rho_i = leak_rate_hz * max(0, 1 + leak_rate_sigma * N(0, 1))`` drawn per pixel at reset. The
  reference starts a random fraction ``u_i ~ U[0, 1)`` of a threshold below the level, so leak
  events of equal-rate pixels are not synchronous (v2e draws log-normal rates instead, and
  dropped this phase). Implemented as a drift added to the log level,
  ``L'(t) = L(t) + rho_i theta_on_i (t - t_reset)``, which keeps the path linear within each
  interval, so the exact crossing times of the ideal model still hold.
- **Hot pixels** (``hot_pixel_fraction`` > 0): that fraction of pixels (Bernoulli per pixel at
  reset) leak ``hot_pixel_rate_hz`` faster: regular ON events at that rate on a static scene.

Randomness as data: every draw is a counter-based hash (:func:`dvsland.pytree.hash_bits`) of the
descent's seed, its step counter, the part's stream tag, a sub-stream and the pixel (or the event's
rank within its descent), computed with torch ops on the tensors' device: the same draws on CPU and
CUDA, and a descent's noise does not depend on its batch-mates or the batch size. Draws at a
descent's start (mismatch, leak rates, hot pixels, phases) use step 0; a step's draws (background
and shot noise) the step's counter. Poisson counts are inverse-CDF draws of one hashed uniform per
descent and step (:func:`poisson_inverse_cdf`), then each event's pixel, time and uniform are
hashed: the cost is proportional to the events, not the pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Tuple

import numpy as np
import torch

from dvsland.pytree import hash_bits, hash_normal, hash_uniform

#: stream tags of the draws (one independent stream per part, :func:`stream_keys`)
TAG_SHOT, TAG_LEAK, TAG_BACKGROUND, TAG_MISMATCH = 0x5807, 0x1EA4, 0xBAC6, 0x3A7C


@dataclass(frozen=True)
class PixelModelParams:
    """Parameters of the non-ideal pixel parts (all off at their defaults).

    Attributes:
        photoreceptor_cutoff_hz: low-pass cut-off at ``full_irradiance`` and above, Hz; 0 = off.
        full_irradiance: irradiance at which the intensity-dependent parts reach their bright
            value (cut-off f_max, shot-noise factor k), in the renderer's units (1 = an albedo-1
            plate facing the sun), > 0.
        shot_noise_rate_hz: shot-noise events per pixel per second (ON + OFF) in the dark; 0 = off.
        shot_noise_bright_factor: shot-noise rate at ``full_irradiance`` relative to the dark rate
            (v2e: 0.25), >= 0.
        leak_rate_hz: mean leak (ON) events per pixel per second on a static scene; 0 = off.
        leak_rate_sigma: relative std. dev. of the per-pixel leak rate, >= 0.
        hot_pixel_fraction: fraction of hot pixels, in [0, 1]; 0 = off.
        hot_pixel_rate_hz: extra ON rate of a hot pixel, Hz, >= 0.
    """

    photoreceptor_cutoff_hz: float = 0.0
    full_irradiance: float = 1.0
    shot_noise_rate_hz: float = 0.0
    shot_noise_bright_factor: float = 0.25
    leak_rate_hz: float = 0.0
    leak_rate_sigma: float = 0.1
    hot_pixel_fraction: float = 0.0
    hot_pixel_rate_hz: float = 100.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"{f.name} must be a number, got {v!r}") from None
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{f.name} must be a finite number >= 0, got {v}")
            object.__setattr__(self, f.name, v)
        if self.full_irradiance <= 0:
            raise ValueError(f"full_irradiance must be > 0, got {self.full_irradiance}")
        if self.hot_pixel_fraction > 1:
            raise ValueError(f"hot_pixel_fraction must be in [0, 1], got {self.hot_pixel_fraction}")

    @property
    def lowpass(self) -> bool:
        return self.photoreceptor_cutoff_hz > 0

    @property
    def shot(self) -> bool:
        return self.shot_noise_rate_hz > 0

    @property
    def drift(self) -> bool:
        """Leak or hot pixels: a per-pixel reference drift."""
        return self.leak_rate_hz > 0 or (self.hot_pixel_fraction > 0 and self.hot_pixel_rate_hz > 0)

    @property
    def any(self) -> bool:
        return self.lowpass or self.shot or self.drift


def element_seed(seed: int, b: int, tag: int) -> int:
    """Seed of batch element ``b``'s stream ``tag`` (a 63-bit mix of the three integers)."""
    x = (int(seed) * 0x9E3779B97F4A7C15 + int(b) * 0xBF58476D1CE4E5B9 + int(tag) * 0x94D049BB133111EB)
    x &= (1 << 64) - 1
    x ^= x >> 31
    return x & ((1 << 63) - 1)


# ----------------------------------------------------------------- photoreceptor bandwidth
def photoreceptor_alpha(irradiance: torch.Tensor, dt_s: float, cutoff_hz: float,
                        full_irradiance: float = 1.0) -> torch.Tensor:
    """Low-pass update weight per pixel, ``1 - exp(-2 pi f_c(I) dt)``.

    Args:
        irradiance: (...) float, linear irradiance I >= 0 of the new frame.
        dt_s: frame interval, s.
        cutoff_hz: f_max, Hz (> 0).
        full_irradiance: I at and above which f_c = f_max.

    Returns:
        (...) same dtype, in [0, 1].
    """
    w = -2.0 * math.pi * cutoff_hz * dt_s
    return irradiance.mul(w / full_irradiance).clamp_(min=w).expm1_().neg_()


def photoreceptor_lowpass_(l_lp: torch.Tensor, l_new: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """In place: ``l_lp += alpha * (l_new - l_lp)`` ((B, H, W) float64). Returns ``l_lp``."""
    return l_lp.lerp_(l_new, alpha)


def shot_noise_rate_hz(irradiance: torch.Tensor, rate_dark_hz: float, bright_factor: float,
                       full_irradiance: float = 1.0) -> torch.Tensor:
    """Shot-noise rate per pixel (ON + OFF), Hz: ``r_dark (1 + (k - 1) min(1, I / I_full))``."""
    x = irradiance.to(torch.float64).div(full_irradiance).clamp(0.0, 1.0)
    return x.mul_(bright_factor - 1.0).add_(1.0).mul_(rate_dark_hz)


# ------------------------------------------------------------------------- random draws
#: inverse-CDF Poisson draws are exact (a table of the CDF) for means up to this; above it, the
#: normal approximation ``floor(lam + sqrt(lam) z + 1/2)`` (continuity-corrected; its error in the
#: distribution is O(1 / sqrt(lam)), under 1 % of a standard deviation here)
POISSON_EXACT_MAX = 64.0


def stream_keys(seed: torch.Tensor, step, tag: int, stream: int = 0) -> torch.Tensor:
    """Per-descent keys of one random stream: (B,) int64, ``hash_bits(seed, step, tag, stream) << 32``.

    Args:
        seed: (B,) int64, each descent's noise seed.
        step: (B,) int64 (or an int), the descent's step counter (0 for the draws at its start).
        tag: the part (:data:`TAG_SHOT`, ...); stream: a sub-stream of the part.

    A draw's key is then ``stream_keys(...) | index`` with ``index`` (< 2^32) the pixel or the
    event's rank within its descent, hashed once more (:func:`keyed_uniform`): the draws of a
    descent depend on its own (seed, step, tag, stream, index) only, on every device.
    """
    if not isinstance(step, int):
        step = torch.as_tensor(step, dtype=torch.int64, device=seed.device)
    return hash_bits(seed, step, int(tag), int(stream)) << 32


def keyed_uniform(keys: torch.Tensor) -> torch.Tensor:
    """Uniform float64 draws in (0, 1), one per int64 key (see :func:`stream_keys`)."""
    return hash_uniform(keys)


def keyed_normal(keys: torch.Tensor) -> torch.Tensor:
    """Standard normal float64 draws, one per int64 key (see :func:`stream_keys`)."""
    return hash_normal(keys)


def pixel_draws(seed: torch.Tensor, shape: Tuple[int, int, int], tag: int, stream: int,
                normal: bool = False) -> torch.Tensor:
    """One draw per pixel of each descent, (B, H, W) float64 on ``seed``'s device: uniform in (0, 1)
    or standard normal; descent b's draws depend on ``seed[b]`` only (made at a descent's start)."""
    B, H, W = shape
    base = stream_keys(seed, 0, tag, stream).view(B, 1, 1)
    keys = base | torch.arange(H * W, dtype=torch.int64, device=seed.device).view(1, H, W)
    return keyed_normal(keys) if normal else keyed_uniform(keys)


def poisson_inverse_cdf(lam: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Poisson counts (int64) of means ``lam`` (float64, >= 0) from uniforms ``u`` in (0, 1), same shape
    (1-D): the smallest k with CDF(k) >= u, exact (a CDF table) for ``lam <= POISSON_EXACT_MAX``,
    the continuity-corrected normal approximation above it. Vectorised: no loop over elements."""
    lam = lam.to(torch.float64)
    small = lam <= POISSON_EXACT_MAX
    k_max = int(POISSON_EXACT_MAX + 12.0 * math.sqrt(POISSON_EXACT_MAX) + 16.0)
    k = torch.arange(k_max, dtype=torch.float64, device=lam.device)
    ls = torch.where(small, lam, torch.zeros_like(lam)).unsqueeze(1)
    logp = torch.xlogy(k, ls) - ls - torch.lgamma(k + 1.0)  # xlogy: 0 log 0 = 0
    cdf = torch.cumsum(torch.exp(logp), dim=1)
    n_small = (cdf < u.unsqueeze(1)).sum(dim=1)
    z = torch.erfinv(u.mul(2.0).sub_(1.0)).mul_(math.sqrt(2.0))
    n_big = torch.floor(lam + lam.sqrt() * z + 0.5).clamp_(min=0.0).to(torch.int64)
    return torch.where(small, n_small, n_big)


#: index of a descent's count draw within its step's stream (event k uses 2k and 2k + 1)
_COUNT_INDEX = 0xFFFFFFFF


def uniform_counts(seed: torch.Tensor, step: torch.Tensor, lam: torch.Tensor, tag: int):
    """The first draw of :func:`uniform_events`: (the stream's keys (B,) int64, each descent's
    Poisson event count (B,) int64), with no host sync (the total is the caller's to read)."""
    base = stream_keys(seed, step, tag)
    return base, poisson_inverse_cdf(lam, keyed_uniform(base | _COUNT_INDEX))


def uniform_events(seed: torch.Tensor, step: torch.Tensor, lam: torch.Tensor, n_pix: int, dt_us: int,
                   tag: int, counts=None) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Poisson events uniform in pixel and integer time, each descent its own mean count.

    Args:
        seed, step: (B,) int64, the descents' seeds and step counters (keys of the draws).
        lam: (B,) float64, mean number of events of each descent over its ``n_pix`` pixels and the
            interval (rate per pixel x interval x pixels): a Poisson process uniform over pixels
            and time, i.e. independent Poisson counts per pixel of mean ``lam / n_pix``.
        n_pix: pixels per descent (< 2^31); dt_us: interval, µs.
        tag: the part's stream tag.
        counts: (keys, counts, their total as an int) of :func:`uniform_counts` for these
            arguments, when the caller has read the total already (no sync here; ``lam`` is then
            not read and may be None); None = drawn here.

    Returns:
        (N,) each, on ``seed``'s device: flat index ``b * n_pix + pixel`` int64, time offset int64 µs
        in [1, dt_us], and a uniform float64 in [0, 1) (for thinning and polarity).

    Draws: the count of each descent is an inverse-CDF draw (:func:`poisson_inverse_cdf`) of the
    uniform of key (seed, step, tag, 2^32 - 1); its k-th event's pixel is ``(h * n_pix) >> 32`` of
    the 32 hashed bits h of key (seed, step, tag, 2k), and its time and uniform the integer and
    fractional parts of ``v dt_us``, v the uniform of key (seed, step, tag, 2k + 1) (so the uniform
    has a resolution of dt_us / 2^32: 2.3e-5 at 100 ms). Independent of the batch-mates.
    """
    B, dev = seed.shape[0], seed.device
    if counts is None:
        base, n = uniform_counts(seed, step, lam, tag)
        total = int(n.sum())  # sync: the events' count
    else:
        base, n, total = counts
    if total == 0:
        e = torch.empty(0, dtype=torch.int64, device=dev)
        return e, e.clone(), torch.empty(0, dtype=torch.float64, device=dev)
    b = torch.repeat_interleave(torch.arange(B, device=dev), n, output_size=total)
    k2 = torch.arange(total, device=dev).sub_((torch.cumsum(n, 0) - n).index_select(0, b)).mul_(2)
    key = base.index_select(0, b).bitwise_or_(k2)
    flat = hash_bits(key).mul_(int(n_pix)).bitwise_right_shift_(32).add_(b * n_pix)
    v = keyed_uniform(key.add_(1)).mul_(int(dt_us))
    t = torch.floor(v)
    u = v.sub_(t)
    return flat, t.clamp_(max=int(dt_us) - 1).to(torch.int64).add_(1), u


def background_lam(seed: torch.Tensor, rate_hz, n_pix: int, dt_us) -> torch.Tensor:
    """(B,) float64 mean background events of each descent over its ``n_pix`` pixels and ``dt_us``
    (an int, or a (B,) int64 tensor: the same values, computed on the device)."""
    rate = torch.as_tensor(rate_hz, dtype=torch.float64, device=seed.device).expand(seed.shape[0])
    if isinstance(dt_us, torch.Tensor):
        return rate * (dt_us.to(torch.float64) * 1e-6 * n_pix)
    return rate * (int(dt_us) * 1e-6 * n_pix)


def draw_background(seed: torch.Tensor, step: torch.Tensor, rate_hz, n_pix: int, dt_us: int, counts=None):
    """Uniform background events (:func:`uniform_events` at ``rate_hz`` per pixel, a float or (B,)
    float64): flat pixel index, time offset (µs, in [1, dt_us]), OFF flag (probability 1/2).
    ``counts``: :func:`uniform_counts` of :func:`background_lam` with ``TAG_BACKGROUND`` and its
    total, where the caller read it already; the rate is then in the counts (``rate_hz`` may be
    None, and no mean is computed again)."""
    if counts is None:
        if rate_hz is None:
            raise ValueError("draw_background: rate_hz must be given without counts")
        lam = background_lam(seed, rate_hz, n_pix, dt_us)
    else:
        lam = None  # the counts are drawn: uniform_events reads no mean
    flat, t_rel, u = uniform_events(seed, step, lam, n_pix, dt_us, TAG_BACKGROUND, counts)
    return flat, t_rel, u < 0.5


def draw_shot_noise(seed: torch.Tensor, step: torch.Tensor, irradiance: torch.Tensor, dt_us: int,
                    params: PixelModelParams):
    """Shot-noise events of one interval by thinning.

    Candidates come at ``r_max = r_dark * max(1, k)`` per pixel (:func:`uniform_events`); the
    candidate's uniform u keeps it when ``u < q = r(I) / r_max`` and makes it OFF when ``u < q / 2``
    (given kept, u is uniform on [0, q): OFF with probability 1/2, independent of the rate).

    Args:
        seed, step: (B,) int64, the descents' seeds and step counters.
        irradiance: (B, H, W) linear irradiance of the new frame.
        dt_us: interval length, µs.
        params: the rate parameters.

    Returns:
        flat pixel index ``(b * H + y) * W + x`` (N,) int64, time offset (N,) int64 µs in [1, dt_us],
        OFF flag (N,) bool, on ``irradiance``'s device (not sorted).
    """
    B, H, W = irradiance.shape
    k = params.shot_noise_bright_factor
    r_max = params.shot_noise_rate_hz * max(1.0, k)
    lam = torch.full((B,), r_max * int(dt_us) * 1e-6 * H * W, dtype=torch.float64, device=seed.device)
    flat, t_rel, u = uniform_events(seed, step, lam, H * W, dt_us, TAG_SHOT)
    if flat.numel():
        # q = r(I) / r_max = a + c min(1, I / I_full), a = r_dark / r_max, c = a (k - 1)
        a = params.shot_noise_rate_hz / r_max
        q = irradiance.reshape(-1).index_select(0, flat).to(torch.float64).mul_(1.0 / params.full_irradiance)
        q = q.clamp_(max=1.0).mul_(a * (k - 1.0)).add_(a)
        off = u < q.mul(0.5)
        if a * min(1.0, k) < 1.0:  # some candidates may be dropped
            keep = _nonzero_idx(u < q)
            flat, t_rel, off = (t.index_select(0, keep) for t in (flat, t_rel, off))
        return flat, t_rel, off
    return flat, t_rel, torch.empty(0, dtype=torch.bool, device=flat.device)


def _nonzero_idx(mask: torch.Tensor) -> torch.Tensor:
    if mask.device.type == "cpu":
        return torch.from_numpy(np.flatnonzero(mask.numpy()))
    return torch.nonzero(mask).squeeze(1)


# --------------------------------------------------------------------- leak and hot pixels
def draw_leak_state(seed: torch.Tensor, shape: Tuple[int, int, int], params: PixelModelParams
                    ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-pixel leak rate, hot-pixel mask and initial phase of each descent (at its start).

    Args:
        seed: (B,) int64, the descents' seeds (draws of key (seed, 0, :data:`TAG_LEAK`, stream, pixel)).
        shape: (B, H, W).

    Returns (B, H, W) on ``seed``'s device: rate_hz float64 (leak rate, plus ``hot_pixel_rate_hz``
    on hot pixels), hot bool, phase float64 in (0, 1) (fraction of a threshold the reference
    starts below the level).
    """
    n = pixel_draws(seed, shape, TAG_LEAK, 0, normal=True)
    phase = pixel_draws(seed, shape, TAG_LEAK, 2)
    rate = n.mul_(params.leak_rate_sigma).add_(1.0).clamp_(min=0.0).mul_(params.leak_rate_hz)
    if params.hot_pixel_fraction > 0:
        hot = pixel_draws(seed, shape, TAG_LEAK, 1) < params.hot_pixel_fraction
    else:
        hot = torch.zeros(shape, dtype=torch.bool, device=seed.device)
    rate += hot.to(torch.float64) * params.hot_pixel_rate_hz
    return rate, hot, phase


# ------------------------------------------------------------------- threshold mismatch
def draw_mismatch(seed: torch.Tensor, sigma: torch.Tensor, shape: Tuple[int, int, int]) -> torch.Tensor:
    """Relative ON/OFF threshold maps (B, 2, H, W) float64: ``1 + sigma[b] N(0, 1)`` clamped at 0.01,
    all ones where ``sigma[b]`` (B,) float64 is 0; descent b's maps depend on ``seed[b]`` only."""
    on = pixel_draws(seed, shape, TAG_MISMATCH, 0, normal=True)
    off = pixel_draws(seed, shape, TAG_MISMATCH, 1, normal=True)
    sig = sigma.to(torch.float64).view(-1, 1, 1, 1)
    rel = torch.stack((on, off), dim=1).mul_(sig).add_(1.0).clamp_(min=0.01)
    return torch.where(sig > 0, rel, torch.ones_like(rel))


__all__ = ["PixelModelParams", "element_seed", "photoreceptor_alpha", "photoreceptor_lowpass_",
           "shot_noise_rate_hz", "stream_keys", "keyed_uniform", "keyed_normal", "pixel_draws",
           "poisson_inverse_cdf", "uniform_counts", "uniform_events", "background_lam", "draw_shot_noise",
           "draw_background", "draw_leak_state", "draw_mismatch", "POISSON_EXACT_MAX", "TAG_SHOT", "TAG_LEAK",
           "TAG_BACKGROUND", "TAG_MISMATCH"]
