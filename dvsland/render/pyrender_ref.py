"""The 3-D reference renderer: pyrender (OpenGL through headless EGL) on trimesh terrain meshes.

Slow on purpose and independent of the fast torch renderer: a true perspective pinhole over a
triangle mesh of the terrain, a z-buffer, a directional sun with a shadow map, and per-fragment
photometry. It exists to check :mod:`dvsland.render.fast`; see docs/render_reference.md.

How a frame is made (``render_one``):

1. Mesh. The camera sits at (0, 0, h0 + altitude) looking straight down (h0: height of the
   landing point, as the fast renderer). Altitudes are grouped in levels ``h_k = lod_step^k``
   (k integer, default step 2^(1/4)); a frame at altitude h uses the level with
   ``h_k / lod_step < h <= h_k``. The level's mesh is the terrain cropped to the footprint at
   ``h_k`` plus ``edge_margin`` on every side and ``sun_margin`` toward the sun (so that shadows
   cast from outside the view still fall in), sampled ``oversample`` times per sensor pixel at
   the bottom of the level (default 1: the terrain is band-limited to that sampling); around it
   a coarse "far field" ring (``far_field`` times wider, without its centre) casts the shadows
   of larger relief and catches rays leaving the fine patch. Meshes are cached (LRU);
   :meth:`PyrenderRenderer.fix_mesh_range` pins one mesh over a descent segment.
2. Photometry, in a fragment shader of our own (pyrender's PBR shader adds a specular lobe and
   gamma-encodes to 8 bits, neither of which belongs in a linear irradiance): per fragment

       I = albedo * (F(cos i, cos e) * lit + ambient)
       F = (1 - L) cos i + 2 L cos i / (cos i + cos e)         (lunar-Lambert, McEwen 1991)

   with i the incidence angle (sun, smooth vertex normal), e the emission angle (toward the
   camera; ``view="nadir"``: from straight up), ``L`` as the fast renderer (McEwen's L at phase
   90 deg - sun elevation) unless ``lunar_l`` is given (0 gives Lambert), ``lit`` in [0, 1] from
   the shadow map (2x2 bilinear percentage-closer filter, receiver-plane slope-scaled depth bias
   from the face normal in light space, so flat ground at a 15 deg sun shows no acne; the sun's
   orthographic box is fitted tightly to the meshes) and ``ambient`` = ``RenderConfig.ambient``.
3. Read-back. Colour is rendered to a 32-bit float framebuffer (pyrender's is 8-bit RGBA; our
   subclass swaps it), with 4x MSAA, at ``supersample`` times the sensor resolution, then
   box-averaged to the sensor pixels: each pixel averages ``4 supersample^2`` samples.

Import order: :mod:`dvsland.render.gl_env` is imported first, which sets ``PYOPENGL_PLATFORM``.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections import OrderedDict
from typing import Optional, Sequence

from dvsland.render import gl_env  # noqa: F401  (must precede pyrender / OpenGL)

import numpy as np
import torch
import trimesh

from dvsland.config.schema import CameraConfig, RenderConfig
from dvsland.render.base import Renderer
from dvsland.render.mesh import terrain_mesh

__all__ = ["PyrenderRenderer", "FRAGMENT_SHADER"]

#: Our fragment shader (replaces pyrender's mesh.frag). Uniform names follow pyrender's, so
#: pyrender binds the lights, the shadow map and the light matrix; the extra uniforms
#: (lunar_l, ambient_frac, bias_*) are set by ``_LinearRenderer._bind_lighting``.
FRAGMENT_SHADER = r"""#version 330 core
struct DirectionalLight {
    vec3 color;
    float intensity;
    vec3 direction;
#ifdef DIRECTIONAL_LIGHT_SHADOWS
    sampler2D shadow_map;
    mat4 light_matrix;
#endif
};
uniform DirectionalLight directional_lights[MAX_DIRECTIONAL_LIGHTS];
uniform int n_directional_lights;
uniform vec3 cam_pos;
uniform float lunar_l;        // lunar-Lambert weight L (0 = Lambert)
uniform float ambient_frac;   // ambient irradiance as a fraction of full sun
uniform float bias_slope;     // receiver-plane bias, in texels of lateral offset covered
uniform float bias_const;     // constant bias, in shadow-map texels of depth slope at 45 deg
uniform float nadir_view;     // 1: emission angle from straight up (as the fast renderer), 0: to the camera

