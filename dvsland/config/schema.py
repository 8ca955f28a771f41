"""Typed configuration sections of a dvsland run.

Every field declares its allowed range (``rng``) or choices (``choices``) in its metadata;
:func:`dvsland.config.validate.validate` checks them and names the parameter and the range
on failure. Units are in the field names where they are not SI seconds/metres.

Numbers the paper (Sikorski, Izzo, Meoni 2021) does not give are marked "not in paper" in
the field's ``doc``; ``configs/paper.yaml`` repeats that as comments.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from dvsland.compiled import MODES as COMPILE_MODES

from .errors import ConfigError

INF = float("inf")

#: Site names of the paper.
SITE_NAMES = ("A", "B", "C", "D", "E", "F", "G", "H", "I")

#: The paper's initial conditions (z0 m, v0 m/s): A-C from 10 km at -200 m/s, D-I from 4 km at -100 m/s.
PAPER_INITIAL_CONDITIONS = {n: (10000.0, -200.0) if n in "ABC" else (4000.0, -100.0) for n in SITE_NAMES}


def opt(default: Any, doc: str = "", rng: Optional[tuple] = None, choices: Optional[tuple] = None,
        open_lo: bool = False, open_hi: bool = False, factory=None):
    """A dataclass field with validation metadata.

    Args:
        default: default value (ignored when ``factory`` is given).
        doc: one-line description with unit.
        rng: ``(lo, hi)`` allowed range, inclusive unless ``open_lo`` / ``open_hi``.
        choices: allowed values (for strings).
    """
    md = {"doc": doc, "rng": rng, "choices": choices, "open_lo": open_lo, "open_hi": open_hi}
    if factory is not None:
        return field(default_factory=factory, metadata=md)
    return field(default=default, metadata=md)


@dataclass
class CameraConfig:
    """Nadir pinhole event camera (DVS128)."""

    width_px: int = opt(128, "sensor width in pixels", rng=(8, 4096))
    height_px: int = opt(128, "sensor height in pixels", rng=(8, 4096))
    fov_deg: float = opt(60.0, "full field of view across the width, degrees "
                         "(not in paper: ~60 deg for a 4.5 mm lens on 40 um pixels)",
                         rng=(1.0, 150.0))
    frame_rate_hz: float = opt(10.0, "frame (and control) rate, Hz", rng=(0.1, 10000.0), open_lo=True)
    sensor: str = opt("custom", "sensor preset: fills width_px, height_px, pixel_pitch_um and (where the preset "
                      "names a lens and focal_length_mm is null) focal_length_mm; 'custom' = the fields as given "
                      "(defaults: DVS128 geometry). See SENSOR_PRESETS", choices=("dvs128", "davis346", "gen4", "gen4_bin2", "square640", "custom"))
    pixel_pitch_um: Optional[float] = opt(None, "pixel pitch, micrometres (from the preset; null = unknown)",
                                          rng=(0.1, 1000.0))
    focal_length_mm: Optional[float] = opt(None, "lens focal length, mm; with pixel_pitch_um it sets fov_deg "
                                           "= 2 atan(width_px pitch / 2 f); null = use fov_deg", rng=(0.1, 1000.0))

    principal_point_px: Optional[list] = opt(None, "[cx, cy] focus of expansion (principal point) in pixel "
                                             "coordinates, pixel centres at integers, x right, y down; "
                                             "null = the sensor centre ((W-1)/2, (H-1)/2); every estimator "
                                             "uses it (not in paper)")

    def __post_init__(self):
        _apply_sensor_preset(self)


#: The DVS128 set-up's horizontal field of view (the paper's), deg: ``camera.fov_deg``'s default,
#: and the one assumed for a dataset or checkpoint that records no focal length.
DEFAULT_FOV_DEG = 60.0


def focal_length_px(width_px: float, fov_deg: float) -> float:
    """Focal length in pixels of a pinhole camera ``width_px`` wide with the horizontal field of
    view ``fov_deg`` (degrees): (W / 2) / tan(fov / 2)."""
    import math

    return 0.5 * float(width_px) / math.tan(math.radians(float(fov_deg)) / 2.0)


#: Sensor presets: (width_px, height_px, pixel_pitch_um, focal_length_mm or None). The lenses are
#: chosen for a horizontal field of view near the DVS128 default of 60 degrees (not vendor kits);
#: set camera.focal_length_mm for another lens. DVS128 keeps fov_deg (60, the paper's set-up).
SENSOR_PRESETS = {
    "dvs128": (128, 128, 40.0, None),
    "davis346": (346, 260, 18.5, 5.5),
    "gen4": (1280, 720, 4.86, 5.5),
    "gen4_bin2": (640, 360, 9.72, 5.5),  # gen4 (1280x720, 4.86 um) read out 2x2-binned
    "square640": (640, 640, 10.0, 5.5),
}


def _apply_sensor_preset(cam: "CameraConfig") -> None:
    """Fill the preset's geometry into ``cam`` and derive fov_deg from pitch and focal length.

    A field left at its class default takes the preset's value; a field set to another value than
    the preset's is an error naming both (so a saved config reloads unchanged)."""
    import math

    if cam.sensor != "custom":
        if cam.sensor not in SENSOR_PRESETS:
            raise ConfigError(f"camera.sensor: {cam.sensor!r} is not allowed; choose one of "
                              f"{sorted(SENSOR_PRESETS) + ['custom']}")
        w, h, pitch, focal = SENSOR_PRESETS[cam.sensor]
        for name, val, default in (("width_px", w, 128), ("height_px", h, 128), ("pixel_pitch_um", pitch, None)):
            cur = getattr(cam, name)
            if cur == default or cur is None:
                setattr(cam, name, val)
            elif cur != val:
                raise ConfigError(f"camera.{name}: {cur} contradicts camera.sensor = {cam.sensor!r} ({val}); "
                                  f"set camera.sensor = 'custom' for another geometry")
        if cam.focal_length_mm is None and focal is not None:
            cam.focal_length_mm = focal
    if cam.focal_length_mm is not None and cam.pixel_pitch_um is not None:
        fov = math.degrees(2 * math.atan(cam.width_px * cam.pixel_pitch_um * 1e-3 / (2 * cam.focal_length_mm)))
        if cam.fov_deg not in (60.0, fov) and abs(cam.fov_deg - fov) > 1e-9:
            raise ConfigError(f"camera.fov_deg: {cam.fov_deg} contradicts the lens ({cam.focal_length_mm} mm on "
                              f"{cam.width_px} px of {cam.pixel_pitch_um} um give {fov:.4f} deg); set one of them")
        cam.fov_deg = fov


