"""The fast batched torch renderer (docs/render.md).

Per site, levels of detail are prepared once (:mod:`dvsland.render.lod`): shaded irradiance and
relative height on sun-aligned tiles, each level twice the extent of the previous. All tiles of
all sites sit side by side in two atlas textures (rows = sites, columns = levels). Per frame:

1. LOD: the ground pixel p = altitude * 2 tan(fov/2) / W gives lambda = log2(p / texel_0); the
   two levels floor(lambda), floor(lambda) + 1 are blended (trilinear mip). A level's content is
   band-limited to its texel (features >= 2 texels), so a pixel averages its footprint and
   nothing shimmers as the camera descends.
2. Parallax: the ray of pixel (i, j) first meets the datum at t * z (t the ray slope); the
   height h there (finer level) moves the hit to t * (z - h) (relief displacement).
3. One ``grid_sample`` of the irradiance atlas for both levels of all B frames (per-element
   offsets into the atlas, no per-element texture copies), then the blend.
4. View angle: tiles are shaded for a nadir view; a fixed per-pixel gain applies the
   lunar-Lambert brightening of flat ground seen off-axis (up to ~20 % in the corners at 60 deg).

Everything per frame is elementwise on (B, H, W) plus two ``grid_sample`` calls: no Python loop
over the batch, no host sync besides the input checks.

CPU threads (``render.threads``, docs/howto/devices.md): torch's CPU ``grid_sample`` runs its batch
dimension in parallel and nothing else, and the atlas is one texture (batch 1), so a plain call uses
one core. With ``render.threads: 1`` (the default) a render call samples in one part and leaves
torch's thread count alone: the process's setting (``simulation.torch_threads``, ``--threads``)
rules. Only when threads are asked for explicitly (``render.threads`` N > 1, or 0 = all cores) is
the sampling grid split into that many equal parts over an ``expand``-ed (not copied) atlas, and the
call runs with that many torch threads, then restores the caller's setting. On a shared machine
extra threads cost more than they bring (docs/howto/devices.md has the measurement).
"""

from __future__ import annotations

import math
import os
import sys
import time
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from dvsland.compiled import CompiledFn, compile_on
from dvsland.config import CameraConfig, RenderConfig
from dvsland.terrain import load_site

from . import native_render
from .base import Renderer
from .lod import LevelParams, SiteLevels, level_params_for, prepare_levels


