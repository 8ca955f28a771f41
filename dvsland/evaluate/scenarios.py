"""Hard scenarios of the open-loop evaluation: hover starts, slow-downs, feature-poor stretches, noise.

The closed-form descents of :mod:`.trajectory` change D slowly and always have texture and clean
events. A real camera also sees a start from hover (|D| ~ 0.005 1/s, where the scene moves by a
fraction of a pixel per second) that speeds up, a slow-down to hover, stretches with hardly any
texture, and bursts of sensor noise. Each scenario here is a prescribed divergence profile D(t)
over one configured site, flown like the evaluation descents (:func:`.reference.fly_profile` on
``loop_step``), with an optional contrast loss over an altitude band and an optional burst of
uniform noise events, scored in named phases.

Profiles: D(t) is piecewise linear through ``d_knots`` at ``t_knots`` (held after the last), and
z(t) = z0 exp(integral of D), v = D z. Every shipped profile needs a thrust >= 0 and at most
about 0.7 g_moon of extra acceleration (the flight is a lander's, on the Moon): a hover start from
|D| < 0.01 to 0.05 1/s within 3 s is only possible below about 100 m (a = z (dD/dt + D^2) >= -g, -g = -1.62 m/s^2).
"""

from __future__ import annotations

from typing import Any, Dict, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch

from dvsland.events import Events
from dvsland.pytree import has_stage_contract


class Scenario(NamedTuple):
    """One hard scenario (see module doc).

    Attributes:
        name: its name in the report.
        description: one line for the report and the docs.
        site: configured site whose terrain is flown over.
        z0_m: start altitude, m.
        t_knots_s, d_knots: (K,) knots of the piecewise-linear D(t), s and 1/s (D < 0 descending).
        duration_s: length of the scenario, s.
        phases: ((label, t_from_s, t_to_s), ...) scored time ranges (steps with t in [from, to)).
        poor_band_m: (z_lo, z_hi) altitudes where the frames keep only ``poor_contrast`` of their
            contrast about their mean (a dust layer; None = none).
        poor_contrast: the kept fraction of contrast in ``poor_band_m``, in (0, 1].
        noise_s: (t_from, t_to) of a burst of uniform noise events, s (None = none).
        noise_hz: rate of the burst per pixel, events/s.
    """

    name: str
    description: str
    site: str
    z0_m: float
    t_knots_s: Tuple[float, ...]
    d_knots: Tuple[float, ...]
    duration_s: float
    phases: Tuple[Tuple[str, float, float], ...]
    poor_band_m: Optional[Tuple[float, float]] = None
    poor_contrast: float = 1.0
    noise_s: Optional[Tuple[float, float]] = None
    noise_hz: float = 0.0


#: the shipped scenarios, by name
SCENARIOS: Dict[str, Scenario] = {s.name: s for s in (
    Scenario("hover_start", "hover at 100 m (D = -0.005 1/s) for 1 s, speeding up to D = -0.05 1/s within 3 s, then held",
             "D", 100.0, (1.0, 4.0), (-0.005, -0.05), 9.0,
             (("after 1 s", 1.0, 9.0), ("speeding up 1-4 s", 1.0, 4.0), ("held 4-9 s", 4.0, 9.0))),
    Scenario("slow_to_hover", "D = -0.05 1/s at 300 m slowing to D = -0.005 1/s within 3 s, then hovering",
             "B", 300.0, (0.0, 3.0, 6.0), (-0.05, -0.05, -0.005), 12.0,
             (("all", 1.0, 12.0), ("slowing 3-6 s", 3.0, 6.0), ("near hover 6-12 s", 6.0, 12.0))),
    Scenario("feature_poor", "D = -0.05 1/s from 2 km; 1.6-1.0 km seen through dust (5 % of the contrast)",
             "E", 2000.0, (0.0,), (-0.05,), 30.0,
             (("before", 1.0, 9.0), ("poor", 9.9, 18.3), ("after", 18.3, 30.0)),
             poor_band_m=(1000.0, 1600.0), poor_contrast=0.05),
    Scenario("noise_burst", "D = -0.03 1/s from 3 km; a 2 s burst of 20 Hz/pixel noise events at 6-8 s",
             "A", 3000.0, (0.0,), (-0.03,), 20.0,
             (("before", 1.0, 6.0), ("burst", 6.0, 8.0), ("after", 8.0, 20.0)),
             noise_s=(6.0, 8.0), noise_hz=20.0),
)}