@dataclass
class SiteConfig:
    """One landing site and the initial conditions of its descent."""

    name: str = opt("A", "site name; its terrain spec is configs/sites/<name>.yaml", choices=SITE_NAMES)
    z0_m: float = opt(10000.0, "initial altitude above the landing point, m", rng=(1.0, 100000.0))
    v0_mps: float = opt(-200.0, "initial vertical velocity, m/s (negative = descending)",
                        rng=(-10000.0, 0.0), open_hi=True)


@dataclass
class RenderConfig:
    """Scene rendering."""

    renderer: str = opt("fast", "renderer: a name in dvsland.render.available_renderers() ('fast', 'pyrender', "
                        "or one registered with register_renderer); checked where the renderer is built")
    sun_elevation_deg: Optional[float] = opt(None, "override every site's sun elevation, degrees "
                                             "(not in paper; sites default to ~15 deg)", rng=(1.0, 90.0))
    ambient: float = opt(0.02, "ambient irradiance floor as a fraction of full sun (not in paper)",
                         rng=(0.0, 1.0), open_lo=True)
    min_altitude_m: float = opt(10.0, "lowest altitude the renderer accepts, m", rng=(0.1, 1e5), open_lo=True)
    max_altitude_m: float = opt(20000.0, "highest altitude the renderer accepts, m", rng=(1.0, 1e6))
    threads: int = opt(1, "CPU threads of the fast renderer's texture sampling: 1 = one part, torch's thread "
                          "count left alone; N > 1 or 0 (= all cores) switch torch to N threads inside each render "
                          "call (not in paper; docs/howto/devices.md)", rng=(0, 256))
    compile: str = opt("false", "fuse the fast renderer's torch sampling (relief and both levels) with torch.compile: "
                       "auto = on a CUDA device, where the torch path runs; the CPU's compiled kernels run "
                       "regardless. Off by default: its speed on a GPU is unmeasured (docs/howto/devices.md)",
                       choices=COMPILE_MODES)


@dataclass
class EmulatorConfig:
    """DVS pixel model (standard log-intensity crossing model; docs/events.md)."""

    threshold: float = opt(0.1, "ON contrast threshold (log intensity)", rng=(0.0, 10.0), open_lo=True)
    threshold_off: Optional[float] = opt(None, "OFF contrast threshold; null = same as threshold",
                                         rng=(0.0, 10.0), open_lo=True)
    refractory_us: float = opt(15.0, "pixel refractory period, microseconds", rng=(0.0, 1e7))
    log_eps: float = opt(1e-4, "epsilon in L = log(I + eps)", rng=(0.0, 1.0), open_lo=True)
    interpolation: str = opt("log", "interpolate log intensity or linear irradiance between frames",
                             choices=("log", "linear"))
    mismatch_sigma: float = opt(0.0, "per-pixel threshold mismatch (std. dev., relative); 0 = ideal "
                                "(not in paper)", rng=(0.0, 1.0))
    background_rate_hz: float = opt(0.0, "background activity per pixel, events/s; 0 = ideal "
                                    "(not in paper)", rng=(0.0, 1e4))
    # non-ideal pixel parts (dvsland.events.pixel_model; docs/events.md), all off = the ideal pixel
    photoreceptor_cutoff_hz: float = opt(0.0, "photoreceptor low-pass cut-off at full_irradiance and above, Hz; "
                                         "proportional to irradiance below it; 0 = ideal (not in paper)",
                                         rng=(0.0, 1e7))
    full_irradiance: float = opt(1.0, "irradiance at which cut-off and shot-noise rate reach their bright "
                                 "values (renderer units: 1 = albedo-1 plate facing the sun)",
                                 rng=(0.0, 1e6), open_lo=True)
    shot_noise_rate_hz: float = opt(0.0, "shot-noise events per pixel per second (ON + OFF) in the dark; "
                                    "0 = ideal (not in paper)", rng=(0.0, 1e4))
    shot_noise_bright_factor: float = opt(0.25, "shot-noise rate at full_irradiance relative to the dark rate "
                                          "(v2e: 0.25)", rng=(0.0, 100.0))
    leak_rate_hz: float = opt(0.0, "leak (ON) events per pixel per second on a static scene; 0 = ideal "
                              "(not in paper)", rng=(0.0, 1e4))
    leak_rate_sigma: float = opt(0.1, "relative std. dev. of the per-pixel leak rate", rng=(0.0, 10.0))
    hot_pixel_fraction: float = opt(0.0, "fraction of hot pixels; 0 = ideal (not in paper)", rng=(0.0, 1.0))
    hot_pixel_rate_hz: float = opt(100.0, "extra ON event rate of a hot pixel, Hz", rng=(0.0, 1e5))
    max_events_per_step: int = opt(20_000_000, "most events one step may emit (all cameras together); more is "
                                   "an error naming this parameter, raised before the events are allocated "
                                   "(about 48 bytes per event at the peak; not in paper)", rng=(1, 10**11))
    max_events_per_descent: int = opt(10_000, "a step of B descents may emit up to this times B events where that "
                                      "is more than max_events_per_step: the cap grows with a large batch (B = 8192: "
                                      "82 M events, about 3.7 GiB); 0 = max_events_per_step alone (not in paper)",
                                      rng=(0, 10**9))
    compile: str = opt("false", "fuse the ideal pixel's step (its torch path, log interpolation) with torch.compile "
                       "over every pixel at once: auto = on a CUDA device; the CPU's compiled kernel runs regardless. "
                       "Off by default: its speed on a GPU is unmeasured (docs/howto/devices.md)",
                       choices=COMPILE_MODES)
    # front-end denoising of every step's events (dvsland.events.denoise; docs/events.md), not in paper
    denoise: str = opt("none", "front-end event filters: 'none', or 'baf', 'refractory', 'hot_pixel' joined by '+' "
                       "(applied left to right, e.g. 'hot_pixel+baf'; tonic's definitions)")
    denoise_baf_time_us: float = opt(10_000.0, "baf: an event needs a neighbour's event within this time "
                                     "before it, us", rng=(0.0, 1e9), open_lo=True)
    denoise_baf_neighbours: int = opt(4, "baf: 4 (tonic) or 8 (jAER) neighbour pixels", choices=(4, 8))
    denoise_refractory_us: float = opt(1_000.0, "refractory filter: an event within this time after the "
                                       "pixel's previous event is dropped, us", rng=(0.0, 1e9))
    denoise_hot_pixel_rate_hz: float = opt(50.0, "hot_pixel: pixels whose mean rate since the start exceeds "
                                           "this are masked, Hz", rng=(0.0, 1e6), open_lo=True)