class FastRenderer(Renderer):
    """Batched LOD-atlas renderer (see module doc).

    Args:
        site_names, camera, render, device: as :class:`Renderer`.
        level_size: texels per level side (default: enough for the camera, 384 for 128 px).
        parallax_iters: relief-displacement iterations (0 = none, 1 default).
        disk_cache: keep prepared levels on disk (``$DVSLAND_CACHE_DIR``).
        progress: show a progress bar over the scenes being prepared (tqdm on stderr: scene, where
            its levels came from, ETA).
        chunk: frames per internal sub-batch (default 32 on CPU, 1024 on CUDA); a batch of more than
            8 sub-batches takes up to 4 x ``chunk`` frames per sub-batch (:func:`sub_batch`).
        blend_levels: trilinear blend of the two bracketing levels (default); False samples the
            nearest level only (an ablation: levels then pop during a descent).
        threads: CPU threads used inside a render call (default ``render.threads``): 1 = one part,
            torch's thread count left as the caller set it; N > 1 or 0 (= all cores) = the sampling
            split in that many parts, torch switched to that many threads during the call and
            restored afterwards. Ignored on CUDA.
        native: on the CPU, sample with the compiled passes of :mod:`dvsland.render.native_render`
            where they are enabled (``DVSLAND_NATIVE_RENDER``, built on first use where a C++ compiler
            is found): the same frames, bit for bit, in about half the time. False: torch's
            ``grid_sample`` always (the reference path).
        compile: fuse the torch path's sampling (:func:`relief_ranges` and :func:`sample_levels`) with
            ``torch.compile`` (default ``render.compile``: "auto" = on a CUDA device, "true", "false");
            the frames equal the eager path's within float rounding; a compile that fails warns once and
            runs eagerly.

    Attributes:
        prep_s: {site: wall seconds spent preparing its levels (0 when cached)}; prep_cpu_s the
            process CPU seconds (the uncontended cost on a shared machine).
        levels: the :class:`LevelParams`.
    """

    name = "fast"

    def __init__(self, site_names: Sequence[str], camera: CameraConfig, render: Optional[RenderConfig] = None,
                 device="cpu", level_size: Optional[int] = None, parallax_iters: int = 1,
                 disk_cache: bool = True, progress: bool = False, blend_levels: bool = True,
                 chunk: Optional[int] = None, threads: Optional[int] = None, suns=None, altitude_ranges=None,
                 native: bool = True, compile: Optional[str] = None):
        super().__init__(site_names, camera, render, device)
        self.native = bool(native)
        rc = self.render_config
        self._compiled = _compiled_sampling(getattr(rc, "compile", "false") if compile is None else compile,
                                            self.device)
        threads = rc.threads if threads is None else threads
        if threads < 0:
            raise ValueError(f"threads must be >= 0 (0 = all cores), got {threads}")
        self.threads = 1 if self.device.type != "cpu" else (threads or os.cpu_count() or 1)
        # torch's global thread count is switched inside a call only when threads were asked for
        self._switch_threads = self.device.type == "cpu" and threads != 1
        if parallax_iters < 0 or parallax_iters > 8:
            raise ValueError(f"parallax_iters must be in [0, 8], got {parallax_iters}")
        self.parallax_iters = int(parallax_iters)
        self.blend_levels = bool(blend_levels)
        if chunk is None:
            chunk = 1024 if self.device.type == "cuda" else 32
        if chunk < 1:
            raise ValueError(f"chunk must be >= 1, got {chunk}")
        self.chunk = int(chunk)
        self.levels: LevelParams = level_params_for(camera, rc, level_size)
        self.prep_s = {}
        self.prep_cpu_s = {}
        self.sources = {}
        tiles = []
        # suns: per entry of site_names (elevation_deg or None, azimuth offset deg): dispersed scenes
        self._scene_keys = scene_keys(self.site_names, suns)
        # altitude_ranges (dispersed scenes only): per entry (lo_m, hi_m) its descents fly through:
        # only the levels that range samples are prepared (lazy levels), frames clamp to them
        k_rng = {}
        if altitude_ranges is not None:
            if suns is None or len(altitude_ranges) != len(self.site_names):
                raise ValueError("altitude_ranges needs suns and one (lo_m, hi_m) per site")
            for key, (a_lo, a_hi) in zip(self._scene_keys, altitude_ranges):
                k_lo = int(math.floor(self._lam(max(float(a_lo), rc.min_altitude_m))))
                k_hi = min(int(math.floor(self._lam(min(float(a_hi), rc.max_altitude_m)))) + 1, self.levels.n_levels - 1)
                old = k_rng.get(key, (k_lo, k_hi))
                k_rng[key] = (max(0, min(k_lo, old[0])), max(k_hi, old[1]))
        keys = list(dict.fromkeys(self._scene_keys))
        if suns is not None:  # scenes of one terrain one after another: their fields are computed once
            keys.sort(key=lambda k: (k.split("@")[0], k))
        from tqdm.auto import tqdm

        bar = tqdm(total=len(keys), desc="terrain", unit="scene", leave=False, disable=not progress, file=sys.stderr)
        for key in keys:
            name = key
            if suns is None:
                terrain = load_site(name, rc.sun_elevation_deg)
            else:
                from .scenes import load_scene

                terrain = load_scene(key, rc.sun_elevation_deg)
            t0 = time.perf_counter()
            if suns is None:
                lv = prepare_levels(terrain, self.levels, disk_cache=disk_cache)
            else:
                from .scenes import prepare_scene_levels

                lv = prepare_scene_levels(terrain, self.levels, key, disk_cache=disk_cache, levels=k_rng.get(key))
            lv.sun_elevation_deg = terrain.sun_elevation_deg
            self.prep_s[name] = lv.prep_s
            self.prep_cpu_s[name] = lv.prep_cpu_s
            self.sources[name] = lv.source
            bar.set_postfix(scene=name, levels=f"{lv.source} {time.perf_counter() - t0:.1f}s", refresh=False)
            bar.update(1)
            bar.refresh()  # each scene shows, also when it came from the cache faster than tqdm redraws
            tiles.append(lv)
        bar.close()
        self._build_atlas(tiles)

    # ------------------------------------------------------------ preparation
    def _build_atlas(self, tiles: Sequence[SiteLevels]) -> None:
        p, dev = self.levels, self.device
        t = p.tile_size
        order = {lv.name: i for i, lv in enumerate(tiles)}
        ha, wa = len(tiles) * t, p.n_levels * t
        self._atlas_pair, self._atlas_tiled = self._assemble_atlases(tiles, ha, wa)
        row_of_site = [order[s] for s in self._scene_keys]
        self._site_row = torch.tensor(row_of_site, dtype=torch.float32, device=dev)
        ang = torch.tensor([tiles[r].angle_rad for r in row_of_site], dtype=torch.float64)
        self._cos = torch.cos(ang).to(device=dev, dtype=torch.float32)
        self._sin = torch.sin(ang).to(device=dev, dtype=torch.float32)
        self.h0_m = {lv.name: lv.h0_m for lv in tiles}
        rngs = [getattr(tiles[r], "levels", None) for r in row_of_site]
        if any(x is not None for x in rngs):
            k_top = p.n_levels - 1.0
            lo = [0.0 if x is None else float(x[0]) for x in rngs]
            # lo + 1 (the blend's and parallax's coarser level) must be prepared: lam < k_hi
            hi = [k_top if x is None or x[1] >= k_top else float(x[1]) - 1e-4 for x in rngs]
            self._lam_lo = torch.tensor(lo, dtype=torch.float32, device=self.device)
            self._lam_hi = torch.tensor(hi, dtype=torch.float32, device=self.device)
        else:
            self._lam_lo = self._lam_hi = None
        self._pitch = self.pixel_m_per_m()
        tx, ty = self.ray_tangents(torch.float64)  # (H, W)
        self._gain = self._emission_gain(tiles, row_of_site, tx, ty)
        # one (H, W) gain when all sites share it (same sun elevation): no per-frame gather
        self._gain_shared = self._gain[0] if bool((self._gain == self._gain[:1]).all()) else None
        # normalised atlas coordinates of tile centres (align_corners=False), float32 with
        # exact integer numerators: x = (level * 2T + T) / W_atlas - 1, y likewise per site row
        self._ox = (2.0 * t, float(t), float(wa))
        self._oy_site = ((self._site_row * (2.0 * t) + t) / ha - 1.0).contiguous()
        # per-site ray slopes in the sun frame, u along (c, s) toward the sun, v along (s, -c), scaled
        # to normalised atlas units per metre at level 0 and stored coordinate-planar (2, S, H, W):
        # every per-frame op is then a plain broadcast over (H, W) (an interleaved (..., 2) layout
        # times a (..., 1) range ran 12x slower), and the grid for grid_sample is a permuted view.
        # Full resolution and 2x2-block resolution (for the parallax pass).
        nrm = torch.tensor([2.0 / (wa * p.base_texel_m), 2.0 / (ha * p.base_texel_m)], dtype=torch.float64)
        self._slopes = self._sun_frame_slopes(tx, ty, nrm)
        h2, w2 = self.height_px // 2, self.width_px // 2
        if self.parallax_iters and h2 >= 2 and w2 >= 2 and self.height_px % 2 == 0 and self.width_px % 2 == 0:
            blk = lambda t: t.reshape(h2, 2, w2, 2).mean(dim=(1, 3))  # noqa: E731
            self._slopes_half = self._sun_frame_slopes(blk(tx), blk(ty), nrm)
        else:
            self._slopes_half = None

    def _assemble_atlases(self, tiles: Sequence[SiteLevels], ha: int, wa: int):
        """((irradiance, height) atlases of (ha, wa) texels, whether in tiles): row r T ... (r + 1) T holds
        scene r's levels side by side, laid out as the sampling will read them (:meth:`_atlases`): in
        tiles for the compiled passes (CPU), else row-major as (1, 1, ha, wa) tensors on the device."""
        t, dev = self.levels.tile_size, self.device
        tiled = dev.type == "cpu" and self.native and native_render.fits((ha, wa)) and native_render.LIBRARY.enabled()
        if tiled:
            pair = native_render.tiled_empty(ha, wa), native_render.tiled_empty(ha, wa)
        else:
            pair = torch.empty(ha, wa, dtype=torch.float32), torch.empty(ha, wa, dtype=torch.float32)
        for r, lv in enumerate(tiles):
            for a, lvl in zip(pair, (lv.irradiance, lv.height_m)):
                block = lvl.permute(1, 0, 2).reshape(t, -1)  # (K, T, T) -> (T, K * T)
                if tiled:
                    native_render.tiled_write(a, r * t, 0, block)
                else:
                    a[r * t:(r + 1) * t] = block
        return (pair if tiled else tuple(a.to(dev)[None, None] for a in pair)), tiled

    def _atlases(self, tiled: bool):
        """The (irradiance, height) atlases: (1, 1, S*T, K*T) float32 tensors row-major, or with ``tiled`` the
        :class:`~dvsland.render.native_render.TiledAtlas` pair the compiled passes read. One layout is held
        at a time (the atlases are most of the renderer's memory), built as the sampling will read it;
        asking for the other converts them (a mode switched after the build)."""
        if self._atlas_tiled != tiled:
            if tiled:
                self._atlas_pair = tuple(native_render.tile_atlas(a[0, 0]) for a in self._atlas_pair)
            else:
                self._atlas_pair = tuple(native_render.untile_atlas(a)[None, None] for a in self._atlas_pair)
            self._atlas_tiled = tiled
        return self._atlas_pair

    @property
    def atlas_irradiance(self) -> torch.Tensor:
        """(1, 1, S*T, K*T) float32: the shaded irradiance of every scene (rows) and level (columns)."""
        return self._atlases(False)[0]

    @property
    def atlas_height(self) -> torch.Tensor:
        """(1, 1, S*T, K*T) float32: the heights (m) in the irradiance atlas's layout."""
        return self._atlases(False)[1]

    def _emission_gain(self, tiles, row_of_site, tx: torch.Tensor, ty: torch.Tensor) -> torch.Tensor:
        """(S, H, W) per-pixel gain for the view direction: the tiles are shaded for a nadir view
        (cos e = n_z); a pixel off the axis sees flat ground at cos e = 1 / sqrt(1 + t^2), which
        lunar-Lambert brightens. gain = R(mu0, cos e_pixel) / R(mu0, 1) for flat ground. tx, ty:
        (H, W) float64 ray tangents."""
        from dvsland.terrain import lunar_lambert_l

        mu = 1.0 / torch.sqrt(1.0 + tx * tx + ty * ty)
        out = []
        for r in row_of_site:
            el = tiles[r].sun_elevation_deg
            mu0 = math.sin(math.radians(el))
            lam = lunar_lambert_l(90.0 - el)
            refl = lambda m: lam * 2 * mu0 / (mu0 + m) + (1 - lam) * mu0  # noqa: E731
            out.append(refl(mu) / refl(1.0))
        return torch.stack(out).to(device=self.device, dtype=torch.float32)

    def _sun_frame_slopes(self, tx: torch.Tensor, ty: torch.Tensor, nrm: torch.Tensor) -> torch.Tensor:
        """(2, S, H, W) float32 sun-frame slopes (u, v) of tangents tx, ty (H, W) float64, times
        nrm (2,) (normalised atlas units per metre at level 0)."""
        c = self._cos.to(torch.float64)[:, None, None]
        s = self._sin.to(torch.float64)[:, None, None]
        uv = torch.stack([(tx * c + ty * s) * nrm[0], (tx * s - ty * c) * nrm[1]])
        return uv.to(device=self.device, dtype=torch.float32).contiguous()

    def _lam(self, altitude_m: float) -> float:
        """Unclamped level of detail of one altitude (m)."""
        return math.log2(altitude_m * (self.pixel_m_per_m() / self.levels.base_texel_m))

    def lod(self, altitude_m: torch.Tensor) -> torch.Tensor:
        """Continuous level of detail lambda (B,) for altitudes (B,) m."""
        lam = torch.log2(altitude_m * (self._pitch / self.levels.base_texel_m))
        return lam.clamp(0.0, self.levels.n_levels - 1.0)

    def _render(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        if not self._switch_threads:
            return self._render_batches(altitude_m, site_idx)
        prev = torch.get_num_threads()
        if self.threads == prev:
            return self._render_batches(altitude_m, site_idx)
        torch.set_num_threads(self.threads)
        try:
            return self._render_batches(altitude_m, site_idx)
        finally:
            torch.set_num_threads(prev)

    def _render_batches(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        """(B, H, W) frames: the per-frame terms and the relief's ray ranges for the whole batch at once
        (small), then the two levels' sampling in sub-batches of ``chunk`` frames, whose grids stay
        cache-sized (B = 256 on CPU: 349 -> 200 ms with chunks of 32). The sub-batches reuse one grid
        buffer and take a handful of operator calls each, so the Python work of a step hardly grows
        with B."""
        b = altitude_m.shape[0]
        h, w = self.height_px, self.width_px
        out = torch.empty(b, h, w, device=self.device)
        if b == 0:
            return out
        lo, frac, oy, z = self._frame_terms(altitude_m, site_idx)
        ax, bx, wa = self._ox
        inv_lo = torch.exp2(-lo)[:, None, None]  # level lo texel scale relative to level 0
        kern = native_render.kernel_for(out) if self.native and native_render.fits(self._atlas_pair[0]) else None
        # rng_n: ray range (metres of z) times the level-lo scale, (B, H, W) or (B, 1, 1)
        rng_n = self._relief_range(lo, oy, z, site_idx, inv_lo, kern) if self.parallax_iters else z * inv_lo
        # grid offsets (coordinate, B) of level lo and lo + 1; level lo + 1 has half the scale of
        # level lo: g1 = (off1 - off0 / 2) + g0 / 2
        ox0 = (lo * ax + bx) / wa - 1.0
        ox1 = ((lo + 1.0) * ax + bx) / wa - 1.0
        off = torch.stack([ox0, oy, ox1 - 0.5 * ox0, oy - 0.5 * oy])[:, :, None, None]  # (4, B, 1, 1)
        gain = self._gain_shared
        if kern is not None:  # one compiled pass over the frames, the same bits (native_render)
            return kern.levels(self._atlases(True)[0], off, self._slopes, site_idx, rng_n, frac,
                               self._gain if gain is None else gain, out, self.threads)
        rows = None if gain is not None else self._gain.index_select(0, site_idx)  # (B, H, W) per frame
        if self._compiled is not None:  # render.compile: the whole batch in one fused call
            return self._compiled[1](self.atlas_irradiance, off, self._slopes.index_select(1, site_idx), rng_n,
                                     frac, gain if rows is None else rows)
        step = min(b, sub_batch(b, self.chunk))
        grid = _LevelGrid(step, h, w, self.device, self.threads, self.atlas_irradiance)
        for i in range(0, b, step):  # a handful of operator calls per sub-batch (slices clamp at the end)
            part = out[i:i + step]
            if part.shape[0] != grid.frames:  # the last, shorter sub-batch: a grid of its size
                grid = _LevelGrid(part.shape[0], h, w, self.device, self.threads, self.atlas_irradiance)
            grid.sample_into(part, off[:, i:i + step], self._slopes.index_select(1, site_idx[i:i + step]),
                             rng_n[i:i + step], frac[i:i + step], gain if rows is None else rows[i:i + step])
        return out

    def _frame_terms(self, altitude_m: torch.Tensor, site_idx: torch.Tensor):
        """Per frame: the finer level lo (B,), the blend weight frac (B, 1, 1), the tile centre's
        atlas y oy (B,) and the altitude z (B, 1, 1)."""
        k_max = self.levels.n_levels
        lam = self.lod(altitude_m)
        if self._lam_lo is not None:  # lazy levels: stay inside the prepared ones
            lam = torch.minimum(torch.maximum(lam, self._lam_lo.index_select(0, site_idx)),
                                self._lam_hi.index_select(0, site_idx))
        lo = torch.floor(lam).clamp(max=k_max - 2.0)
        frac = (lam - lo)[:, None, None]
        if not self.blend_levels:
            frac = torch.round(frac)
        oy = self._oy_site.index_select(0, site_idx)  # (B,) tile-centre y (index_select: ~5x faster than [idx])
        return lo, frac, oy, altitude_m[:, None, None]

    def _relief_range(self, lo: torch.Tensor, oy: torch.Tensor, z: torch.Tensor, site_idx: torch.Tensor,
                      inv_lo: torch.Tensor, kern=None) -> torch.Tensor:
        """Relief displacement: the ray meets the ground at slope * (z - h); heights from the next
        coarser level on 2 x 2 pixel blocks (a smooth field), upsampled bilinearly. (B, H, W) ray
        ranges (m) times the level-lo scale ``inv_lo`` (B, 1, 1). ``kern``: the compiled passes
        (:mod:`dvsland.render.native_render`), which give the same bits, or None (torch)."""
        ax, bx, wa = self._ox
        half = self._slopes_half is not None
        slopes = self._slopes_half if half else self._slopes  # (2, S, h', w')
        lvl = torch.clamp(lo + (1.0 if half else 0.0), max=self.levels.n_levels - 1.0)
        off = torch.stack([(lvl * ax + bx) / wa - 1.0, oy])[..., None, None]  # (2, B, 1, 1)
        inv = torch.exp2(-lvl)[:, None, None]
        if kern is not None:
            return kern.relief(self._atlases(True)[1], off, slopes, site_idx, z, inv, inv_lo, self.parallax_iters,
                               self.threads, upsample2x=half)  # the upsampling in the same pass
        fn = relief_ranges if self._compiled is None else self._compiled[0]  # render.compile: fused
        return fn(self.atlas_height, off, slopes.index_select(1, site_idx), z, inv, inv_lo, self.parallax_iters, half)


class _LevelGrid:
    """The sampling grid of one sub-batch of F frames at both levels, (2, 2, F, H, W) float32 (coordinate,
    level, frame, pixel), with its views for ``torch.grid_sampler`` made once: the irradiance atlas
    (expanded over the thread parts) and the grid as (parts, 2 F H / parts, W, 2)."""

    def __init__(self, frames: int, h: int, w: int, device, threads: int, atlas: torch.Tensor):
        self.frames = frames
        self.g = torch.empty(2, 2, frames, h, w, device=device)
        rows = 2 * frames * h
        n = threads if (threads > 1 and rows % threads == 0) else 1
        self.atlas = atlas.expand(n, -1, -1, -1)
        self.grid = self.g.view(2, rows, w).permute(1, 2, 0).reshape(n, rows // n, w, 2)  # a view
        self.shape = (2, frames, h, w)

    def sample_into(self, out: torch.Tensor, off: torch.Tensor, slopes: torch.Tensor, rng_n: torch.Tensor,
                    frac: torch.Tensor, gain: torch.Tensor) -> None:
        """Write into ``out`` (F, H, W) the frames sampled at off (4, F, 1, 1) + slopes (2, F, H, W) x
        rng_n (F, H, W) (level lo + 1: half of it): bilinear, border-clamped samples (align_corners
        False) of both levels, blended by frac (F, 1, 1) and times the view-angle gain ((H, W) or
        (F, H, W))."""
        torch.addcmul(off[:2], slopes, rng_n, out=self.g[:, 0])
        torch.add(off[2:], self.g[:, 0], alpha=0.5, out=self.g[:, 1])
        # F.grid_sample's own call (mode bilinear = 0, padding border = 1, align_corners False);
        # its (parts, 1, 2 F H / parts, W) result is level lo's F frames, then level lo + 1's
        both = torch.grid_sampler(self.atlas, self.grid, 0, 1, False).view(self.shape)
        torch.lerp(both[0], both[1], frac, out=out).mul_(gain)


def _compiled_sampling(mode, device):
    """(relief, levels): :func:`relief_ranges` and :func:`sample_levels` through ``torch.compile`` where
    the ``render.compile`` setting ``mode`` is on for ``device``, else None (the eager torch path)."""
    if not compile_on(mode, device):
        return None
    return (CompiledFn(relief_ranges, "render.compile", "the relief's ray ranges"),
            CompiledFn(sample_levels, "render.compile", "the levels' sampling"))


def sample_levels(atlas: torch.Tensor, off: torch.Tensor, slopes: torch.Tensor, rng_n: torch.Tensor,
                  frac: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """(F, H, W) float32 frames, as :meth:`_LevelGrid.sample_into` computes them, as one pure function
    of tensors (what ``render.compile`` fuses): the two levels' bilinear, border-clamped samples of
    ``atlas`` (1, 1, Ha, Wa) at off (4, F, 1, 1) + slopes (2, F, H, W) x rng_n ((F, H, W) or (F, 1, 1);
    level lo + 1: half of it), blended by frac (F, 1, 1), times gain ((H, W) or (F, H, W))."""
    f, h, w = slopes.shape[1:]
    g0 = torch.addcmul(off[:2], slopes, rng_n)  # (2 coordinates, F, H, W): level lo
    g1 = torch.add(off[2:], g0, alpha=0.5)  # level lo + 1
    grid = torch.stack([torch.stack([g0[0], g1[0]]), torch.stack([g0[1], g1[1]])], -1)  # (2 levels, F, H, W, 2)
    both = torch.grid_sampler(atlas, grid.view(1, 2 * f * h, w, 2), 0, 1, False).view(2, f, h, w)
    return torch.lerp(both[0], both[1], frac) * gain


def relief_ranges(atlas_h: torch.Tensor, off: torch.Tensor, slopes: torch.Tensor, z: torch.Tensor, inv: torch.Tensor,
                  inv_lo: torch.Tensor, iters: int, half: bool) -> torch.Tensor:
    """The relief's ray ranges times ``inv_lo`` (F, 1, 1), as :meth:`FastRenderer._relief_range`'s torch
    path computes them, as one pure function of tensors (what ``render.compile`` fuses): ``iters`` times
    r = max(z - height(off (2, F, 1, 1) + slopes (2, F, h, w) r inv), 0.05 z), heights sampled from
    ``atlas_h`` (1, 1, Ha, Wa); z, inv (F, 1, 1). (F, h, w), or (F, 2 h, 2 w) upsampled when ``half``."""
    f, hh, ww = slopes.shape[1:]
    rng = z
    for _ in range(iters):
        g = torch.addcmul(off, slopes, rng * inv)  # (2, F, h, w) normalised atlas coordinates
        hgt = torch.grid_sampler(atlas_h, g.view(2, f * hh, ww).permute(1, 2, 0).unsqueeze(0), 0, 1, False)
        rng = (z - hgt.view(f, hh, ww)).clamp(min=0.05 * z)
    rng_n = rng * inv_lo
    return _upsample2x(rng_n) if half else rng_n


def sub_batch(batch_size: int, chunk: int) -> int:
    """Frames per sub-batch of a render call of ``batch_size`` frames: ``chunk``, or as many as 8 equal
    sub-batches need, up to 4 x ``chunk``. The grids stay cache-sized (32 frames of 128 x 128: 8 MiB)
    while the per-sub-batch operator calls stop growing with the batch below 32 x chunk frames (B =
    576 on the CPU: 8 sub-batches of 72 frames, as fast as 18 of 32)."""
    return max(chunk, min(4 * chunk, -(-batch_size // 8)))


def scene_keys(site_names, suns=None) -> list:
    """One key per entry of ``site_names``: the name itself, or with ``suns`` (per entry
    ``(elevation_deg or None, azimuth_offset_deg)``) the scene label ``E~2@el12@az+5``."""
    if suns is None:
        return list(site_names)
    suns = list(suns)
    if len(suns) != len(site_names):
        raise ValueError(f"suns must give one (elevation_deg, azimuth_offset_deg) per site, got {len(suns)} "
                         f"for {len(site_names)} sites")
    from dvsland.layout.batch import scene_label

    return [scene_label(n, None if e is None else float(e), float(a)) for n, (e, a) in zip(site_names, suns)]


def _upsample2x(x: torch.Tensor) -> torch.Tensor:
    """(B, h, w) -> (B, 2 h, 2 w): bilinear 2x upsampling with align_corners=False and edge
    clamping, equal to ``F.interpolate(mode="bilinear")`` up to float rounding. Separable fixed
    weights (3/4, 1/4), columns first, so the row pass writes whole rows (about 2x faster than
    ``F.interpolate`` on one CPU thread for 18 x 64 x 64: 0.40 against 0.84 ms)."""
    b, h, w = x.shape
    xp = torch.cat([x[..., :1], x, x[..., -1:]], dim=2)  # (B, h, w + 2)
    y = torch.empty(b, h, w, 2, dtype=x.dtype, device=x.device)
    torch.lerp(xp[..., 1:-1], xp[..., :-2], 0.25, out=y[..., 0])
    torch.lerp(xp[..., 1:-1], xp[..., 2:], 0.25, out=y[..., 1])
    y = y.view(b, h, 2 * w)
    yp = torch.cat([y[:, :1], y, y[:, -1:]], dim=1)  # (B, h + 2, 2 w)
    z = torch.empty(b, h, 2, 2 * w, dtype=x.dtype, device=x.device)
    torch.lerp(yp[:, 1:-1], yp[:, :-2], 0.25, out=z[:, :, 0])
    torch.lerp(yp[:, 1:-1], yp[:, 2:], 0.25, out=z[:, :, 1])
    return z.view(b, 2 * h, 2 * w)
