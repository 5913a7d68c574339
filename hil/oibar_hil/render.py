"""Headless OpenGL renderer (moderngl on EGL: Mesa llvmpipe on CPU, the NVIDIA driver where a
GPU is present).

One pass draws the background (black space with an analytic Earth, or a Perlin backdrop),
one depth pass renders the Sun's shadow map (cached while the Sun direction is unchanged), and
one pass draws the meshes with Lambert + Blinn-Phong lighting from the Sun, an Earth-albedo fill
light and a small ambient term. The id pass writes each part's id into the red channel instead
of a colour, for label checks.

World coordinates are LVLH metres (the station flies LVLH-hold). The Earth is drawn by
ray-sphere intersection in the background shader rather than as a mesh: its 6371 km radius
would wreck the depth precision of a metre-scale scene, and the limb is exact this way.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from .camera import R_GL_CV, PinholeCamera
from .meshes import ID_ADAPTER, ID_MODULE, Part
from .textures import earth_texture, perlin_background

EARTH_RADIUS_KM = 6371.0

_MESH_VS = """
#version 330
uniform mat4 u_vp;
in vec3 in_pos; in vec3 in_nrm; in vec4 in_col; in float in_id;
out vec3 v_pos; out vec3 v_nrm; out vec4 v_col; out float v_id;
void main() {
    v_pos = in_pos; v_nrm = in_nrm; v_col = in_col; v_id = in_id;
    gl_Position = u_vp * vec4(in_pos, 1.0);
}
"""

_MESH_FS = """
#version 330
uniform int u_mode;              // 0 shaded, 1 part ids
uniform vec3 u_sun_dir;          // unit, towards the Sun
uniform vec3 u_earth_dir;        // unit, towards the Earth's centre
uniform vec3 u_cam_pos;
uniform float u_sun_intensity;
uniform float u_ambient;
uniform float u_albedo;
uniform float u_shadow_bias;
uniform mat4 u_light_vp_near;      // cascade 0: around the berthing fixture
uniform mat4 u_light_vp_far;       // cascade 1: the station around the port
uniform sampler2DShadow u_shadow_near;
uniform sampler2DShadow u_shadow_far;
in vec3 v_pos; in vec3 v_nrm; in vec4 v_col; in float v_id;
out vec4 f_color;
bool inside(vec3 s) { return s.x > 0.0 && s.x < 1.0 && s.y > 0.0 && s.y < 1.0 && s.z < 1.0; }
void main() {
    if (u_mode == 1) { f_color = vec4(v_id / 255.0, 0.0, 0.0, 1.0); return; }
    vec3 n = normalize(v_nrm);
    vec3 view = normalize(u_cam_pos - v_pos);
    if (dot(n, view) < 0.0) n = -n;   // thin panels are seen from both sides
    float ndl = max(dot(n, u_sun_dir), 0.0);
    float lit = 0.0;
    if (ndl > 0.0) {
        // Normal-offset lookup plus a constant bias against shadow acne.
        vec3 s0 = (u_light_vp_near * vec4(v_pos + n * 0.002, 1.0)).xyz * 0.5 + 0.5;
        lit = 1.0;
        if (inside(s0)) {
            lit = texture(u_shadow_near, vec3(s0.xy, s0.z - u_shadow_bias));
        } else {
            vec3 s1 = (u_light_vp_far * vec4(v_pos + n * 0.02, 1.0)).xyz * 0.5 + 0.5;
            if (inside(s1)) lit = texture(u_shadow_far, vec3(s1.xy, s1.z - u_shadow_bias));
        }
    }
    vec3 h = normalize(u_sun_dir + view);
    float spec = ndl > 0.0 ? pow(max(dot(n, h), 0.0), 48.0) * v_col.a : 0.0;
    vec3 c = v_col.rgb * (u_ambient + u_albedo * max(dot(n, u_earth_dir), 0.0) + u_sun_intensity * ndl * lit)
           + vec3(spec * lit * u_sun_intensity);
    f_color = vec4(pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}
"""

_DEPTH_VS = """
#version 330
uniform mat4 u_light_vp;
in vec3 in_pos;
void main() { gl_Position = u_light_vp * vec4(in_pos, 1.0); }
"""

_DEPTH_FS = """
#version 330
void main() { }
"""

_BG_VS = """
#version 330
in vec2 in_xy;
// Drawn after the meshes at the far plane with depth test LEQUAL, so only uncovered pixels
// pay for the background shader (early-z rejects the rest).
void main() { gl_Position = vec4(in_xy, 1.0, 1.0); }
"""

_BG_FS = """
#version 330
uniform int u_bg;                 // 0 space + Earth, 1 Perlin backdrop
uniform mat3 u_R_world_cam;       // OpenCV camera axes -> LVLH
uniform vec4 u_intr;              // fx, fy, cx, cy (pixel-corner convention)
uniform float u_height;
uniform vec3 u_sun_dir;
uniform vec3 u_earth_center_km;   // LVLH, from the station
uniform mat3 u_R_ecef_world;
uniform sampler2D u_tex;
out vec4 f_color;
const float PI = 3.14159265358979;
const float R_EARTH = 6371.0;
vec2 equirect(vec3 d) {
    return vec2(atan(d.y, d.x) / (2.0 * PI) + 0.5, 0.5 - asin(clamp(d.z, -1.0, 1.0)) / PI);
}
void main() {
    float u = gl_FragCoord.x;
    float v = u_height - gl_FragCoord.y;
    vec3 d_cam = vec3((u - u_intr.z) / u_intr.x, (v - u_intr.w) / u_intr.y, 1.0);
    vec3 d = normalize(u_R_world_cam * d_cam);
    if (u_bg == 1) {
        // The backdrop is fixed to the target frame so it moves like a distant scene.
        f_color = vec4(texture(u_tex, equirect(d)).rgb, 1.0);
        return;
    }
    vec3 c = u_earth_center_km;
    float b = dot(d, c);
    float disc = b * b - (dot(c, c) - R_EARTH * R_EARTH);
    vec3 col = vec3(0.0);
    if (disc > 0.0 && b > 0.0) {
        float t = b - sqrt(disc);
        vec3 n = normalize(t * d - c);
        vec4 g = texture(u_tex, equirect(u_R_ecef_world * n));
        vec3 surf = mix(g.rgb, vec3(0.95), g.a);
        float ndl = max(dot(n, u_sun_dir), 0.0);
        // Thin blue haze towards the limb, where the line of sight grazes the atmosphere.
        float graze = 1.0 - clamp(-dot(n, d), 0.0, 1.0);
        col = surf * (0.02 + 1.1 * ndl) + vec3(0.25, 0.45, 0.9) * pow(graze, 3.0) * (0.1 + ndl);
    } else {
        // Glow just above the limb.
        float ang = acos(clamp(b / length(c), -1.0, 1.0));
        float limb = asin(R_EARTH / length(c));
        float above = ang - limb;
        if (above > 0.0 && above < 0.03) {
            float sunlit = max(dot(d, u_sun_dir), 0.0);
            col = vec3(0.2, 0.4, 0.9) * (1.0 - above / 0.03) * (0.15 + 0.5 * sunlit);
        }
    }
    f_color = vec4(pow(clamp(col, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}
"""


@dataclass(frozen=True)
class RenderSettings:
    shadow_map_px: int = 2048
    shadow_near_half_extent_m: float = 0.6   # cascade around the fixture: ~0.6 mm texels
    shadow_far_half_extent_m: float = 20.0   # cascade around the port: ~2 cm texels
    shadow_depth_m: float = 120.0
    shadow_bias: float = 0.0005
    msaa_samples: int = 0                # off: ~2.5x faster on llvmpipe, labels unaffected
    sun_intensity: float = 1.0
    ambient: float = 0.03
    albedo_max: float = 0.30             # Earth-shine fill at full sunlit Earth below
    noise_sigma_dn: float = 0.0          # optional sensor noise (8-bit digital numbers)
    blur_sigma_px: float = 0.0           # optional optical blur (Gaussian)


def create_context():
    """A standalone headless GL 3.3+ context on EGL."""
    import moderngl

    try:
        return moderngl.create_standalone_context(require=330, backend="egl")
    except Exception as exc:  # noqa: BLE001 - turn driver noise into one actionable message
        raise RuntimeError(
            "could not create a headless OpenGL context on EGL; on Debian install "
            "`apt-get install --no-install-recommends libegl1 libgl1 libegl-mesa0 libgl1-mesa-dri` "
            f"(cause: {exc})"
        ) from exc


def _m4(M: np.ndarray) -> bytes:
    return np.asarray(M, dtype="f4").T.tobytes()  # GLSL wants column-major


def _m3(M: np.ndarray) -> bytes:
    return np.asarray(M, dtype="f4").T.tobytes()


def crease_normals(vertices: np.ndarray, faces: np.ndarray, crease_deg: float = 35.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-corner normals: area-weighted average of the faces around a vertex whose normals are
    within `crease_deg` of the corner's own face, so cylinders look round and box edges stay
    sharp. Returns unshared corner vertices (3F, 3) and normals (3F, 3)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])   # |cross| = 2 * area
    area2 = np.linalg.norm(cross, axis=1)
    n_face = cross / np.maximum(area2, 1e-30)[:, None]
    corner_vertex = f.reshape(-1)
    corner_face = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(corner_vertex, kind="stable")
    sorted_v = corner_vertex[order]
    start = np.searchsorted(sorted_v, np.arange(len(v)), side="left")
    deg = np.bincount(corner_vertex, minlength=len(v))
    rep = deg[corner_vertex]                                   # neighbours of each corner
    owner = np.repeat(np.arange(len(corner_vertex)), rep)
    offs = np.arange(rep.sum()) - np.repeat(np.cumsum(rep) - rep, rep)
    nb_face = corner_face[order[start[corner_vertex[owner]] + offs]]
    keep = np.einsum("ij,ij->i", n_face[corner_face[owner]], n_face[nb_face]) >= np.cos(np.radians(crease_deg))
    acc = np.zeros((len(corner_vertex), 3))
    np.add.at(acc, owner[keep], cross[nb_face[keep]])
    normals = acc / np.maximum(np.linalg.norm(acc, axis=1), 1e-30)[:, None]
    return v[corner_vertex], normals


def _vertex_data(parts: list[Part]) -> tuple[np.ndarray, np.ndarray]:
    """Interleaved float32 (pos3, nrm3, rgb+spec4, id1) and uint32 indices."""
    verts = []
    for p in parts:
        pos, nrm = crease_normals(p.mesh.vertices, p.mesh.faces)
        v = np.empty((len(pos), 11), dtype=np.float32)
        v[:, 0:3] = pos
        v[:, 3:6] = nrm
        v[:, 6:9] = p.rgb
        v[:, 9] = p.specular
        v[:, 10] = p.part_id
        verts.append(v)
    data = np.concatenate(verts)
    return data, np.arange(len(data), dtype=np.uint32)


def view_matrix(R_world_cam: np.ndarray, p_world_cam: np.ndarray) -> np.ndarray:
    """World -> GL eye coordinates for a camera with OpenCV axes R_world_cam at p_world_cam."""
    V = np.eye(4)
    V[:3, :3] = R_GL_CV @ R_world_cam.T
    V[:3, 3] = -V[:3, :3] @ p_world_cam
    return V


def light_matrix(sun_dir: np.ndarray, focus: np.ndarray, half_extent_m: float, depth_m: float) -> np.ndarray:
    """Orthographic view-projection of the Sun, centred on `focus`."""
    z = sun_dir / np.linalg.norm(sun_dir)             # eye looks along -z, i.e. away from the Sun
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    V = np.eye(4)
    V[:3, :3] = np.stack([x, y, z])
    V[:3, 3] = -V[:3, :3] @ focus
    s, d = half_extent_m, depth_m
    P = np.diag([1 / s, 1 / s, -1 / d, 1.0])          # z_eye in [-d, d] -> ndc [1, -1]
    return P @ V


class Renderer:
    def __init__(self, camera: PinholeCamera | None = None, settings: RenderSettings | None = None, ctx=None):
        import moderngl

        self.camera = camera or PinholeCamera()
        self.settings = settings or RenderSettings()
        self.ctx = ctx or create_context()
        c, s = self.ctx, self.settings
        W, H = self.camera.width_px, self.camera.height_px
        self.mesh_prog = c.program(vertex_shader=_MESH_VS, fragment_shader=_MESH_FS)
        self.depth_prog = c.program(vertex_shader=_DEPTH_VS, fragment_shader=_DEPTH_FS)
        self.bg_prog = c.program(vertex_shader=_BG_VS, fragment_shader=_BG_FS)
        tri = np.array([-1, -1, 3, -1, -1, 3], dtype="f4")
        self.bg_vao = c.vertex_array(self.bg_prog, [(c.buffer(tri.tobytes()), "2f", "in_xy")])

        samples = s.msaa_samples
        self.fbo = c.framebuffer(
            color_attachments=[c.renderbuffer((W, H), 4, samples=samples)],
            depth_attachment=c.depth_renderbuffer((W, H), samples=samples),
        )
        self.resolve_fbo = c.framebuffer(color_attachments=[c.renderbuffer((W, H), 4)]) if samples else self.fbo

        self.shadow_tex, self.shadow_fbo = [], []
        for _ in range(2):   # near and far cascades
            tex = c.depth_texture((s.shadow_map_px, s.shadow_map_px))
            tex.compare_func = "<="
            tex.filter = (moderngl.LINEAR, moderngl.LINEAR)   # 2x2 PCF in hardware
            self.shadow_tex.append(tex)
            self.shadow_fbo.append(c.framebuffer(depth_attachment=tex))
        self._shadow_key = None
        self._light_vp = [np.eye(4), np.eye(4)]

        self._earth_tex = None   # built on first use: ~1 s of noise, not needed for `perlin`
        self.bg_tex = None
        self.background = "iss"
        self.mesh_vao = self.depth_vao = None
        self.focus = np.zeros(3)
        self.gl_renderer = c.info.get("GL_RENDERER", "unknown")

    def _texture(self, img: np.ndarray):
        import moderngl

        h, w, comps = img.shape
        tex = self.ctx.texture((w, h), comps, np.ascontiguousarray(img).tobytes())
        tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        tex.repeat_x, tex.repeat_y = True, False
        return tex

    def load_scene(self, parts: list[Part], background: str, focus_lvlh: np.ndarray, perlin_seed: int | None = None):
        """Upload the meshes; `focus_lvlh` centres the shadow map (the target port)."""
        for vao in (self.mesh_vao, self.depth_vao):
            if vao is not None:
                vao.release()
        # Target fixture first, station last: front-to-back order lets early-z skip hidden work.
        parts = sorted(parts, key=lambda p: (p.part_id >= ID_ADAPTER, p.part_id >= ID_MODULE))
        data, idx = _vertex_data(parts)
        vbo = self.ctx.buffer(data.tobytes())
        ibo = self.ctx.buffer(idx.tobytes())
        self.mesh_vao = self.ctx.vertex_array(
            self.mesh_prog, [(vbo, "3f 3f 4f 1f", "in_pos", "in_nrm", "in_col", "in_id")], index_buffer=ibo, index_element_size=4)
        self.depth_vao = self.ctx.vertex_array(
            self.depth_prog, [(vbo, "3f 32x", "in_pos")], index_buffer=ibo, index_element_size=4)
        self.background = background
        self.focus = np.asarray(focus_lvlh, dtype=float)
        if background == "perlin":
            if perlin_seed is None:
                raise ValueError("the perlin background needs a seed")
            self.bg_tex = self._texture(perlin_background(perlin_seed))
        else:
            if self._earth_tex is None:
                self._earth_tex = self._texture(earth_texture(width=2048, height=1024))
            self.bg_tex = self._earth_tex
        self._shadow_key = None
        self.triangles = int(len(idx))

    def _update_shadow(self, sun_lvlh: np.ndarray) -> None:
        key = (tuple(np.round(sun_lvlh, 12)), tuple(self.focus))
        if key == self._shadow_key:
            return
        s = self.settings
        self.ctx.enable(self.ctx.DEPTH_TEST)
        self.ctx.polygon_offset = (1.5, 2.0)   # slope-scaled bias
        for i, half in enumerate((s.shadow_near_half_extent_m, s.shadow_far_half_extent_m)):
            self._light_vp[i] = light_matrix(sun_lvlh, self.focus, half, s.shadow_depth_m)
            self.shadow_fbo[i].use()
            self.shadow_fbo[i].clear(depth=1.0)
            self.depth_prog["u_light_vp"].write(_m4(self._light_vp[i]))
            self.depth_vao.render()
        self.ctx.polygon_offset = (0.0, 0.0)
        self._shadow_key = key

    def render(self, R_lvlh_cam: np.ndarray, p_lvlh_cam: np.ndarray, sun_lvlh: np.ndarray,
               R_ecef_lvlh: np.ndarray | None = None, earth_center_lvlh_km: np.ndarray | None = None,
               mode: str = "shaded", rng: np.random.Generator | None = None) -> np.ndarray:
        """One frame as (H, W, 3) uint8, row 0 at the top. mode 'id' returns part ids in
        channel 0 and no background, lighting, noise or blur."""
        if self.mesh_vao is None:
            raise RuntimeError("load_scene() first")
        cam, s, ctx = self.camera, self.settings, self.ctx
        sun = np.asarray(sun_lvlh, dtype=float)
        sun = sun / np.linalg.norm(sun)
        if mode == "shaded":
            self._update_shadow(sun)
        earth_c = np.array([0.0, 0.0, 6371.0 + 420.0]) if earth_center_lvlh_km is None else np.asarray(earth_center_lvlh_km, float)
        R_ecef = np.eye(3) if R_ecef_lvlh is None else R_ecef_lvlh

        self.fbo.use()
        self.fbo.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        # All meshes are closed with outward CCW faces: culling back faces halves the work.
        ctx.enable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.depth_func = "<="
        mp = self.mesh_prog
        V = view_matrix(np.asarray(R_lvlh_cam, float), np.asarray(p_lvlh_cam, float))
        mp["u_vp"].write(_m4(cam.gl_projection() @ V))
        mp["u_mode"].value = 1 if mode == "id" else 0
        if mode != "id":
            earth_dir = earth_c / np.linalg.norm(earth_c)
            mp["u_light_vp_near"].write(_m4(self._light_vp[0]))
            mp["u_light_vp_far"].write(_m4(self._light_vp[1]))
            mp["u_sun_dir"].value = tuple(sun)
            mp["u_earth_dir"].value = tuple(earth_dir)
            mp["u_cam_pos"].value = tuple(np.asarray(p_lvlh_cam, float))
            mp["u_sun_intensity"].value = s.sun_intensity
            mp["u_ambient"].value = s.ambient
            # Earth-shine scales with how much of the Earth below is sunlit.
            mp["u_albedo"].value = s.albedo_max * max(0.0, float(-sun @ earth_dir))
            mp["u_shadow_bias"].value = s.shadow_bias
            self.shadow_tex[0].use(location=2)
            self.shadow_tex[1].use(location=3)
            mp["u_shadow_near"].value = 2
            mp["u_shadow_far"].value = 3
        self.mesh_vao.render()

        if mode != "id":
            ctx.disable(ctx.CULL_FACE)
            bp = self.bg_prog
            bp["u_bg"].value = 1 if self.background == "perlin" else 0
            bp["u_R_world_cam"].write(_m3(R_lvlh_cam))
            bp["u_intr"].value = (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px)
            bp["u_height"].value = float(cam.height_px)
            bp["u_sun_dir"].value = tuple(sun)
            bp["u_earth_center_km"].value = tuple(earth_c)
            bp["u_R_ecef_world"].write(_m3(R_ecef))
            self.bg_tex.use(location=1)
            bp["u_tex"].value = 1
            self.bg_vao.render()

        if self.resolve_fbo is not self.fbo:
            ctx.copy_framebuffer(self.resolve_fbo, self.fbo)
        raw = self.resolve_fbo.read(components=3, alignment=1)
        img = np.frombuffer(raw, dtype=np.uint8).reshape(cam.height_px, cam.width_px, 3)[::-1]
        if mode == "id":
            return np.ascontiguousarray(img)
        return apply_sensor_effects(np.ascontiguousarray(img), s.noise_sigma_dn, s.blur_sigma_px, rng)

    def release(self) -> None:
        self.ctx.release()


def _gauss_kernel(sigma: float) -> np.ndarray:
    r = max(1, int(np.ceil(3 * sigma)))
    x = np.arange(-r, r + 1)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def apply_sensor_effects(img: np.ndarray, noise_sigma_dn: float, blur_sigma_px: float,
                         rng: np.random.Generator | None) -> np.ndarray:
    """Optional blur (separable Gaussian) then additive Gaussian read noise, both in 8-bit DN."""
    if blur_sigma_px <= 0 and noise_sigma_dn <= 0:
        return img
    out = img.astype(np.float32)
    if blur_sigma_px > 0:
        k = _gauss_kernel(blur_sigma_px)
        r = len(k) // 2
        pad = np.pad(out, ((r, r), (r, r), (0, 0)), mode="edge")
        tmp = sum(k[i] * pad[:, i:i + out.shape[1]] for i in range(len(k)))
        out = sum(k[i] * tmp[i:i + out.shape[0]] for i in range(len(k)))
    if noise_sigma_dn > 0:
        if rng is None:
            raise ValueError("sensor noise needs a seeded rng (determinism)")
        out = out + rng.normal(0.0, noise_sigma_dn, out.shape).astype(np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def set_llvmpipe_threads(n: int) -> None:
    """Mesa's CPU rasteriser reads LP_NUM_THREADS when the context is created."""
    os.environ.setdefault("LP_NUM_THREADS", str(n))