in vec3 frag_position;
#ifdef NORMAL_LOC
in vec3 frag_normal;
#endif
#ifdef COLOR_0_LOC
in vec4 color_multiplier;
#endif
out vec4 frag_color;

#ifdef DIRECTIONAL_LIGHT_SHADOWS
float lit_fraction(mat4 lm, sampler2D smap, vec3 n_face)
{
    vec4 pc = lm * vec4(frag_position, 1.0);          // orthographic: w == 1
    vec3 lc = pc.xyz * 0.5 + 0.5;                      // uv in [0,1], depth in [0,1]
    if (lc.x < 0.0 || lc.x > 1.0 || lc.y < 0.0 || lc.y > 1.0 || lc.z > 1.0) return 1.0;
    vec2 size = vec2(textureSize(smap, 0));
    // Rows of the linear part of the light matrix: a_k = s_k r_k (r_k orthonormal light axes).
    vec3 a0 = vec3(lm[0][0], lm[1][0], lm[2][0]);
    vec3 a1 = vec3(lm[0][1], lm[1][1], lm[2][1]);
    vec3 a2 = vec3(lm[0][2], lm[1][2], lm[2][2]);
    float s0 = length(a0), s1 = length(a1), s2 = length(a2);
    vec3 nl = vec3(dot(a0, n_face) / s0, dot(a1, n_face) / s1, dot(a2, n_face) / s2);
    float nz = max(abs(nl.z), 0.05);
    // depth (NDC) change per unit NDC x / y on the receiver's plane
    float gx = abs(s2 / s0 * nl.x / nz), gy = abs(s2 / s1 * nl.y / nz);
    float texel_dx = 2.0 / size.x, texel_dy = 2.0 / size.y;   // one texel in NDC
    float bias_ndc = bias_slope * (gx * texel_dx + gy * texel_dy)
                   + bias_const * (s2 / s0 * texel_dx + s2 / s1 * texel_dy);
    float compare = lc.z - 0.5 * bias_ndc;
    // bilinear percentage-closer filter over the 2x2 nearest texel centres (4 taps)
    vec2 tex = 1.0 / size;
    vec2 f = fract(lc.xy * size - 0.5);
    vec2 c = (floor(lc.xy * size - 0.5) + 0.5) / size;
    float lb = compare > texture(smap, c).r ? 1.0 : 0.0;
    float lt = compare > texture(smap, c + vec2(0.0, tex.y)).r ? 1.0 : 0.0;
    float rb = compare > texture(smap, c + vec2(tex.x, 0.0)).r ? 1.0 : 0.0;
    float rt = compare > texture(smap, c + tex).r ? 1.0 : 0.0;
    return 1.0 - mix(mix(lb, lt, f.y), mix(rb, rt, f.y), f.x);
}
#endif

void main()
{
    float albedo = 1.0;
#ifdef COLOR_0_LOC
    albedo = color_multiplier.r;
#endif
    vec3 n_face = normalize(cross(dFdx(frag_position), dFdy(frag_position)));
    if (n_face.z < 0.0) n_face = -n_face;
#ifdef NORMAL_LOC
    vec3 n = normalize(frag_normal);
#else
    vec3 n = n_face;
#endif
    vec3 v = nadir_view > 0.5 ? vec3(0.0, 0.0, 1.0) : normalize(cam_pos - frag_position);
    float cos_e = max(dot(n, v), 0.0);
    float direct = 0.0;
    for (int k = 0; k < n_directional_lights; k++) {
        vec3 l = normalize(-directional_lights[k].direction);
        float cos_i = max(dot(n, l), 0.0);
        float f = (1.0 - lunar_l) * cos_i;
        if (cos_i + cos_e > 0.0) f += 2.0 * lunar_l * cos_i / (cos_i + cos_e);
        float lit = 1.0;
#ifdef DIRECTIONAL_LIGHT_SHADOWS
        if (f > 0.0) lit = lit_fraction(directional_lights[k].light_matrix,
                                        directional_lights[k].shadow_map, n_face);
#endif
        direct += directional_lights[k].intensity * f * lit;
    }
    frag_color = vec4(albedo * (direct + ambient_frac), 0.0, 0.0, 1.0);
}
"""


def _write_shader_dir() -> str:
    """A temporary folder with pyrender's vertex/depth shaders and our mesh.frag."""
    pyrender = gl_env.import_pyrender()
    src = os.path.join(os.path.dirname(pyrender.__file__), "shaders")
    dst = tempfile.mkdtemp(prefix="dvsland_pyrender_shaders_")
    for name in os.listdir(src):
        with open(os.path.join(src, name), "r") as f:
            text = f.read()
        with open(os.path.join(dst, name), "w") as f:
            f.write(text)
    with open(os.path.join(dst, "mesh.frag"), "w") as f:
        f.write(FRAGMENT_SHADER)
    return dst