@dataclass
class DPRConfig:
    """The paper's Density Peaks Ranking + mean-shift estimator (section 4)."""

    n_max: int = opt(15, "N_max: centroids kept by DPR", rng=(1, 1000))
    n_min: int = opt(15, "n_min: events within R needed to keep a centroid", rng=(1, 100000))
    radius_px: float = opt(4.0, "R: flat mean-shift kernel radius, px", rng=(0.5, 64.0))
    c_min: int = opt(3, "C_min: below this many centroids, re-initialise with DPR", rng=(2, 1000))
    r_min_px: float = opt(3.0, "r_min: drop a centroid closer than this to the edge, px", rng=(0.0, 64.0))
    memory_ms: float = opt(500.0, "temporal memory T of events, ms", rng=(1.0, 100000.0))
    blur_sigma_px: float = opt(2.0, "DPR Gaussian blur sigma, px (not in paper)", rng=(0.1, 32.0))
    meanshift_iters: int = opt(20, "maximum mean-shift iterations per step (not in paper)", rng=(1, 1000))
    meanshift_tol_px: float = opt(0.01, "mean-shift convergence tolerance, px (not in paper)",
                                  rng=(0.0, 10.0), open_lo=True)
    merge_px: float = opt(1.0, "centroids closer than this merge, the lower-ranked is dropped, px (not in paper)",
                          rng=(0.0, 64.0))
    nms_px: int = opt(3, "odd max-pool window of the DPR local maxima, px (not in paper)", rng=(1, 63))
    pair_weighting: str = opt("none", "Eq. 8 average over pairs: none = the paper's plain mean, length = "
                              "weighted by pair length (not in paper)", choices=("none", "length"))
    baseline_steps: int = opt(1, "1 = the paper's Eq. 8 between consecutive steps; k > 1 compares each pair with "
                              "its length up to k steps ago, inverse-variance weighted (not in paper)", rng=(1, 1000))
    hot_pixel_factor: float = opt(0.0, "cap each pixel of the windowed image at this many times the element's mean "
                                       "count per active pixel (hot pixels; not in paper); 0 = off", rng=(0.0, 1e6))


