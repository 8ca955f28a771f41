"""Build validated config dataclasses from plain dicts (as read from YAML).

Errors are :class:`ConfigError` and name the parameter (dotted path), the file, and the
allowed range or choices.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import typing
from typing import Any, Optional, Tuple

from dvsland.checks import check_choice, check_range

from .errors import ConfigError
from .schema import LIST_ITEM_TYPES, Config


def _where(source: Optional[str]) -> str:
    return f" (in {source})" if source else ""


def _field_types(cls) -> dict:
    return typing.get_type_hints(cls)


def _strip_optional(tp):
    """Return (inner_type, is_optional) for Optional[X]."""
    if typing.get_origin(tp) is typing.Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def coerce_scalar(value: Any, tp, path: str, source: Optional[str]) -> Any:
    """Convert ``value`` to the scalar type ``tp`` (int, float, bool, str) or raise ConfigError."""
    def bad(expected: str):
        return ConfigError(f"{path}{_where(source)}: expected {expected}, got {value!r}")

    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no", "1", "0"):
            return value.lower() in ("true", "yes", "1")
        raise bad("true or false")
    if tp is int:
        if isinstance(value, bool):
            raise bad("an integer")
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        if isinstance(value, str):
            try:
                f = float(value)
            except ValueError:
                raise bad("an integer") from None
            if f.is_integer():
                return int(f)
        raise bad("an integer")
    if tp is float:
        if isinstance(value, bool):
            raise bad("a number")
        if isinstance(value, (int, float)):
            return float(value)
        if isinstance(value, str):  # YAML 1.1 reads "5e6" as a string
            try:
                return float(value)
            except ValueError:
                raise bad("a number") from None
        raise bad("a number")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
        raise bad("a string")
    if tp is dict:
        if isinstance(value, dict):
            return dict(value)
        raise bad("a mapping")
    raise bad(str(tp))


def _check_field(value: Any, md: dict, path: str, source: Optional[str]) -> None:
    if value is None:
        return
    if md.get("choices") is not None:
        check_choice(path, value, md["choices"], where=_where(source), error=ConfigError)
    rng = md.get("rng")
    if rng is not None and isinstance(value, (int, float)):
        check_range(path, value, rng[0], rng[1], open_lo=bool(md.get("open_lo")), open_hi=bool(md.get("open_hi")),
                    where=_where(source), error=ConfigError)


def build(cls, data: Any, path: str = "", source: Optional[str] = None):
    """Build dataclass ``cls`` from a dict, validating keys, types and ranges.

    Args:
        cls: a config dataclass (e.g. :class:`~dvsland.config.schema.Config`).
        data: mapping of field name to value (missing fields take their default).
        path: dotted prefix of this section for error messages.
        source: file name for error messages.
    """
    if data is None:
        data = {}
    if dataclasses.is_dataclass(data) and isinstance(data, cls):
        data = dataclasses.asdict(data)
    if not isinstance(data, dict):
        raise ConfigError(f"{path or 'config'}{_where(source)}: expected a mapping, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [k for k in data if k not in fields]
    if unknown:
        where = f"{path}." if path else ""
        raise ConfigError(f"unknown key '{where}{unknown[0]}'{_where(source)}; "
                          f"known keys here: {sorted(fields)}")
    types = _field_types(cls)
    kwargs = {}
    for name, f in fields.items():
        fpath = f"{path}.{name}" if path else name
        if name not in data:
            continue
        value = data[name]
        if isinstance(value, bool) and "true" in (f.metadata.get("choices") or ()):  # true/false/auto: YAML's bool
            value = "true" if value else "false"
        kwargs[name] = convert(value, types[name], fpath, source, owner=cls, name=name)
        _check_field(kwargs[name], f.metadata, fpath, source)
    obj = cls(**kwargs)
    return obj


def convert(value: Any, tp, path: str, source: Optional[str], owner=None, name: str = ""):
    """Convert a raw value to field type ``tp`` (dataclass, list of dataclasses, scalar)."""
    tp, optional = _strip_optional(tp)
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{path}{_where(source)}: must not be null")
    if dataclasses.is_dataclass(tp):
        return build(tp, value, path, source)
    if tp is list or typing.get_origin(tp) is list:
        item_tp = LIST_ITEM_TYPES.get((owner, name))
        if isinstance(value, str):  # "A,B,C" from the command line
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}{_where(source)}: expected a list, got {value!r}")
        if item_tp is None:
            return list(value)
        return [build(item_tp, v, f"{path}[{i}]", source) for i, v in enumerate(value)]
    return coerce_scalar(value, tp, path, source)


def check_config(cfg: Config, source: Optional[str] = None) -> Config:
    """Cross-field checks that no single field can make. Returns ``cfg``.

    Names of stage implementations (``estimator.name``, ``render.renderer``,
    ``controller.name``) are checked where the stages are built, against their registries
    (:func:`dvsland.stages.check_names`), so that loading a config imports no stage.
    """
    if cfg.dynamics.dry_mass_kg >= cfg.dynamics.mass_kg:
        raise ConfigError(f"dynamics.dry_mass_kg{_where(source)}: {cfg.dynamics.dry_mass_kg} must be "
                          f"below dynamics.mass_kg = {cfg.dynamics.mass_kg}")
    if cfg.controller.thrust_max_n is not None and cfg.controller.thrust_max_n < cfg.controller.thrust_min_n:
        raise ConfigError(f"controller.thrust_max_n{_where(source)}: {cfg.controller.thrust_max_n} must be "
                          f">= controller.thrust_min_n = {cfg.controller.thrust_min_n}")
    pp = cfg.camera.principal_point_px
    if pp is not None:
        W, H = cfg.camera.width_px, cfg.camera.height_px
        try:
            cx, cy = (float(v) for v in pp)
        except (TypeError, ValueError):
            raise ConfigError(f"camera.principal_point_px{_where(source)}: expected [cx, cy] (two numbers, px) "
                              f"or null, got {pp!r}") from None
        if not (0.0 <= cx <= W - 1 and 0.0 <= cy <= H - 1):
            raise ConfigError(f"camera.principal_point_px{_where(source)}: [{cx}, {cy}] is off the sensor; "
                              f"allowed cx in [0, {W - 1}], cy in [0, {H - 1}] px")
        cfg.camera.principal_point_px = [cx, cy]
    if cfg.render.min_altitude_m >= cfg.render.max_altitude_m:
        raise ConfigError(f"render.min_altitude_m{_where(source)}: must be below render.max_altitude_m")
    if not cfg.controller.settings:
        raise ConfigError(f"controller.settings{_where(source)}: needs at least one setting")
    names = [s.name for s in cfg.simulation.sites]
    if len(set(names)) != len(names):
        raise ConfigError(f"simulation.sites{_where(source)}: site names must be unique, got {names}")
    for i, s in enumerate(cfg.simulation.sites):
        if s.z0_m > cfg.render.max_altitude_m:
            raise ConfigError(f"simulation.sites[{i}].z0_m{_where(source)}: {s.z0_m} is above "
                              f"render.max_altitude_m = {cfg.render.max_altitude_m}")
    check_run_semantics(cfg, source)
    from .dispersion import check_dispersion_config

    try:
        check_dispersion_config(cfg.dispersion, source or "")
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    return cfg


# ---------------------------------------------------------------------------------------------
# The one validation path: YAML files, ``--set``, the CLI and the Python API all end here.
# The checks below are semantic: they need several fields, or what the run will build from them.

#: peak bytes per camera pixel the simulator holds per site (renderer levels) and per descent
#: (frames, emulator state in float64, estimator images), fitted to the peak RSS of
#: ``dvsland simulate realistic`` for 1 s at 512 x 512 px: sites D (B = 2) 845 MiB, D-G (B = 8)
#: 3096 MiB, i.e. about 3000 B/px per site with its two descents; rounded up, a rough bound
SITE_BYTES_PER_PX = 2400
STATE_BYTES_PER_PX = 300
#: bytes per event at the emulator's peak (keys, sort, decoded Events)
BYTES_PER_EVENT = 48
#: peak bytes per texel of one terrain level in preparation (float64 fields over the tile and its
#: shadow pad; measured 195-462 B on site A at 512-2048 texels); levels are prepared one at a time
PREP_BYTES_PER_TEXEL = 480
#: bytes per texel of a prepared scene's tiles (irradiance and height, float32, and the atlas copy);
#: a tile is about 3 x camera.width_px texels wide, so a wide camera needs far more than its pixels
ATLAS_BYTES_PER_TEXEL = 16
#: the cmax search's memory per element: bytes per pixel of its two int64 half-images, cropped to
#: the sensor box and one pixel beyond (the image and one product of it at a time), per event and
#: candidate (the warp factors of every candidate) and per event of the candidates scored at once
#: (the warped positions, corner weights and indices of one chunk of candidates)
CMAX_BYTES_PER_CANVAS_PX = 16
CMAX_BYTES_PER_EVENT_CANDIDATE = 8
CMAX_BYTES_PER_EVENT = 100
#: longest run name / label after the folder-name mapping, characters (file names: <= 255 bytes)
MAX_NAME_CHARS = 120
#: longest path the OS takes (PATH_MAX) and longest single name in it (NAME_MAX), bytes
MAX_PATH_BYTES, MAX_FILE_NAME_BYTES = 4096, 255

_DEVICE_RE = re.compile(r"^(cpu|cuda(:\d+)?)$")


def validate_config(cfg, source: Optional[str] = None) -> Config:
    """Check a whole config exactly as the YAML loader does and return a checked copy.

    ``cfg`` may be a :class:`Config` built in Python (fields set by hand) or a plain dict: every
    field goes through the same type conversion and range check as a file (NaN and inf fail
    every range), then :func:`check_config`. This is what ``dvsland.simulate``, ``evaluate``,
    the ``events`` and ``render`` commands and ``config show`` run.

    Raises:
        ConfigError: naming the parameter and the allowed range.
    """
    if not (isinstance(cfg, (Config, dict))):
        raise ConfigError(f"config must be a dvsland Config or a mapping, got {type(cfg).__name__}")
    try:
        data = dataclasses.asdict(cfg) if isinstance(cfg, Config) else cfg
    except TypeError as exc:
        raise ConfigError(f"config: a section is not a config section: {exc}") from None
    built = build(Config, data, source=source or "Python Config")
    return check_config(built, source=source or "Python Config")


def check_run_semantics(cfg: Config, source: Optional[str] = None) -> None:
    """Checks that need several fields: run name, device, time span, labels, estimator sections,
    memory. Raises ConfigError naming the parameter."""
    w = _where(source)
    check_run_name(cfg.name, f"name{w}")
    if not cfg.logging.root.strip():
        raise ConfigError(f"logging.root{w}: must not be empty (the folder under which run folders are made)")
    if not _DEVICE_RE.match(cfg.simulation.device):
        raise ConfigError(f"simulation.device{w}: {cfg.simulation.device!r} is not supported; "
                          f"use 'cpu', 'cuda' or 'cuda:N'")
    dt = 1.0 / cfg.camera.frame_rate_hz
    if cfg.simulation.t_max_s < dt:
        raise ConfigError(f"simulation.t_max_s{w}: {cfg.simulation.t_max_s!r} s is shorter than one control "
                          f"step (1 / camera.frame_rate_hz = {dt:g} s); allowed [{dt:g}, 1e6]")
    _check_labels(cfg, w)
    _check_estimator_sections(cfg, w)


def check_run_name(name: str, what: str = "name") -> None:
    """A run name becomes a folder name under ``logging.root``: no path separators, no ``..``."""
    if not name or name in (".", "..") or "/" in name or "\\" in name or "\0" in name or name.strip() != name:
        raise ConfigError(f"{what}: {name!r} is not allowed; a run name must be a plain folder name "
                          f"(no '/', '\\\\', '..', leading or trailing spaces; not empty)")
    if len(name.encode()) > MAX_NAME_CHARS:
        raise ConfigError(f"{what}: {len(name)} characters ({name[:40]!r}...) is too long for a folder name; "
                          f"allowed 1 to {MAX_NAME_CHARS} characters")


def setting_label(kp: float, n_bin: int, label: str = "") -> str:
    """Label of a controller setting: ``label`` if given, else e.g. ``Kp5e6-n5`` for Kp = 5e6,
    n_bin = 5 (the simulator's run labels are ``<site>/<setting label>``)."""
    if label:
        return label
    mant, exp = f"{kp:.3e}".split("e")
    mant = mant.rstrip("0").rstrip(".")
    return f"Kp{mant}e{int(exp)}-n{int(n_bin)}"


def folder_name(label: str) -> str:
    """File-system-safe folder name of a run label (``A/Kp5e6-n5`` -> ``A_Kp5e6-n5``): every
    character outside ``[A-Za-z0-9_.+-]`` becomes ``_``."""
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", label)


_safe = folder_name


def _check_labels(cfg: Config, w: str) -> None:
    seen = {}
    for i, s in enumerate(cfg.controller.settings):
        lab = setting_label(s.kp, s.n_bin, s.label)
        key = _safe(lab)
        if key in seen:
            j, other = seen[key]
            same = "the same label" if other == lab else f"labels that map to the same folder name {key!r}"
            raise ConfigError(f"controller.settings[{i}].label{w}: {lab!r} and settings[{j}] ({other!r}) have "
                              f"{same}; run labels name TensorBoard folders and figures, so they must be "
                              f"unique after replacing characters outside [A-Za-z0-9_.+-] by '_'")
        seen[key] = (i, lab)
        if len(key.encode()) > MAX_NAME_CHARS:
            raise ConfigError(f"controller.settings[{i}].label{w}: {len(lab)} characters ({lab[:40]!r}...) is too "
                              f"long; a label names TensorBoard folders and figures: allowed up to "
                              f"{MAX_NAME_CHARS} characters")


def _check_estimator_sections(cfg: Config, w: str) -> None:
    dpr, cm = cfg.estimator.dpr, cfg.estimator.cmax
    if dpr.nms_px % 2 == 0:
        raise ConfigError(f"estimator.dpr.nms_px{w}: {dpr.nms_px} must be odd; allowed odd integers in [1, 63]")
    if not cm.d_min < cm.d_max:
        raise ConfigError(f"estimator.cmax.d_min{w}: {cm.d_min} must be below estimator.cmax.d_max = {cm.d_max}")
    if cm.refine_points % 2 == 0:
        raise ConfigError(f"estimator.cmax.refine_points{w}: {cm.refine_points} must be odd; "
                          f"allowed odd integers in [3, 1001]")
    if 0 < cm.radial_bin_px < 0.01:
        raise ConfigError(f"estimator.cmax.radial_bin_px{w}: {cm.radial_bin_px!r} px is too fine an annulus; "
                          f"allowed 0 (off) or [0.01, 1000] px")
    _check_path_size(cfg.estimator.snn.checkpoint, f"estimator.snn.checkpoint{w}")


def _check_path_size(path: str, what: str) -> None:
    """A path longer than the OS takes (PATH_MAX, NAME_MAX per name) is a ConfigError naming it."""
    parts = [len(p.encode()) for p in str(path).split("/")]
    if len(str(path).encode()) > MAX_PATH_BYTES or max(parts, default=0) > MAX_FILE_NAME_BYTES:
        raise ConfigError(f"{what}: a path of {len(str(path))} characters ({str(path)[:40]!r}...) is too long; "
                          f"allowed up to {MAX_PATH_BYTES} bytes, each folder or file name up to "
                          f"{MAX_FILE_NAME_BYTES} bytes")


def memory_limit_bytes(cfg: Config) -> float:
    """``simulation.max_memory_gb`` in bytes; 0 = 80 % of this machine's physical memory, and on a
    CUDA ``simulation.device`` at most 90 % of the card's free memory (:func:`device_free_bytes`)."""
    return _memory_limit(cfg)[0]


def _memory_limit(cfg: Config) -> Tuple[float, str]:
    """(:func:`memory_limit_bytes`, where it came from for messages: `` (90 % of the ... GiB free on
    cuda:0)`` when the card was asked, else ``""``), the card asked once."""
    gb = float(getattr(cfg.simulation, "max_memory_gb", 0.0) or 0.0)
    if gb > 0:
        return gb * 2 ** 30, ""
    try:
        limit = 0.8 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        limit = math.inf
    free = device_free_bytes(getattr(cfg.simulation, "device", "cpu"))
    if free is None:
        return limit, ""
    return min(limit, 0.9 * free), f" (90 % of the {free / 2 ** 30:.1f} GiB free on {cfg.simulation.device})"


def device_free_bytes(device) -> Optional[float]:
    """Free memory of a CUDA ``device`` now (``torch.cuda.mem_get_info``), bytes; None for the CPU
    or where CUDA cannot say (torch not loaded with CUDA, no card)."""
    name = str(device or "cpu")
    if not name.startswith("cuda"):
        return None
    try:
        import torch

        if not torch.cuda.is_available():
            return None
        return float(torch.cuda.mem_get_info(torch.device(name))[0])
    except (ImportError, RuntimeError, ValueError, AssertionError):
        return None


def memory_parts(cfg: Config, n_sites: Optional[int] = None, batch_size: Optional[int] = None) -> dict:
    """Rough peak memory of a simulation by part, bytes: ``pixels`` (per-pixel state of every site
    and descent, or the prepared terrain tiles of every scene where they are larger: a wide camera),
    ``terrain`` (one level in preparation), ``events`` (one step's events at
    ``emulator.max_events_per_step``) and ``cmax`` (the cmax search: a warped image per element and
    candidate). ``n_sites`` and ``batch_size`` default to the whole configured experiment."""
    from .level_grid import GUTTER, level_grid

    n_sites = len({s.name for s in cfg.simulation.sites}) if n_sites is None else int(n_sites)
    B = _batch(cfg, batch_size)
    W, H = cfg.camera.width_px, cfg.camera.height_px
    lg = level_grid(cfg.camera, cfg.render)
    tex = float(lg.level_size + 2 * GUTTER) ** 2  # the tile: the window and its gutter
    site = max(SITE_BYTES_PER_PX * float(W * H), lg.n_levels * tex * ATLAS_BYTES_PER_TEXEL)
    parts = {"pixels": n_sites * site + B * STATE_BYTES_PER_PX * float(W * H),
             "terrain": tex * PREP_BYTES_PER_TEXEL,
             "events": float(event_cap_of(cfg, B)) * BYTES_PER_EVENT, "cmax": 0.0}
    if cfg.estimator.name == "cmax":
        cm = cfg.estimator.cmax
        G = max(cm.n_grid, cm.refine_points)
        n_ev = float(cm.max_events or 4000) * math.sqrt(W * H) / 128.0
        parts["cmax"] = B * (2.0 * (W + 3) * (H + 3) * CMAX_BYTES_PER_CANVAS_PX
                             + n_ev * (G * CMAX_BYTES_PER_EVENT_CANDIDATE + CMAX_BYTES_PER_EVENT))
    return parts


def event_cap_of(cfg: Config, batch_size: int) -> int:
    """The most events one step of ``batch_size`` descents may emit: the larger of
    ``emulator.max_events_per_step`` and ``emulator.max_events_per_descent`` x ``batch_size``."""
    em = cfg.emulator
    return max(int(getattr(em, "max_events_per_step", 0) or 0),
               int(getattr(em, "max_events_per_descent", 0) or 0) * int(batch_size))


def _batch(cfg: Config, batch_size: Optional[int]) -> int:
    return (len(cfg.simulation.sites) * len(cfg.controller.settings) * cfg.simulation.n_seeds
            if batch_size is None else int(batch_size))


def estimate_run_bytes(cfg: Config, n_sites: Optional[int] = None, batch_size: Optional[int] = None) -> float:
    """Rough peak memory of a simulation, bytes: the sum of :func:`memory_parts`."""
    return float(sum(memory_parts(cfg, n_sites, batch_size).values()))


def check_memory(cfg: Config, n_sites: Optional[int] = None, batch_size: Optional[int] = None,
                 source: Optional[str] = None) -> None:
    """ConfigError when :func:`estimate_run_bytes` exceeds :func:`memory_limit_bytes`, naming the
    parts. The simulator runs it on the batch it is about to build (after ``--sites``), before the
    run folder is made, a campaign on each grid point's largest shard before its plan is saved;
    it depends on the machine, so loading a config does not. A run that fits then goes through :func:`check_event_rates`."""
    parts, (limit, limit_from) = memory_parts(cfg, n_sites, batch_size), _memory_limit(cfg)
    need = sum(parts.values())
    if need <= limit:
        check_event_rates(cfg, batch_size, source)
        return
    gib = {k: f"{v / 2 ** 30:.1f} GiB" for k, v in parts.items()}
    cm = cfg.estimator.cmax
    raise ConfigError(
        f"simulation.max_memory_gb{_where(source)}: this run needs about {need / 2 ** 30:.1f} GiB, above the limit of "
        f"{limit / 2 ** 30:.1f} GiB{limit_from}: {gib['pixels']} for the {cfg.camera.width_px}x{cfg.camera.height_px} px camera "
        f"(terrain tiles and {SITE_BYTES_PER_PX} B per pixel per site + {STATE_BYTES_PER_PX} B per pixel per "
        f"descent, B = {_batch(cfg, batch_size)}), {gib['terrain']} to prepare a terrain level, {gib['events']} for "
        f"{event_cap_of(cfg, _batch(cfg, batch_size))} events per step (emulator.max_events_per_step = "
        f"{getattr(cfg.emulator, 'max_events_per_step', 0)}, emulator.max_events_per_descent = "
        f"{getattr(cfg.emulator, 'max_events_per_descent', 0)} x B) x {BYTES_PER_EVENT} B"
        + (f", {gib['cmax']} for the cmax search (estimator.cmax.n_grid = {cm.n_grid})" if parts["cmax"] else "")
        + "; use fewer sites, settings or seeds, a smaller camera, a lower emulator.max_events_per_step or "
          "estimator.cmax.n_grid, or raise simulation.max_memory_gb")


#: the smallest change of log intensity per pixel and control step assumed by
#: :func:`event_rate_parts` (a descent over textured terrain changes far more)
MIN_CONTRAST_PER_STEP = 1e-3


def event_rate_parts(cfg: Config) -> dict:
    """Lower estimate of the events one pixel emits per control step, by the setting that drives
    them: {"emulator.<name> = <value>": events per pixel per step}. Noise rates (background, leak,
    shot noise, hot pixels) times the step ``1 / camera.frame_rate_hz``; the contrast threshold's
    share as :data:`MIN_CONTRAST_PER_STEP` over the lowest threshold. A dispersed rate or threshold
    is left out (the estimate stays a lower one)."""
    em, dt, disp = cfg.emulator, cfg.dt_s, cfg.dispersion

    def dispersed(name: str) -> bool:
        return bool(disp.enabled) and getattr(disp, name).kind != "off"

    parts = {}
    if not dispersed("background_rate_hz"):
        parts[f"emulator.background_rate_hz = {em.background_rate_hz:g}"] = em.background_rate_hz * dt
    parts[f"emulator.leak_rate_hz = {em.leak_rate_hz:g}"] = em.leak_rate_hz * dt
    parts[f"emulator.shot_noise_rate_hz = {em.shot_noise_rate_hz:g}"] = (
        em.shot_noise_rate_hz * min(1.0, em.shot_noise_bright_factor) * dt)
    parts[f"emulator.hot_pixel_fraction = {em.hot_pixel_fraction:g} x emulator.hot_pixel_rate_hz = "
          f"{em.hot_pixel_rate_hz:g}"] = em.hot_pixel_fraction * em.hot_pixel_rate_hz * dt
    if not dispersed("threshold_scale"):
        off = em.threshold if em.threshold_off is None else em.threshold_off
        name, th = ("threshold_off", off) if off < em.threshold else ("threshold", em.threshold)
        parts[f"emulator.{name} = {th:g}"] = MIN_CONTRAST_PER_STEP / th
    return {k: v for k, v in parts.items() if v > 0}


def check_event_rates(cfg: Config, batch_size: Optional[int] = None, source: Optional[str] = None) -> None:
    """ConfigError, before anything is flown, when the settings of :func:`event_rate_parts` imply
    more events in one step of ``batch_size`` descents (default: the whole experiment) than
    ``emulator.max_events_per_step``; the message names the setting with the largest share and its
    value (values inside the schema's ranges can do this: ``background_rate_hz = 1e4`` on a DVS128
    at 10 Hz is 1000 events per pixel per step). A refractory period bounds a pixel's count."""
    parts = event_rate_parts(cfg)
    per_px = sum(parts.values())
    r_us = float(cfg.emulator.refractory_us)
    if r_us > 0:
        per_px = min(per_px, cfg.dt_s * 1e6 / r_us)
    B, W, H = _batch(cfg, batch_size), cfg.camera.width_px, cfg.camera.height_px
    n, cap = per_px * B * W * H, event_cap_of(cfg, B)
    if n <= cap:
        return
    top = max(parts, key=parts.get)
    others = [k for k in parts if k != top]
    raise ConfigError(
        f"{top}{_where(source)}: one control step would emit at least about {n:.3g} events "
        f"(B = {B} descents x {W}x{H} px x {per_px:.3g} per pixel per step"
        + (f", with {', '.join(others)}" if others else "")
        + f"), above the cap of {cap} (emulator.max_events_per_step = {cfg.emulator.max_events_per_step}, "
          f"emulator.max_events_per_descent = {cfg.emulator.max_events_per_descent} x B; about "
          f"{n * BYTES_PER_EVENT / 2 ** 30:.3g} GiB at {BYTES_PER_EVENT} B per event); "
          f"{'raise' if 'threshold' in top else 'lower'} {top.split(' = ')[0]}, fly fewer descents or raise "
          f"emulator.max_events_per_step or emulator.max_events_per_descent if the memory is there")