def scenario_names() -> Tuple[str, ...]:
    return tuple(SCENARIOS)


def resolve_scenarios(names) -> Tuple[Scenario, ...]:
    """Scenario objects from names ("all", "none", a comma list, or Scenario objects)."""
    if isinstance(names, str):
        names = {"all": list(SCENARIOS), "none": [], "": []}.get(names.strip(), names.split(","))
    out = []
    for n in names or ():
        if isinstance(n, Scenario):
            out.append(n)
            continue
        n = str(n).strip()
        if n not in SCENARIOS:
            raise ValueError(f"scenarios: unknown scenario {n!r}; known: {list(SCENARIOS)} (or 'all', 'none')")
        out.append(SCENARIOS[n])
    return tuple(out)


def divergence_at(sc: Scenario, t_s: np.ndarray) -> np.ndarray:
    """D(t) of ``sc`` (piecewise linear through its knots, held outside), (N,) float64, 1/s."""
    return np.interp(np.asarray(t_s, dtype=np.float64), sc.t_knots_s, sc.d_knots)


def altitude_at(sc: Scenario, t_s: np.ndarray) -> np.ndarray:
    """z(t) = z0 exp(integral_0^t D) of ``sc`` (exact for the piecewise-linear D), (N,) float64, m."""
    t = np.asarray(t_s, dtype=np.float64)
    tk = np.concatenate([[0.0], np.asarray(sc.t_knots_s, dtype=np.float64)])
    dk = divergence_at(sc, tk)
    cum = np.concatenate([[0.0], np.cumsum(np.diff(tk) * 0.5 * (dk[1:] + dk[:-1]))])
    i = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 1)
    return sc.z0_m * np.exp(cum[i] + (t - tk[i]) * 0.5 * (dk[i] + divergence_at(sc, t)))


def scenario_profiles(scs: Sequence[Scenario], dt_s: float) -> Tuple[np.ndarray, np.ndarray, int]:
    """Altitude profiles of the scenarios as one batch: (z_ref (S, N + 2) m, v0 (S,) m/s, N steps),
    N the longest scenario's steps; shorter ones continue their profile past their end (not scored)."""
    n = int(np.ceil(max(s.duration_s for s in scs) / dt_s - 1e-9))
    t = np.arange(n + 2) * dt_s
    z = np.stack([altitude_at(s, t) for s in scs])
    v0 = np.array([s.d_knots[0] * s.z0_m if s.t_knots_s[0] <= 0 else divergence_at(s, [0.0])[0] * s.z0_m
                   for s in scs])
    return z, v0, n