@dataclass
class CMaxConfig:
    """Contrast-maximisation divergence estimator (after McLeod et al. 2022; not in the paper).

    Defaults chosen on the open-loop evaluation (docs/estimators.md): an adaptive window in which
    the scene grows by about 10 %, dithered event positions, radial density flattening, one
    warm-started Newton round on 4000 events per element, and the lag correction."""

    window_ms: float = opt(1000.0, "event window warped per estimate, ms", rng=(1.0, 10000.0))
    d_min: float = opt(-1.0, "lowest divergence searched, 1/s", rng=(-100.0, 0.0))
    d_max: float = opt(0.5, "highest divergence searched, 1/s", rng=(0.0, 100.0))
    n_grid: int = opt(21, "coarse grid size of the D search (memory: one warped image per candidate; 2001 = "
                      "steps of 0.1 1/s over the widest [d_min, d_max])", rng=(3, 2001))
    n_refine: int = opt(2, "refinement rounds around the best grid value", rng=(0, 20))
    min_events: int = opt(50, "fewer events in the window than this gives NaN", rng=(1, 10**9))
    refine_points: int = opt(9, "odd number of candidates per refinement round", rng=(3, 1001))
    max_events: int = opt(4000, "events warped per element on a 128 x 128 sensor (x sqrt(W H) / 128 on a larger "
                                "one; thinned by a hash of each event); 0 = all",
                          rng=(0, 10**9))
    dither: bool = opt(True, "spread events uniformly within their pixel before warping")
    blur_sigma_px: float = opt(0.0, "Gaussian blur of the warped image before the variance, px (0 = none)",
                               rng=(0.0, 16.0))
    window_motion: float = opt(0.1, "adaptive window: target |D| * window (0 = fixed window_ms)", rng=(0.0, 10.0))
    window_min_ms: float = opt(200.0, "shortest adaptive window, ms", rng=(1.0, 100000.0))
    window_max_ms: float = opt(3000.0, "longest adaptive window, ms", rng=(1.0, 100000.0))
    newton_iters: int = opt(1, "Newton rounds (3 candidates each) per update, warm-started", rng=(1, 100))
    step_motion: float = opt(0.01, "first Newton step = step_motion / window, 1/s per 1/s", rng=(0.0, 1.0),
                             open_lo=True)
    extrapolate: bool = opt(True, "carry the window-middle estimate to the end of the interval (linear "
                                   "time-to-contact trend)")
    trend_steps: int = opt(100, "estimates in the trend fit of extrapolate", rng=(3, 100000))
    radial_bin_px: float = opt(8.0, "flatten the event density over radius about the FoE in annuli this wide, "
                                    "px (0 = off)", rng=(0.0, 1000.0))
    research_rel: float = opt(0.5, "search globally again when the estimate's half-split standard error exceeds "
                                   "this fraction of |D|", rng=(0.0, 1e9), open_lo=True)
    smooth_steps: int = opt(20, "with extrapolate: average the last this many estimates along the trend line "
                               "(0 or 1 = off; <= trend_steps)", rng=(0, 100000))
    radial_power: float = opt(0.5, "exponent of the radial density flattening: weight = (mean density / "
                                   "annulus density)^radial_power (0 = off, 1 = flat)", rng=(0.0, 2.0))
    smooth_clip: float = opt(1.0, "keep the averaged estimate within this many standard errors of the unaveraged "
                                  "one (bounds the lag where tau is not linear; 0 = no bound)", rng=(0.0, 100.0))
    smooth_by_std: bool = opt(False, "weight the averaged estimates by 1 / their half-split variance")
    research_zero: float = opt(1.0, "search globally again when |D| is below this many first Newton steps "
                                    "(step_motion / window): a warm start near zero stays locked (0 = off)",
                               rng=(0.0, 1e3))
    window_growth: float = opt(1.5, "the adaptive window grows by at most this factor per update, and only from a "
                                    "trusted estimate (one near zero or lost sets it back to window_ms)",
                               rng=(1.0, 1e3))
    hot_pixel_factor: float = opt(8.0, "down-weight the events of a pixel holding more than this many times its "
                                       "element's mean count per active pixel (hot pixels; 0 = off)", rng=(0.0, 1e6))
    trend_tol: float = opt(0.15, "use the extrapolate trend only where its line fits tau to this RMS fraction "
                                 "of the mean tau (0 = always)", rng=(0.0, 1e3))
    structure_none: float = opt(0.15, "noise floor of the score: an estimate whose score exceeds that of "
                                      "structureless events by at most this fraction is no estimate (NaN)",
                                rng=(0.0, 1e3))
    structure_full: float = opt(0.4, "... by at least this fraction it keeps its confidence (linear between; "
                                     "0 = no noise-floor test; needs dither)", rng=(0.0, 1e3))


@dataclass
class OracleConfig:
    """Ground-truth divergence, optionally corrupted, for controller studies."""

    noise_abs: float = opt(0.0, "additive Gaussian noise sigma, 1/s", rng=(0.0, 100.0))
    noise_rel: float = opt(0.0, "proportional Gaussian noise sigma (fraction of |D|)", rng=(0.0, 100.0))
    delay_steps: int = opt(0, "delay in control steps", rng=(0, 10000))


@dataclass
class SNNConfig:
    """The trained spiking estimator 'snn' (docs/estimators_snn.md)."""

    checkpoint: str = opt("", "checkpoint from scripts/train_snn.py; empty = the one shipped with dvsland")
    warmup_steps: int = opt(5, "updates after a reset that return NaN while the read-out charges", rng=(0, 10000))
    max_silent_steps: int = opt(10, "NaN after this many updates in a row without an event in the annulus "
                                    "(0 = never)", rng=(0, 100000))
    confidence_events: float = opt(100.0, "annulus events per update at which the confidence is 0.5",
                                   rng=(0.0, 1e9), open_lo=True)


@dataclass
class LearnedConfig:
    """A network trained by the recipe, 'learned' (docs/learning.md)."""

    checkpoint: str = opt("", "checkpoint of `dvsland train --model ...`; empty or 'cnn' = the shipped CNN, "
                              "'cnn_realistic' = the shipped CNN fine-tuned through the realistic pixel too, "
                              "'cnn_landing' = the shipped CNN fine-tuned on the landing loss in the closed loop, "
                              "'cnn_wide' = the shipped CNN fine-tuned through both pixels on terrains and on "
                              "procedural textures zoomed at |D| up to 0.6 1/s (dvsland dataset zoom), "
                              "'cnn_dagger' = cnn_wide trained on its own closed-loop flights through the realistic "
                              "pixel (two rounds), "
                              "'cnn_both' = the shipped CNN fine-tuned on its own datasets flown through both "
                              "pixels (ideal and realistic_sensor), "
                              "'spiking' = the shipped spiking model, "
                              "'spiking8' = the spiking model on eight control steps (0.8 s) of events, "
                              "'spiking8_px2' = spiking8 refined onto 2-pixel cells, "
                              "'spiking8_px2_more' = spiking8_px2 fine-tuned on four more seeds of both laws, "
                              "'spiking8_both' = spiking8 fine-tuned on its datasets flown through both pixels, "
                              "'spiking8_dagger' = spiking8_both trained on its own closed-loop flights through the "
                              "realistic pixel")
    min_events: int = opt(20, "windows with fewer events give no estimate (NaN)", rng=(1, 1000000000))
    flips: int = opt(1, "mirrored copies of each window the network reads, their estimates averaged (test-time "
                        "mirroring; the recipe trains on mirrored windows): 1 = the window alone, 2 = and its 180 "
                        "degree turn, 4 = and its mirrorings in x and y, 8 = and their transposes; each copy costs "
                        "one more forward", choices=(1, 2, 4, 8))