def _make_linear_renderer_class():
    """pyrender.Renderer subclass: float32 colour framebuffer, tight sun shadow box, our uniforms."""
    pyrender = gl_env.import_pyrender()
    from OpenGL import GL
    from pyrender.renderer import Renderer

    class _LinearRenderer(Renderer):
        shading_uniforms: dict = {}
        light_box = None  # (V (4,4), P (4,4)) of the sun's shadow camera, set per scene
        shadow_key = None  # identifies (meshes, sun): the shadow map is redrawn only when it changes
        _drawn_shadow_key = None

        def _shadow_mapping_pass(self, scene, light_node, flags):
            if self.shadow_key is not None and self.shadow_key == self._drawn_shadow_key:
                return  # same meshes, same sun: the shadow map in the light's texture still holds
            super()._shadow_mapping_pass(scene, light_node, flags)
            self._drawn_shadow_key = self.shadow_key

        def _get_light_cam_matrices(self, scene, light_node, flags):
            if self.light_box is not None:
                return self.light_box
            return super()._get_light_cam_matrices(scene, light_node, flags)

        def _bind_lighting(self, scene, program, node, flags):
            super()._bind_lighting(scene, program, node, flags)
            for k, val in self.shading_uniforms.items():
                program.set_uniform(k, float(val))

        def _configure_main_framebuffer(self):
            if self._main_fb is not None and (self.viewport_width, self.viewport_height) != tuple(self._main_fb_dims):
                self._delete_main_framebuffer()
            if self._main_fb is not None:
                return
            w, h = self.viewport_width, self.viewport_height
            self._main_cb, self._main_db = GL.glGenRenderbuffers(2)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._main_cb)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA32F, w, h)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._main_db)
            GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT24, w, h)
            self._main_fb = GL.glGenFramebuffers(1)
            GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
            GL.glFramebufferRenderbuffer(GL.GL_DRAW_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, self._main_cb)
            GL.glFramebufferRenderbuffer(GL.GL_DRAW_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, self._main_db)
            self._main_cb_ms, self._main_db_ms = GL.glGenRenderbuffers(2)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._main_cb_ms)
            GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, 4, GL.GL_RGBA32F, w, h)
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._main_db_ms)
            GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, 4, GL.GL_DEPTH_COMPONENT24, w, h)
            self._main_fb_ms = GL.glGenFramebuffers(1)
            GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb_ms)
            GL.glFramebufferRenderbuffer(GL.GL_DRAW_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, self._main_cb_ms)
            GL.glFramebufferRenderbuffer(GL.GL_DRAW_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, self._main_db_ms)
            status = GL.glCheckFramebufferStatus(GL.GL_DRAW_FRAMEBUFFER)
            if status != GL.GL_FRAMEBUFFER_COMPLETE:
                raise RuntimeError(f"float multisample framebuffer incomplete (status {status})")
            self._main_fb_dims = (w, h)

        def _read_main_framebuffer(self, scene, flags):
            w, h = self._main_fb_dims
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
            GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
            GL.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST)
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb)
            buf = GL.glReadPixels(0, 0, w, h, GL.GL_RED, GL.GL_FLOAT)
            img = np.frombuffer(buf, dtype=np.float32).reshape(h, w)
            return np.flip(img, axis=0).copy()

    return _LinearRenderer, pyrender


def _ortho(left, right, bottom, top, near, far) -> np.ndarray:
    """OpenGL orthographic projection matrix (4, 4) float64."""
    P = np.eye(4)
    P[0, 0] = 2.0 / (right - left)
    P[1, 1] = 2.0 / (top - bottom)
    P[2, 2] = -2.0 / (far - near)
    P[0, 3] = -(right + left) / (right - left)
    P[1, 3] = -(top + bottom) / (top - bottom)
    P[2, 3] = -(far + near) / (far - near)
    return P