class DustyFrames:
    """A frame source that keeps only ``contrast`` of each frame's contrast about its mean while
    the altitude lies in the element's ``band_m`` (a feature-poor stretch); else the inner frames.

    Args:
        inner: renderer (``render(altitude_m, site_idx)``) or callable with that signature.
        band_m: (B, 2) float64 [z_lo, z_hi] per element, m (NaN = never).
        contrast: (B,) kept fraction of contrast in (0, 1].
    """

    def __init__(self, inner, band_m: torch.Tensor, contrast: torch.Tensor):
        self.inner, self.band_m, self.contrast = inner, band_m, contrast

    def render(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        r = self.inner
        frames = r.render(altitude_m, site_idx) if hasattr(r, "render") else r(altitude_m, site_idx)
        # a call may be for a subset of the batch: the bands are looked up by scene index
        band = self.band_m.to(frames.device)[site_idx]
        k = self.contrast.to(frames.device)[site_idx].to(frames.dtype)
        z = altitude_m.to(band.device, torch.float64)
        poor = (z >= band[:, 0]) & (z <= band[:, 1])
        mean = frames.mean((1, 2), keepdim=True)
        flat = mean + (frames - mean) * k.view(-1, 1, 1)
        return torch.where(poor.view(-1, 1, 1), flat, frames)


class NoisyState(NamedTuple):
    """State of a :class:`NoisyEmulator` under the stage contract: the inner emulator's state and
    the time of the last frame, (B,) int64 µs."""

    inner: Any
    t_prev_us: torch.Tensor


class NoisyEmulator:
    """An emulator whose events gain a burst of uniform noise: in each element's ``window_us``,
    ``rate_hz`` events per pixel and second at uniformly random pixels, times and polarities,
    drawn from a generator seeded by ``seed`` and the step's end time (the same on every run).

    It offers the inner emulator's object API (``reset``/``step``) and, when the inner one has it,
    the stage contract (``init_state``/``step_state``/``reset_where``, state :class:`NoisyState`).
    """

    def __init__(self, inner, window_us: torch.Tensor, rate_hz: torch.Tensor, sensor_size, seed: int = 0):
        self.inner, self.window_us, self.rate_hz = inner, window_us, rate_hz
        self.W, self.H = int(sensor_size[0]), int(sensor_size[1])
        self.seed, self._t_prev = int(seed), None
        if not has_stage_contract(inner):  # the contract only over an inner emulator that has it
            self.init_state = self.step_state = self.reset_where = None

    # ------------------------------------------------------------------ the object API
    def reset(self, frames, t_us: int):
        self._t_prev = int(t_us)
        return self.inner.reset(frames, t_us)

    def set_element_params(self, **kw):
        return self.inner.set_element_params(**kw)

    def step(self, frames, t_us: int) -> Events:
        ev = self.inner.step(frames, t_us)
        t0, self._t_prev = self._t_prev, int(t_us)
        return self._burst(ev, t0, int(t_us))

    # ------------------------------------------------------------------ the stage contract
    def init_state(self, frames, t_us: int, seed=None) -> NoisyState:
        inner = self.inner.init_state(frames, t_us, seed)
        return NoisyState(inner, torch.full((frames.shape[0],), int(t_us), dtype=torch.int64, device=frames.device))

    def step_state(self, state: NoisyState, frames, t_us: int):
        inner, ev = self.inner.step_state(state.inner, frames, t_us)
        t0 = int(state.t_prev_us.max())  # one host read: the batch shares its clock
        return NoisyState(inner, torch.full_like(state.t_prev_us, int(t_us))), self._burst(ev, t0, int(t_us))

    def reset_where(self, state: NoisyState, mask, frames, t_us: int, seed=None) -> NoisyState:
        inner = self.inner.reset_where(state.inner, mask, frames, t_us, seed)
        return NoisyState(inner, torch.where(mask, torch.full_like(state.t_prev_us, int(t_us)), state.t_prev_us))

    def _burst(self, ev: Events, t0: int, t1: int) -> Events:
        """``ev`` with the burst's events of ``(t0, t1]`` merged in (sorted by (b, t))."""
        lo = self.window_us[:, 0].clamp(min=t0)
        hi = self.window_us[:, 1].clamp(max=t1)
        span_s = ((hi - lo).clamp_min(0)).to(torch.float64) * 1e-6
        n = torch.round(self.rate_hz * span_s * self.W * self.H).to(torch.int64)  # (B,)
        total = int(n.sum())
        if total == 0:
            return ev
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + t1)
        b = torch.repeat_interleave(torch.arange(n.numel()), n)
        u = torch.rand(total, generator=g, dtype=torch.float64)
        t = lo[b] + (u * (hi - lo)[b].to(torch.float64)).floor().to(torch.int64) + 1
        x = torch.randint(0, self.W, (total,), generator=g)
        y = torch.randint(0, self.H, (total,), generator=g)
        p = (torch.randint(0, 2, (total,), generator=g) * 2 - 1).to(torch.int8)
        dev = ev.b.device
        cat = [torch.cat([getattr(ev, f), v.to(dev, getattr(ev, f).dtype)]) for f, v in
               zip(("b", "x", "y", "t", "p"), (b, x, y, t, p))]
        return Events(*cat, sort=True)