@dataclass
class FusedConfig:
    """Several estimators on the same events, one estimate, 'fused' (not in paper; docs/estimators.md)."""

    members: str = opt("cmax,learned", "the member estimators, comma-separated (at least two; each built from its "
                                       "own section, e.g. estimator.cmax, estimator.learned)")
    rule: str = opt("precision", "how their estimates combine: 'precision' = the inverse-variance mean of their "
                                 "relative sigmas, inflated where they disagree; 'priority' = the first member whose "
                                 "confidence reaches min_confidence, else the most confident",
                    choices=("precision", "priority"))
    min_confidence: float = opt(0.15, "the bar of rule 'priority'", rng=(0.0, 1.0))
    tables: str = opt("members", "with estimator.calibration a set (ideal, realistic): 'members' = each member by "
                                 "its own table (more accurate); 'own' = the combined output by fused's own table "
                                 "where one ships for these members and checkpoint, the members raw (better "
                                 "calibrated per step), else each member by its own",
                      choices=("own", "members"))


@dataclass
class AbstainConfig:
    """The motion-evidence test every event estimator runs behind (not in paper): a window that shows
    no moving scene (sensor noise, a static scene, a global flicker) gives no estimate."""

    enabled: bool = opt(True, "run the test (false: every estimate passes as its estimator gave it)")
    cell_px: int = opt(8, "side of the cells of the clustering index, px", rng=(2, 256))
    clustering_none: float = opt(1.4, "clustering index (1 = random) at or below which a window shows no structure",
                                 rng=(0.0, 1e3))
    clustering_full: float = opt(1.6, "clustering index at or above which it shows a scene", rng=(0.0, 1e3))
    neighbours_none: float = opt(3.25, "neighbour excess over random (standard errors) at or below which a window "
                                 "shows no structure", rng=(-1e3, 1e3))
    neighbours_full: float = opt(4.25, "neighbour excess at or above which it shows a scene", rng=(-1e3, 1e3))
    flicker_full: float = opt(0.5, "|corr(polarity, time)| at or below which a window is no flicker", rng=(0.0, 1.0))
    flicker_none: float = opt(0.7, "|corr(polarity, time)| at or above which it is a flicker (no estimate)",
                              rng=(0.0, 1.0))
    min_events: int = opt(200, "events of one descent in a window below which it is not judged", rng=(0, 10**9))
    full_events: int = opt(300, "events from which a window is judged fully", rng=(0, 10**9))
    saturated_from: float = opt(0.6, "share of active pixels from which the clustering and neighbour tests "
                                "fade out (most pixels active: they cannot show structure; the flicker test "
                                "stays)", rng=(0.0, 1.0))
    saturated_full: float = opt(0.75, "share of active pixels at which they no longer judge", rng=(0.0, 1.0))


@dataclass
class EstimatorConfig:
    """Which divergence estimator runs, and its parameters."""

    name: str = opt("dpr", "estimator name (see dvsland.estimators.available_estimators())")
    dpr: DPRConfig = opt(None, "parameters of 'dpr'", factory=DPRConfig)
    cmax: CMaxConfig = opt(None, "parameters of 'cmax'", factory=CMaxConfig)
    oracle: OracleConfig = opt(None, "parameters of 'oracle'", factory=OracleConfig)
    snn: SNNConfig = opt(None, "parameters of 'snn'", factory=SNNConfig)
    learned: LearnedConfig = opt(None, "parameters of 'learned'", factory=LearnedConfig)
    fused: FusedConfig = opt(None, "parameters of 'fused' (its members' own sections hold theirs)",
                             factory=FusedConfig)
    abstain: AbstainConfig = opt(None, "the motion-evidence test every event estimator runs behind",
                                 factory=AbstainConfig)
    calibration: str = opt("none", "post-hoc confidence calibration (not in paper): 'none' = the estimator's own "
                           "confidence; 'ideal' or 'realistic' = the table shipped for the estimator and that pixel "
                           "(dvsland/estimators/calibration/<estimator>_<set>.json); a shipped name such as "
                           "'cmax_realistic'; or a path to a .json table fitted by `dvsland evaluate --calibration "
                           "--fit-calibration` (docs/estimators.md)")
    params: dict = opt(None, "free-form keyword parameters for other (third-party) estimators",
                       factory=dict)


@dataclass
class ControllerSetting:
    """One controller setting (paper: Kp = 5e6 with n_bin = 5, Kp = 4e6 with n_bin = 10)."""

    kp: float = opt(5e6, "proportional gain Kp, N/s", rng=(0.0, 1e12), open_lo=True)
    n_bin: int = opt(5, "moving-average filter length, estimates", rng=(1, 10000))
    label: str = opt("", "label used in results and logs; empty = derived from kp and n_bin")


def _paper_settings():
    return [ControllerSetting(kp=5e6, n_bin=5), ControllerSetting(kp=4e6, n_bin=10)]


@dataclass
class DivPConfig:
    """Options of the ``div_p`` law (the paper's released implementation)."""

    feedforward_mg: bool = opt(False, "add m g to u = Kp e (the released code: no)")