def _sun_pose(sun_dir: np.ndarray) -> np.ndarray:
    """(4, 4) pose whose +z axis points toward the sun (pyrender lights shine along -z)."""
    z = np.asarray(sun_dir, np.float64)
    z = z / np.linalg.norm(z)
    ref = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(ref, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, y, z
    return pose


def _light_box(sun_pose: np.ndarray, vertices: np.ndarray):
    """(V, P) of an orthographic sun camera enclosing ``vertices`` (N, 3) (via their bounding box)."""
    R = sun_pose[:3, :3]
    lo3, hi3 = vertices.min(axis=0), vertices.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo3[0], hi3[0]) for y in (lo3[1], hi3[1]) for z in (lo3[2], hi3[2])])
    p = corners @ R                      # coordinates along the light axes x, y, z
    lo, hi = p.min(axis=0), p.max(axis=0)
    pad = 1e-3 * max(float(np.max(hi - lo)), 1e-6)
    lo, hi = lo - pad, hi + pad
    pose = np.eye(4)
    pose[:3, :3] = R
    pose[:3, 3] = R @ np.array([0.0, 0.0, hi[2] + pad])  # camera sits sun-ward of everything
    V = np.linalg.inv(pose)
    # in camera coordinates z_cam = z - (hi+pad); visible depth -z_cam in [pad, hi - lo + 2 pad]
    P = _ortho(lo[0], hi[0], lo[1], hi[1], pad, (hi[2] - lo[2]) + 2 * pad)
    return V, P


