"""The stages of the loop, built from a config: the one place that wires them.

Every command that needs stages builds them here (``simulate``, ``evaluate``, ``events``, the
spiking estimator's training data), so a new renderer, estimator or controller plugs in once:

- the **event source**: a renderer (``render.renderer``, from :func:`dvsland.render.get_renderer`)
  and the event emulator (``emulator``), paired as :class:`EventSource`;
- the **estimator** (``estimator.name`` and its section, from :mod:`dvsland.estimators`);
- the **controller** (``controller``; one per batch element's setting).

Names are checked here, against the registries (:func:`check_names`), not when a config is
loaded: ``dvsland.config`` imports no stage. Stage modules are imported inside the functions,
so importing this module is cheap (no torch).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, NamedTuple, Optional, Sequence, Union

from dvsland.config import Config, ConfigError

if TYPE_CHECKING:  # annotations only: importing this module loads no torch
    import torch


# ------------------------------------------------------------------ names
def check_names(cfg: Config, source: str = "") -> None:
    """Check the stage names of ``cfg`` against their registries.

    Raises:
        ConfigError: ``estimator.name``, ``render.renderer`` or ``controller.name`` names nothing
            registered; the message lists the known names.
    """
    from dvsland.render import available_renderers

    where = f" (in {source})" if source else ""
    from dvsland.estimators.registry import estimator_class

    try:  # a registered name, an entry point, or an import path 'package.module:Class'
        estimator_class(cfg.estimator.name)
    except ValueError as exc:
        raise ConfigError(f"estimator.name{where}: {exc}") from None
    known = available_renderers()
    if cfg.render.renderer not in known:
        raise ConfigError(f"render.renderer{where}: unknown renderer {cfg.render.renderer!r}; known: {known}")
    known = available_controllers()
    if cfg.controller.name not in known:
        raise ConfigError(f"controller.name{where}: unknown controller {cfg.controller.name!r}; known: {known}")


# ------------------------------------------------------------------ event source
@dataclass
class EventSource:
    """A renderer and an event emulator: altitudes in, events out.

    Attributes:
        renderer: object with ``render(altitude_m (B,), site_idx (B,) int64) -> (B, H, W)`` float32
            linear irradiance, or such a callable.
        emulator: :class:`dvsland.events.EventEmulator`.
    """

    renderer: Any
    emulator: Any

    def render(self, altitude_m: torch.Tensor, site_idx: torch.Tensor, in_range: bool = False) -> torch.Tensor:
        """Frames (B, H, W) float32 at ``altitude_m`` (B,) m of sites ``site_idx`` (B,) int64.
        ``in_range``: the caller guarantees the inputs' range (the loop does), so a renderer that
        offers ``render_in_range`` skips its checks (and their host sync)."""
        r = self.renderer
        if in_range and hasattr(r, "render_in_range"):
            return r.render_in_range(altitude_m, site_idx)
        return r.render(altitude_m, site_idx) if hasattr(r, "render") else r(altitude_m, site_idx)

    def reset(self, altitude_m: torch.Tensor, site_idx: torch.Tensor, t_us: int) -> torch.Tensor:
        """Render the first frame and start the emulator on it at ``t_us``; returns the frames."""
        frames = self.render(altitude_m, site_idx)
        self.emulator.reset(frames, int(t_us))
        return frames

    def step(self, altitude_m: torch.Tensor, site_idx: torch.Tensor, t_us: int):
        """Render the next frame and emulate the events up to ``t_us``; returns (frames, Events)."""
        frames = self.render(altitude_m, site_idx)
        return frames, self.emulator.step(frames, int(t_us))


def build_event_source(cfg: Config, site_names: Sequence[str], device: Any = "cpu", renderer: Any = None,
                       seed: Optional[int] = None, **renderer_kwargs) -> EventSource:
    """The configured renderer for ``site_names`` and the configured emulator.

    Args:
        cfg: config (``camera``, ``render``, ``emulator``, ``simulation.seed``).
        site_names: the renderer's sites (``site_idx`` indexes them).
        device: torch device.
        renderer: ``None`` (``render.renderer``), a registered renderer name, or a ready renderer
            object / frame callable (used as is).
        seed: emulator seed (default ``simulation.seed``).
        renderer_kwargs: extra arguments of the renderer class (e.g. ``progress`` for "fast").
    """
    from dvsland.events import EventEmulator

    if renderer is None or isinstance(renderer, str):
        from dvsland.render import get_renderer

        renderer = get_renderer(renderer or cfg.render.renderer, list(site_names), cfg.camera, cfg.render,
                                device=device, **renderer_kwargs)
    seed = cfg.simulation.seed if seed is None else int(seed)
    return EventSource(renderer, EventEmulator.from_config(cfg.emulator, device, seed=seed))


# ------------------------------------------------------------------ estimator
def build_estimator(cfg: Config, batch_size: int, device: Any = "cpu", name: Optional[str] = None,
                    seed: Optional[int] = None):
    """Estimator ``name`` (default ``estimator.name``) for ``batch_size`` descents, with the
    parameters of its config section; see :func:`dvsland.estimators.make_estimator`."""
    from dvsland.estimators import make_estimator

    return make_estimator(cfg, batch_size, device, name=name, seed=seed)


# ------------------------------------------------------------------ controller
def available_controllers() -> list:
    """Names accepted by ``controller.name`` (the controller registry's, where
    :mod:`dvsland.control` has one)."""
    import dvsland.control as control

    registry = getattr(control, "available_controllers", None)
    return sorted(registry()) if registry is not None else ["tau_p"]


def build_controller(cfg: Config, layout, device: Any = "cpu"):
    """The configured controller (``controller.name`` with its options) for the elements of ``layout``
    (a :class:`dvsland.sim.BatchLayout`: per-element Kp, n_bin and initial conditions), from the
    controller registry (:func:`dvsland.control.make_controller`)."""
    from dvsland.control import descent_params, make_controller

    if cfg.controller.name not in available_controllers():
        raise ConfigError(f"controller.name: unknown controller {cfg.controller.name!r}; "
                          f"known: {available_controllers()}")
    return make_controller(cfg, descent_params(cfg, layout, device))


# ------------------------------------------------------------------ all of them
class LoopSettings(NamedTuple):
    """The loop's constants, read once from the config (the loop itself never reads the config).

    Attributes:
        dt_s: control step, s.
        n_steps_max: steps in ``simulation.t_max_s``.
        t_max_s, success_altitude_m, crash_divergence: termination thresholds (s, m, 1/s).
        g_mps2: gravity, m/s^2 (the efference copy's acceleration is thrust/m - g).
        mass_kg: initial mass, kg.
        render_min_altitude_m, render_max_altitude_m: the renderer's altitude range, m (altitudes
            are clamped into it before rendering).
        estimator_name: the configured estimator's name (results and logs).
        compact: finished descents leave the step's hot path (``simulation.compact``).
        compile: the filter's and the law's steps run through ``torch.compile``
            (``simulation.compile``: "auto" is on for a CUDA device, off elsewhere).
    """

    dt_s: float
    n_steps_max: int
    t_max_s: float
    success_altitude_m: float
    crash_divergence: float
    g_mps2: float
    mass_kg: float
    render_min_altitude_m: float
    render_max_altitude_m: float
    estimator_name: str
    compact: bool = True
    compile: bool = False

    @classmethod
    def from_config(cls, cfg: Config, device: Any = None) -> "LoopSettings":
        """The settings of ``cfg``; ``device`` (default ``simulation.device``) resolves ``simulation.compile=auto``."""
        import math

        sim, dt = cfg.simulation, float(cfg.dt_s)
        return cls(dt_s=dt, n_steps_max=int(math.ceil(sim.t_max_s / dt - 1e-9)), t_max_s=float(sim.t_max_s),
                   success_altitude_m=float(sim.success_altitude_m), crash_divergence=float(sim.crash_divergence),
                   g_mps2=float(cfg.dynamics.g_mps2), mass_kg=float(cfg.dynamics.mass_kg),
                   render_min_altitude_m=float(cfg.render.min_altitude_m),
                   render_max_altitude_m=float(cfg.render.max_altitude_m), estimator_name=str(cfg.estimator.name),
                   compact=bool(getattr(sim, "compact", True)), compile=_compile_on(sim, device))


def _compile_on(sim: Any, device: Any = None) -> bool:
    """Whether ``simulation.compile`` ("auto", "true", "false"; a bool too) fuses the filter and the law on
    ``device`` (default ``simulation.device``): "auto" where it pays, on a CUDA device."""
    from dvsland.compiled import compile_on

    return compile_on(getattr(sim, "compile", "auto"), device if device is not None else getattr(sim, "device", "cpu"))


@dataclass
class Stages:
    """What :func:`build_stages` returns: every box of the loop, built once.

    Attributes:
        cfg: the resolved config the stages were built from (read, never written).
        layout: the batch layout (B elements).
        estimator: divergence estimator for B elements.
        events: :class:`EventSource`, or None when the estimator needs no events (``oracle``).
        controller: controller for the B elements.
        filter: the divergence filter (moving average or efference-copy filter).
        dynamics: :class:`dvsland.dynamics.LanderDynamics`.
        params: :class:`dvsland.control.DescentParams` of the B elements.
        settings: :class:`LoopSettings`.
        device: torch device of the loop state.
        scene_idx: (B,) int64 on ``device``, the renderer's row of each element (its site, or its
            dispersed scene).
    """

    cfg: Any
    layout: Any
    estimator: Any
    events: Optional[EventSource]
    controller: Any
    filter: Any = None
    dynamics: Any = None
    params: Any = None
    settings: Optional[LoopSettings] = None
    device: Any = "cpu"
    scene_idx: Any = None

    @property
    def renderer(self):
        return self.events.renderer if self.events is not None else None

    @property
    def emulator(self):
        return self.events.emulator if self.events is not None else None

    @property
    def batch_size(self) -> int:
        return int(self.layout.batch_size)

    @property
    def needs_events(self) -> bool:
        return self.events is not None


def build_stages(cfg: Config, sites: Union[None, str, Sequence[str], Any] = None, device: Any = "cpu", *,
                 estimator: Any = None, renderer: Any = None, controller: Any = None,
                 record_events: bool = False, progress: bool = False) -> Stages:
    """Build the closed loop's stages for ``cfg``: the one place that wires them.

    Args:
        cfg: the resolved config.
        sites: a :class:`dvsland.layout.BatchLayout`, or a subset of the configured sites (``"A,B"``
            or a list; None = all), expanded by :func:`dvsland.layout.build_layout`.
        device: torch device.
        estimator: None (the configured one) or a ready estimator for B elements.
        renderer: None (``render.renderer``), a renderer name, or a renderer object; built only
            when the estimator needs events.
        controller: None (the configured one) or a ready controller for B elements.
        record_events: build the renderer and the emulator even when the estimator needs no events
            (a dataset records the camera while the truth flies); the estimator then receives them.
        progress: show the fast renderer's terrain preparation as a progress bar (per scene).

    Raises:
        ConfigError: a stage name is not registered (see :func:`check_names`).
        ValueError: an estimator instance built for another batch size; an estimator that needs
            events without a renderer.
    """
    import torch

    from dvsland.control import descent_params, make_filter
    from dvsland.dynamics import LanderDynamics
    from dvsland.layout import BatchLayout, build_layout

    if isinstance(sites, BatchLayout):
        layout = sites
    else:
        layout = build_layout(cfg, sites.split(",") if isinstance(sites, str) else sites)
    device = torch.device(device)
    B = layout.batch_size
    if estimator is None:
        est = _build_plugin_estimator(cfg, B, device, layout.noise_seed)
    else:
        est = estimator
        if getattr(est, "batch_size", B) != B:
            raise ValueError(f"estimator instance is for batch_size={est.batch_size}, the batch has B={B}")
    events = None
    if record_events or getattr(est, "needs_events", True):
        if device.type == "cpu":
            start_kernel_builds(cfg, est, renderer)
        kw = _dispersed_scene_kwargs(cfg, layout, renderer)
        if progress and (renderer or cfg.render.renderer) == "fast":
            kw["progress"] = True
        names = kw.pop("site_names", layout.site_names)  # dispersed scenes: their sites (variants)
        events = build_event_source(cfg, names, device, renderer, seed=layout.noise_seed, **kw)
        if layout.sensor or layout.dispersed:  # a Monte Carlo batch: per-element sensor values
            events.emulator.set_element_params(element_seeds=layout.seed, **layout.sensor)
    if controller is None:
        controller = build_controller(cfg, layout, device)
    params = descent_params(cfg, layout, device)
    prior = params if cfg.controller.efference.prior_state == "dispersed" else _nominal_params(params, layout)
    filt = make_filter(cfg, prior, controller)
    return Stages(cfg, layout, est, events, controller, filter=filt, dynamics=LanderDynamics.from_config(cfg.dynamics),
                  params=params, settings=LoopSettings.from_config(cfg, device), device=device,
                  scene_idx=layout.tensor("scene_idx", device, torch.int64))


def start_kernel_builds(cfg: Config, estimator: Any = None, renderer: Any = None) -> int:
    """Start compiling, in one background thread, the C++ kernels that a CPU run with ``estimator``
    and ``renderer`` (None: the configured one) loads on first use and finds neither built nor
    loaded (:func:`dvsland.native_build.build_in_background`): the terrain's and the renderer's
    for the fast renderer, the emulator's, ``cmax``'s or ``dpr``'s for those estimators, and the
    ``efference_fit`` filter's for that filter. The
    compiler runs beside the scenes' preparation instead of before the first steps; each kernel's
    first use waits for its build. Returns the builds started (0 on a warm cache)."""
    from dvsland.control import native_fit
    from dvsland.estimators import native_cmax, native_dpr
    from dvsland.estimators.cmax import CMaxEstimator
    from dvsland.estimators.dpr import DPREstimator
    from dvsland.events import native as events_native
    from dvsland.native_build import build_in_background
    from dvsland.render import native_render
    from dvsland.terrain import native_noise

    libraries = []
    if (renderer or cfg.render.renderer) == "fast":
        libraries += [native_noise.LIBRARY, native_render.LIBRARY]
    libraries.append(events_native.LIBRARY)
    if isinstance(estimator, CMaxEstimator):
        libraries.append(native_cmax.LIBRARY)
    elif isinstance(estimator, DPREstimator):
        libraries.append(native_dpr.LIBRARY)
    if cfg.controller.filter == "efference_fit":
        libraries.append(native_fit.LIBRARY)
    return build_in_background(libraries)


def _build_plugin_estimator(cfg: Config, batch_size: int, device, seed):
    """The configured estimator; one built from an import path (``pkg.mod:Class``, ``file.py:Class``)
    is user code: whatever its construction raises, or an object without ``update`` and ``reset``,
    is one :class:`dvsland.plugins.PluginError` naming it."""
    from dvsland.plugins import PluginError, call_plugin

    name = cfg.estimator.name
    if ":" not in name:  # a built-in or registered estimator: its own errors name its parameters
        return build_estimator(cfg, batch_size, device, seed=seed)
    est = call_plugin(name, "__init__", build_estimator, cfg, batch_size, device, seed=seed)
    if not all(callable(getattr(est, m, None)) for m in ("update", "reset")):
        raise PluginError(name, "__init__", f"expected a divergence estimator (an object with update() and "
                                            f"reset()), got {type(est).__name__}")
    return est


def _nominal_params(params, layout):
    """``params`` with the sites' undispersed initial state (z0, v0): the efference filter's prior
    (a craft knows its planned start, not its dispersion). Unchanged when nothing is dispersed."""
    import dataclasses

    import torch

    scale = {k: layout.dispersed.get(k) for k in ("z0_scale", "v0_scale")}
    if all(v is None for v in scale.values()):
        return params
    z0, v0 = params.z0_m, params.v0_mps
    if scale["z0_scale"] is not None:
        z0 = z0 / torch.as_tensor(scale["z0_scale"], dtype=z0.dtype, device=z0.device)
    if scale["v0_scale"] is not None:
        v0 = v0 / torch.as_tensor(scale["v0_scale"], dtype=v0.dtype, device=v0.device)
    return dataclasses.replace(params, z0_m=z0, v0_mps=v0)


def _dispersed_scene_kwargs(cfg: Config, layout, renderer) -> dict:
    """Renderer arguments of a batch with dispersed scenes (:mod:`dvsland.layout.dispersion`): its
    scenes' sites (variants), suns and altitude ranges (lazy levels of the fast renderer)."""
    if not layout.scenes_dispersed or not (renderer is None or isinstance(renderer, str)):
        return {}
    name = renderer or cfg.render.renderer
    kw = {"site_names": list(layout.scene_site)}
    if name != "fast":
        if any(sun != (None, 0.0) for sun in layout.scene_sun):
            raise ValueError("dispersion.sun_elevation_deg / sun_azimuth_offset_deg need render.renderer='fast'")
        return kw
    import numpy as np

    top = [float(np.max(layout.z0_m[layout.scene_idx == i])) for i in range(len(layout.scene_names))]
    kw.update(suns=list(layout.scene_sun),
              altitude_ranges=[(cfg.simulation.success_altitude_m, z) for z in top])
    return kw


#: ``f(altitude_m (B,), site_idx (B,) int64) -> (B, H, W)`` float32 frames (torch tensors)
FrameSource = Callable[[Any, Any], Any]

__all__ = ["Stages", "LoopSettings", "EventSource", "build_stages", "start_kernel_builds", "build_event_source",
           "build_estimator", "build_controller", "available_controllers", "check_names", "FrameSource"]