@dataclass
class DivGSConfig:
    """Options of the ``div_gs`` law (gain scheduled on the efference-copy altitude; not in paper)."""

    lambda_per_s: float = opt(1.0, "divergence-loop rate lambda, 1/s (gain K = lambda m z_hat)",
                              rng=(0.0, 100.0), open_lo=True)
    d_final_per_s: float = opt(0.03, "divergence of the final constant-divergence approach, 1/s (the speed "
                               "at altitude z is then d_final z: 1.5 m/s at 50 m)", rng=(0.0, 10.0), open_lo=True)
    v_min_mps: float = opt(0.0, "lowest sink rate of the final approach, m/s (0 = none): the target is "
                           "-max(d_final, v_min / z_hat), so a too-low altitude estimate cannot make the craft "
                           "hover above the ground", rng=(0.0, 1000.0))
    v_min_sigma: float = opt(0.0, "the sink-rate floor grows by this many of the filter's posterior standard "
                             "deviations of the velocity: v_min + v_min_sigma sigma_v (0 = off), so that a velocity "
                             "estimate the filter cannot vouch for still descends (needs controller.filter="
                             "efference_fit or efference)", rng=(0.0, 10.0))


@dataclass
class PolicyLawConfig:
    """Options of the ``policy`` law: a small network's thrust (``dvsland train-loop --what policy``; not in paper)."""

    checkpoint: str = opt("", "the trained policy's checkpoint (policy.pt of dvsland train-loop); empty = an "
                          "untrained network that starts near hover")
    hidden: int = opt(32, "hidden units of an untrained network (a checkpoint carries its own)", rng=(1, 4096))
    tau_min_s: float = opt(4.0, "lowest time to contact of the observed target -1/max(tau0 - c2 t, tau_min), s",
                           rng=(0.0, 1e4), open_lo=True)
    observation: str = opt("basic", "what the network sees: basic (filtered D, D*(t), their difference, hover "
                           "fraction) or efference (also the raw estimate D_hat, its confidence and the filter's "
                           "altitude; needs controller.filter=efference_fit or efference) or efference_doubt (also "
                           "the efference_fit filter's offsets from its plan in prior sigmas and its rejected share; "
                           "needs controller.filter=efference_fit); a checkpoint records its own",
                           choices=("basic", "efference", "efference_doubt"))
    base: str = opt("none", "none: thrust = sigmoid(net) x top; div_gs: a residual on div_gs (controller.div_gs's "
                    "constants), thrust = u_div_gs + authority x m g tanh(net), which starts as div_gs exactly",
                    choices=("none", "div_gs"))
    authority: float = opt(1.0, "the residual's reach in units of m g (base=div_gs only; 1 for base=none): "
                           "thrust = u_div_gs + authority x m g tanh(net); a checkpoint records its own",
                           rng=(0.0, 3.0), open_lo=True)


@dataclass
class EfferenceConfig:
    """Options of the ``efference`` filter: EKF on (z, v) fusing D_hat with the known thrust (not in paper)."""

    prior_scale: float = opt(1.0, "initial guess = prior_scale x the nominal (z0, v0)", rng=(0.0, 100.0),
                             open_lo=True)
    prior_rel_sigma: float = opt(0.3, "relative std. dev. of the prior on z and v", rng=(0.0, 10.0), open_lo=True)
    accel_sigma_mps2: float = opt(0.05, "absolute std. dev. of the known acceleration, m/s^2", rng=(0.0, 100.0))
    accel_sigma_rel: float = opt(0.02, "relative std. dev. of the thrust acceleration u/m", rng=(0.0, 10.0))
    meas_sigma_rel: float = opt(0.3, "relative std. dev. of one D_hat", rng=(0.0, 100.0))
    meas_sigma_abs: float = opt(0.005, "absolute std. dev. of one D_hat, 1/s", rng=(0.0, 100.0), open_lo=True)
    gate_sigma: float = opt(5.0, "reject an estimate further than this many std. dev. from the prediction",
                            rng=(0.0, 1e6), open_lo=True)
    min_altitude_m: float = opt(1.0, "lowest altitude estimate, m", rng=(0.0, 1e5), open_lo=True)
    prior_rel_sigma_v: Optional[float] = opt(None, "relative std. dev. of the prior on v; null = prior_rel_sigma",
                                             rng=(0.0, 10.0), open_lo=True)
    prior_state: str = opt("nominal", "prior (z0, v0): the site's nominal start (the craft does not know its "
                           "dispersion) or the dispersed start itself", choices=("nominal", "dispersed"))
    meas_noise: str = opt("fixed", "R of one D_hat: fixed (meas_sigma_rel, meas_sigma_abs) or confidence (plus the "
                          "estimator's own error 0.1 sqrt(1/c - 1) from its confidence() c; c = 0: no update)",
                          choices=("fixed", "confidence"))
    huber_k: float = opt(0.0, "clip accepted innovations to this many std. dev. (Huber); 0 = off", rng=(0.0, 1e6))
    max_step_rel: float = opt(0.0, "largest relative change of z_hat and v_hat in one update; 0 = off",
                              rng=(0.0, 10.0))
    cov_cap_rel: float = opt(0.0, "cap of the std. dev. of z and v relative to z_hat and |v_hat|; 0 = off",
                             rng=(0.0, 100.0))
    cauchy_c: float = opt(2.0, "efference_fit: scale of the Cauchy weight of an estimate, std. dev.",
                          rng=(0.0, 1e6), open_lo=True)
    iterations: int = opt(3, "efference_fit: Gauss-Newton rounds per control step", rng=(1, 100))
    forget_s: float = opt(0.0, "efference_fit: an estimate's weight decays as exp(-age / forget_s), s; 0 = never",
                          rng=(0.0, 1e6))
    min_confidence: float = opt(0.0, "estimates whose confidence() is below this are not used", rng=(0.0, 1.0))