class PyrenderRenderer(Renderer):
    """The pyrender reference behind the ``Renderer`` interface (``get_renderer("pyrender", ...)``).

    Args:
        site_names: names of the sites, indexed by ``site_idx`` in :meth:`render`.
        camera: the camera (``width_px``, ``height_px``, ``fov_deg`` across the width).
        render: render options (``ambient``, ``sun_elevation_deg``, altitude range).
        device: torch device of the returned frames (rendering itself is OpenGL on the CPU here).
        shadows: cast shadows (a shadow map); without, only ``cos i`` shading.
        lunar_l: lunar-Lambert weight L for every site; None = per site, as the fast renderer:
            McEwen's L(phase) at phase = 90 deg - sun elevation.
        oversample: terrain samples per sensor pixel at the bottom of a level, in [0.25, 8]
            (the terrain is band-limited to that sampling: features >= ~2 samples).
        mesh_upsample: mesh vertices per terrain sample per side (interpolated, >= 1).
        lod_step: altitude ratio between mesh levels (> 1).
        supersample: render at this many times the sensor resolution per axis, then box-average.
        edge_margin, sun_margin: mesh margins as fractions of the footprint.
        far_field: side of the coarse shadow-casting ring as a multiple of the mesh side
            (0 disables); its vertex count per side is ``far_field_n``.
        cache_size: meshes kept (LRU) across calls.
        view: emission angle e of the photometry: "camera" (toward the camera, physical) or
            "nadir" (from straight up, as the fast renderer's pre-shaded levels).
        terrains: terrain objects to use instead of ``load_site(name)`` (tests: closed-form scenes).
    """

    name = "pyrender"

    def __init__(self, site_names: Sequence[str], camera: CameraConfig, render: Optional[RenderConfig] = None,
                 device="cpu", *, shadows: bool = True, lunar_l: Optional[float] = None, oversample: float = 1.0,
                 lod_step: float = 2 ** 0.25, supersample: int = 2, edge_margin: float = 0.05,
                 sun_margin: float = 0.5, far_field: float = 3.0, far_field_n: int = 160,
                 cache_size: int = 6, view: str = "camera", mesh_upsample: int = 1,
                 terrains: Optional[Sequence] = None):
        super().__init__(site_names, camera, render, device=device)
        if not gl_env.egl_available():
            raise RuntimeError(gl_env.egl_unavailable_reason())
        self.shadows = bool(shadows)
        if view not in ("camera", "nadir"):
            raise ValueError(f"view must be 'camera' or 'nadir', got {view!r}")
        self.view = view
        if not 0.25 <= oversample <= 8.0:
            raise ValueError(f"oversample must be in [0.25, 8], got {oversample}")
        if not lod_step > 1.0:
            raise ValueError(f"lod_step must be > 1, got {lod_step}")
        if int(supersample) < 1 or int(supersample) > 8:
            raise ValueError(f"supersample must be an integer in [1, 8], got {supersample}")
        if far_field != 0 and far_field <= 1.0:
            raise ValueError(f"far_field must be 0 (off) or > 1, got {far_field}")
        self.oversample = float(oversample)
        self.lod_step = float(lod_step)
        self.supersample = int(supersample)
        self.edge_margin = float(edge_margin)
        self.sun_margin = float(sun_margin)
        self.far_field = float(far_field)
        self.far_field_n = int(far_field_n)
        self.cache_size = int(cache_size)
        if int(mesh_upsample) < 1:
            raise ValueError(f"mesh_upsample must be an integer >= 1, got {mesh_upsample}")
        self.mesh_upsample = int(mesh_upsample)
        self._serial = 0
        self.bias_slope = 3.0  # texels of receiver-plane slope covered (the 2x2 filter reaches 1 texel;
        #                        the rest absorbs face normals blurred by quad derivatives at triangle edges)
        self.bias_const = 1.0  # plus one texel of a 45-degree slope
        if terrains is None:
            from dvsland.terrain import load_site

            terrains = [load_site(s, sun_elevation_deg=self.render_config.sun_elevation_deg) for s in self.site_names]
        elif len(terrains) != len(self.site_names):
            raise ValueError(f"terrains must have one entry per site ({len(self.site_names)}), got {len(terrains)}")
        self.terrains = list(terrains)
        if lunar_l is not None and not 0.0 <= lunar_l <= 1.0:
            raise ValueError(f"lunar_l must be in [0, 1], got {lunar_l}")
        #: lunar-Lambert L per site: given, or the fast renderer's rule L(phase = 90 deg - sun elevation)
        self.lunar_l = [float(lunar_l) if lunar_l is not None else _lunar_l_of(t) for t in self.terrains]

        self._pyrender = gl_env.import_pyrender()
        self._osr = None
        self._scene = None
        self._mesh_nodes = []
        self._scene_key = None
        self._cache: "OrderedDict[tuple, tuple]" = OrderedDict()
        self._h0: dict = {}
        self._fixed = None

    # ---------------------------------------------------------------- geometry of a level
    @property
    def half_fov_tan(self) -> float:
        return self.tan_half_fov

    def square_footprint_m(self, altitude_m: float) -> float:
        """Side of the ground square seen at ``altitude_m`` over flat ground (max of width, height), m."""
        return self.footprint_m(altitude_m) * max(1.0, self.camera.height_px / self.camera.width_px)

    def level_of(self, altitude_m: float) -> int:
        """Mesh level k with ``lod_step^(k-1) < altitude_m <= lod_step^k``."""
        return int(math.ceil(math.log(altitude_m) / math.log(self.lod_step) - 1e-9))

    def level_patch(self, site: int, level):
        """(extent_m, n, center_xy_m) of the fine mesh of a level (an int k, or a fixed range
        ``("fixed", h_top_m, h_bottom_m)``, see :meth:`fix_mesh_range`)."""
        if isinstance(level, tuple):
            h_top, h_bottom = float(level[1]), float(level[2])
        else:
            h_top = self.lod_step ** level
            h_bottom = h_top / self.lod_step
        fp = self.square_footprint_m(h_top)
        extent = fp * (1.0 + 2.0 * self.edge_margin + self.sun_margin)
        sun = np.asarray(self.terrains[site].sun_direction, np.float64)
        horiz = sun[:2] / max(np.linalg.norm(sun[:2]), 1e-12)
        if np.linalg.norm(sun[:2]) < 1e-9:
            horiz = np.zeros(2)
        center = horiz * fp * self.sun_margin / 2.0
        px_bottom = self.square_footprint_m(h_bottom) / max(self.camera.width_px, self.camera.height_px)
        n = int(math.ceil(extent / (px_bottom / self.oversample)))
        return extent, n, (float(center[0]), float(center[1]))

    def ground_z_m(self, site: int) -> float:
        """Height h0 of the landing point (0, 0) above the datum, m: altitudes are measured from it.

        As the fast renderer (:mod:`dvsland.render.lod`): the terrain band-limited to the central
        pixel's ground size at ``min_altitude_m``, mean of the 2 x 2 texels around (0, 0).
        """
        if site not in self._h0:
            terrain = self.terrains[site]
            texel = self.pixel_m_per_m() * self.render_config.min_altitude_m
            self._h0[site] = float(terrain.height_at_origin(texel)) if hasattr(terrain, "height_at_origin") else 0.0
        return self._h0[site]

    def camera_z_m(self, altitude_m: float, site: int) -> float:
        """World z of the camera for a frame at ``altitude_m`` over site ``site``, m."""
        return self.ground_z_m(site) + float(altitude_m)

    # ---------------------------------------------------------------- GL state
    def _ensure_gl(self):
        if self._osr is not None:
            return
        cls, pyrender = _make_linear_renderer_class()
        self._pyrender = pyrender
        w, h = self.camera.width_px * self.supersample, self.camera.height_px * self.supersample
        self._osr = pyrender.OffscreenRenderer(w, h)
        self._osr._renderer.__class__ = cls
        self._osr._renderer.shading_uniforms = {}
        self._osr._renderer.light_box = None
        self._shader_dir = _write_shader_dir()
        self._osr._renderer._program_cache = pyrender.shader_program.ShaderProgramCache(shader_dir=self._shader_dir)
        self._scene = pyrender.Scene(bg_color=np.zeros(4), ambient_light=np.zeros(3))
        ss = self.supersample
        fx = (self.camera.width_px * ss / 2.0) / self.half_fov_tan
        self._cam = pyrender.IntrinsicsCamera(fx=fx, fy=fx, cx=self.camera.width_px * ss / 2.0,
                                              cy=self.camera.height_px * ss / 2.0, znear=1.0, zfar=10.0)
        self._cam_node = self._scene.add(self._cam, pose=np.eye(4))
        self._light = pyrender.DirectionalLight(color=np.ones(3), intensity=1.0)
        self._light_node = self._scene.add(self._light, pose=np.eye(4))

    def close(self) -> None:
        """Free the GL context (also done at garbage collection)."""
        if getattr(self, "_osr", None) is not None:
            try:
                gl_env.delete_offscreen(self._osr)
            except Exception:
                pass
        self._osr = None
        if getattr(self, "_shader_dir", None):
            import shutil

            shutil.rmtree(self._shader_dir, ignore_errors=True)
            self._shader_dir = None
        if hasattr(self, "_cache"):
            self._cache.clear()

    def __del__(self):
        self.close()

    def _primitive_mesh(self, tm):
        """pyrender.Mesh from a trimesh with float albedo (no 8-bit quantisation)."""
        pyrender = self._pyrender
        alb = tm.vertex_attributes["albedo"].astype(np.float32)
        col = np.stack([alb, alb, alb, np.ones_like(alb)], axis=1)
        mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=np.ones(4), metallicFactor=0.0,
                                                 roughnessFactor=1.0, doubleSided=True)
        prim = pyrender.Primitive(positions=np.asarray(tm.vertices, np.float32),
                                  normals=np.asarray(tm.vertex_normals, np.float32),
                                  indices=np.asarray(tm.faces, np.uint32), color_0=col, material=mat)
        return pyrender.Mesh(primitives=[prim])

    def fix_mesh_range(self, top_m: Optional[float] = None, bottom_m: Optional[float] = None) -> None:
        """Use ONE mesh for every frame with ``bottom_m <= altitude <= top_m`` (covering the view at
        ``top_m``, sampled for ``bottom_m``): no level switches inside a short descent segment, e.g.
        to count events without the reference's own level pops. ``fix_mesh_range()`` restores levels.
        """
        if top_m is None:
            self._fixed = None
            return
        if not (0 < bottom_m <= top_m):
            raise ValueError(f"need 0 < bottom_m <= top_m, got bottom_m={bottom_m}, top_m={top_m}")
        self._fixed = (float(top_m), float(bottom_m))

    def level_meshes(self, site: int, level):
        """The trimesh meshes of a level: [fine] or [fine, far-field ring] (cached)."""
        key = (site, level)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        terrain = self.terrains[site]
        extent, n, center = self.level_patch(site, level)
        fine = terrain_mesh(terrain, extent, n, center, upsample=self.mesh_upsample)
        meshes = [fine]
        if self.far_field > 0:
            ext_far = extent * self.far_field
            nf = self.far_field_n
            far = terrain_mesh(terrain, ext_far, nf, center)
            # drop the ring's faces inside the fine patch (shrunk by one coarse texel: overlap)
            c = far.triangles_center
            inner = extent / 2.0 - ext_far / nf
            keep = ~((np.abs(c[:, 0] - center[0]) < inner) & (np.abs(c[:, 1] - center[1]) < inner))
            ring = trimesh.Trimesh(vertices=far.vertices, faces=far.faces[keep], vertex_normals=far.vertex_normals,
                                   process=False, validate=False)
            ring.vertex_attributes["albedo"] = far.vertex_attributes["albedo"]
            far = ring
            meshes.append(far)
        vertices = np.concatenate([m.vertices for m in meshes], axis=0)
        self._serial += 1
        entry = (meshes, [self._primitive_mesh(m) for m in meshes],
                 _light_box(_sun_pose(terrain.sun_direction), vertices), self._serial)
        self._cache[key] = entry
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return entry

    # ---------------------------------------------------------------- rendering
    def render_one(self, altitude_m: float, site: int) -> np.ndarray:
        """One frame, (H, W) float32 numpy, linear irradiance (fraction of full sun x albedo)."""
        self._ensure_gl()
        pyrender = self._pyrender
        terrain = self.terrains[site]
        fx = self._fixed
        if fx is not None and fx[1] * (1 - 1e-9) <= altitude_m <= fx[0] * (1 + 1e-9):
            level = ("fixed", fx[0], fx[1])
        else:
            level = self.level_of(altitude_m)
        meshes, pmeshes, box, serial = self.level_meshes(site, level)
        key = (site, level, serial)
        if self._scene_key != key:
            for node in self._mesh_nodes:
                self._scene.remove_node(node)
            self._mesh_nodes = [self._scene.add(pm) for pm in pmeshes]
            self._scene_key = key
        self._scene.set_pose(self._light_node, _sun_pose(terrain.sun_direction))
        cam_z = self.camera_z_m(altitude_m, site)
        pose = np.eye(4)
        pose[2, 3] = cam_z
        self._scene.set_pose(self._cam_node, pose)
        # depth range: from just above the highest vertex to below the lowest one
        zmin = min(float(m.vertices[:, 2].min()) for m in meshes)
        zmax = max(float(m.vertices[:, 2].max()) for m in meshes)
        far_xy = max(float(np.abs(m.vertices[:, :2]).max()) for m in meshes)
        self._cam.znear = max(1e-3 * altitude_m, min(0.5 * altitude_m, cam_z - zmax - 1e-3 * altitude_m))
        self._cam.zfar = math.hypot(cam_z - zmin, far_xy) * 1.01 + 1.0
        r = self._osr._renderer
        r.light_box = box
        r.shadow_key = (id(self._scene), key, tuple(np.round(terrain.sun_direction, 12)))
        r.shading_uniforms = {"lunar_l": self.lunar_l[site], "ambient_frac": self.render_config.ambient,
                              "bias_slope": self.bias_slope, "bias_const": self.bias_const,
                              "nadir_view": 1.0 if self.view == "nadir" else 0.0}
        flags = pyrender.RenderFlags.SHADOWS_DIRECTIONAL if self.shadows else pyrender.RenderFlags.NONE
        img = self._osr.render(self._scene, flags=flags)
        ss = self.supersample
        H, W = self.camera.height_px, self.camera.width_px
        return img.reshape(H, ss, W, ss).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)

    def _render(self, altitude_m: torch.Tensor, site_idx: torch.Tensor) -> torch.Tensor:
        """Frames of a checked batch, one by one (a Python loop: this is the slow reference).

        Args:
            altitude_m: (B,) float32 altitudes above the landing point, m (checked by the base).
            site_idx: (B,) int64 site indices (checked by the base).

        Returns:
            (B, H, W) float32 on ``device``: linear irradiance, finite and > 0.
        """
        alts = altitude_m.detach().cpu().double().numpy()
        sites = site_idx.detach().cpu().numpy()
        if len(alts) == 0:
            return torch.empty(0, self.height_px, self.width_px, dtype=torch.float32, device=self.device)
        frames = np.stack([self.render_one(float(a), int(s)) for a, s in zip(alts, sites)], axis=0)
        return torch.from_numpy(frames).to(self.device)


def _lunar_l_of(terrain) -> float:
    """The lunar-Lambert L the fast renderer uses for a site: McEwen's L(phase), phase = 90 deg -
    sun elevation (a nadir camera), from :func:`dvsland.terrain.lunar_lambert_l`."""
    from dvsland.terrain.photometry import lunar_lambert_l

    el = math.degrees(math.asin(float(np.clip(np.asarray(terrain.sun_direction)[2], -1.0, 1.0))))
    return float(lunar_lambert_l(90.0 - el))