@dataclass
class ControllerConfig:
    """The thrust law, its per-descent settings, its filter and bounds."""

    name: str = opt("tau_p", "controller law: tau_p (Eq. 2 in tau-space), div_p (the paper's released code), "
                    "div_gs (gain scheduled on the efference-copy altitude), policy (a network trained by dvsland "
                    "train-loop), or a registered name "
                    "(see dvsland.control.available_controllers())")
    c2: float = opt(0.5, "slope of the TTC target tau*(t) = tau0 - c2 t (the paper's text: c^2 = 0.5; "
                    "its released code: c*c = 0.25)", rng=(0.0, 1.0), open_lo=True, open_hi=True)
    settings: list = opt(None, "controller settings flown for every site", factory=_paper_settings)
    thrust_min_n: float = opt(0.0, "lowest thrust, N (not in paper: an engine cannot pull)", rng=(0.0, 1e9))
    thrust_max_n: Optional[float] = opt(None, "highest thrust, N; null = unbounded (Eq. 2 as written; "
                                        "not in paper)", rng=(0.0, 1e12), open_lo=True)
    missing_policy: str = opt("hold", "what to do when the filtered estimate is missing (and, for tau_p, "
                              "wrong-signed): hold the last thrust, or hover (m g)", choices=("hold", "hover"))
    filter: str = opt("auto", "divergence filter: moving_average (mean of the last n_bin estimates), "
                      "efference (EKF with the known thrust; gives an altitude estimate), auto (efference "
                      "for a law that needs an altitude, else moving_average)",
                      choices=("auto", "moving_average", "efference", "efference_fit"))
    div_p: DivPConfig = opt(None, "options of 'div_p'", factory=DivPConfig)
    div_gs: DivGSConfig = opt(None, "options of 'div_gs'", factory=DivGSConfig)
    policy: PolicyLawConfig = opt(None, "options of 'policy'", factory=PolicyLawConfig)
    efference: EfferenceConfig = opt(None, "options of the 'efference' filter", factory=EfferenceConfig)
    params: dict = opt(None, "free-form keyword options for other (third-party) controllers", factory=dict)


@dataclass
class DynamicsConfig:
    """Vertical 1-D lander dynamics (paper Eq. 1)."""

    g_mps2: float = opt(1.62, "gravity, m/s^2 (Moon)", rng=(0.0, 100.0), open_lo=True)
    g0_mps2: float = opt(9.81, "standard gravity for Isp, m/s^2", rng=(0.1, 100.0))
    isp_s: float = opt(600.0, "specific impulse, s", rng=(1.0, 1e5))
    mass_kg: float = opt(10000.0, "initial mass, kg (not in paper)", rng=(0.0, 1e9), open_lo=True)
    dry_mass_kg: float = opt(1000.0, "dry mass: thrust ends when reached, kg (not in paper)",
                             rng=(0.0, 1e9), open_lo=True)
    integrator: str = opt("exact", "integration over a control step, thrust held: exact (rocket equation), "
                          "euler (one explicit Euler step: the paper's released code), substeps (RK4)",
                          choices=("exact", "euler", "substeps"))
    substeps: int = opt(100, "sub-steps per control step for integrator='substeps'", rng=(1, 100000))


def _paper_sites():
    """The paper's nine sites with their initial conditions (:data:`PAPER_INITIAL_CONDITIONS`)."""
    return [SiteConfig(name=n, z0_m=z0, v0_mps=v0) for n, (z0, v0) in PAPER_INITIAL_CONDITIONS.items()]


@dataclass
class SimulationConfig:
    """The batched closed-loop experiment."""

    sites: list = opt(None, "sites and their initial conditions (default: the paper's nine)",
                     factory=_paper_sites)
    seed: int = opt(0, "master seed; expands to per-element seeds", rng=(0, 2**63 - 1))
    n_seeds: int = opt(1, "independent seeds per (site, setting)", rng=(1, 100000))
    t_max_s: float = opt(200.0, "timeout, s of flight", rng=(0.0, 1e6), open_lo=True)
    success_altitude_m: float = opt(50.0, "success when altitude <= this, m", rng=(0.0, 1e5))
    crash_divergence: float = opt(0.5, "crash when |D| = -v/z >= this, 1/s", rng=(0.0, 1e3), open_lo=True)
    device: str = opt("cpu", "torch device ('cpu', 'cuda', 'cuda:0', ...)")
    seed_offset: int = opt(0, "first seed index of this batch: seeds seed_offset .. seed_offset + n_seeds - 1 "
                           "(a campaign shard); dispersion draws depend on the seed index, not the batch",
                           rng=(0, 2**62))
    torch_threads: int = opt(1, "torch CPU threads set for the run; 0 = leave torch's default (1 measured "
                             "fastest on 2 cores: the per-step ops are small)", rng=(0, 256))
    max_memory_gb: float = opt(0.0, "refuse a run whose estimated peak memory (per-pixel state of every "
                               "descent plus emulator.max_events_per_step events) exceeds this, GiB; 0 = 80 % "
                               "of this machine's memory (not in paper)", rng=(0.0, 1e6))
    compact: bool = opt(True, "finished descents leave the hot path: their events are dropped before the "
                        "estimator (false: the estimator still sees them; docs/campaigns.md)")
    compile: str = opt("auto", "run the filter's and the law's steps through torch.compile: a few fused kernels "
                       "instead of hundreds of small ones per step, after a one-off compile of about 10 s; auto = on "
                       "a GPU (where it pays: +7 % descent-steps/s over the first steps and +9.5 % near the ground "
                       "at B = 8192 on an H200), not on a CPU (where the filter's rounds run in a compiled kernel "
                       "already and inductor needs a C++ compiler); true/false force it (docs/howto/devices.md)",
                       choices=COMPILE_MODES)


@dataclass
class Dispersion:
    """One dispersed parameter: off (the config's nominal value), fixed, uniform on [low, high],
    or normal (mean, std) clipped to [low, high]. Drawn per (site, seed index); see
    :mod:`dvsland.layout.dispersion`."""

    kind: str = opt("off", "distribution", choices=("off", "fixed", "uniform", "normal"))
    value: float = opt(0.0, "the value of 'fixed'", rng=(-1e9, 1e9))
    low: float = opt(0.0, "lower bound of 'uniform'; clip bound of 'normal'", rng=(-1e9, 1e9))
    high: float = opt(0.0, "upper bound of 'uniform'; clip bound of 'normal'", rng=(-1e9, 1e9))
    mean: float = opt(0.0, "mean of 'normal'", rng=(-1e9, 1e9))
    std: float = opt(0.0, "standard deviation of 'normal'", rng=(0.0, 1e9))


#: allowed range of each dispersed parameter's draws (checked on low/high/value/mean)
DISPERSION_RANGES = {
    "z0_scale": (0.05, 20.0), "v0_scale": (0.05, 20.0), "sun_elevation_deg": (1.0, 90.0),
    "sun_azimuth_offset_deg": (-360.0, 360.0), "threshold_scale": (0.01, 100.0),
    "mismatch_sigma": (0.0, 1.0), "background_rate_hz": (0.0, 1e4), "refractory_us": (0.0, 1e7),
}


@dataclass
class DispersionConfig:
    """Per-seed dispersions of a Monte Carlo batch (not in paper). ``enabled: false`` (the
    default) switches all of them off: every seed then flies the nominal experiment."""

    enabled: bool = opt(False, "master switch of every dispersion below")
    terrain_variants: int = opt(0, "scene: seed k flies terrain realisation k mod N of its site (0 = the shipped "
                                "terrain, j = variant '<site>~j', the same statistics drawn anew); 0 or 1 = off",
                                rng=(0, 1000))
    sun_elevation_deg: Dispersion = opt(None, "scene: sun elevation, degrees (replaces the site's)",
                                        factory=Dispersion)
    sun_azimuth_offset_deg: Dispersion = opt(None, "scene: added to the site's sun azimuth, degrees",
                                             factory=Dispersion)
    sun_step_deg: float = opt(1.0, "scene: sun angles are rounded to this step so that seeds share prepared "
                              "scenes (each distinct scene costs one terrain preparation)", rng=(0.01, 90.0))
    z0_scale: Dispersion = opt(None, "flight: factor on the site's initial altitude z0_m", factory=Dispersion)
    v0_scale: Dispersion = opt(None, "flight: factor on the site's initial velocity v0_mps", factory=Dispersion)
    threshold_scale: Dispersion = opt(None, "sensor: factor on the ON and OFF contrast thresholds",
                                      factory=Dispersion)
    mismatch_sigma: Dispersion = opt(None, "sensor: per-pixel threshold mismatch std. dev. (relative), "
                                     "replaces emulator.mismatch_sigma", factory=Dispersion)
    background_rate_hz: Dispersion = opt(None, "sensor: background events per pixel per second, replaces "
                                         "emulator.background_rate_hz", factory=Dispersion)
    refractory_us: Dispersion = opt(None, "sensor: refractory period, us, replaces emulator.refractory_us",
                                    factory=Dispersion)


@dataclass
class LoggingConfig:
    """Run output."""

    root: str = opt("logs", "folder under which run folders are made")
    tensorboard: bool = opt(True, "write TensorBoard event files")
    image_every_s: float = opt(5.0, "log frames and event images every this many s of flight",
                               rng=(0.0, 1e6), open_lo=True)
    scalar_every_s: float = opt(0.5, "write TensorBoard scalars every this many s of flight (the control "
                                "step or less: every step; traces.npz always holds every step)",
                                rng=(0.0, 1e6), open_lo=True)
    figures: bool = opt(True, "write PNG figures at the end of a run")
    quiet: bool = opt(False, "no progress bar or summary printout")


@dataclass
class Config:
    """A whole dvsland run."""

    name: str = opt("run", "run name; the run folder is logs/<name>-<UTC timestamp>/")
    camera: CameraConfig = opt(None, factory=CameraConfig)
    render: RenderConfig = opt(None, factory=RenderConfig)
    emulator: EmulatorConfig = opt(None, factory=EmulatorConfig)
    estimator: EstimatorConfig = opt(None, factory=EstimatorConfig)
    controller: ControllerConfig = opt(None, factory=ControllerConfig)
    dynamics: DynamicsConfig = opt(None, factory=DynamicsConfig)
    simulation: SimulationConfig = opt(None, factory=SimulationConfig)
    logging: LoggingConfig = opt(None, factory=LoggingConfig)
    dispersion: DispersionConfig = opt(None, factory=DispersionConfig)

    @property
    def dt_s(self) -> float:
        """Control / frame interval, s."""
        return 1.0 / self.camera.frame_rate_hz

    def initial_conditions(self, site: str) -> tuple:
        """(z0_m, v0_mps) of ``site`` from ``simulation.sites``, else the paper's
        (:data:`PAPER_INITIAL_CONDITIONS`; a variant ``A~1`` takes its site's)."""
        for s in self.simulation.sites:
            if s.name == site:
                return float(s.z0_m), float(s.v0_mps)
        base = str(site).split("~")[0]
        if base not in PAPER_INITIAL_CONDITIONS:
            raise ValueError(f"unknown site {site!r}: expected one of {', '.join(SITE_NAMES)}")
        return PAPER_INITIAL_CONDITIONS[base]


#: Element types of list-valued fields (dataclass annotations cannot say it at runtime).
LIST_ITEM_TYPES = {
    (SimulationConfig, "sites"): SiteConfig,
    (ControllerConfig, "settings"): ControllerSetting,
}
