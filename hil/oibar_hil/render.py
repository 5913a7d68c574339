"""Headless OpenGL renderer (moderngl on EGL: Mesa llvmpipe on CPU, the NVIDIA driver where a
GPU is present).

A depth pass renders the Sun's two shadow-map cascades into one atlas (cached while the Sun
direction is unchanged) and the Earth's shadow maps into another (one per sample direction over
its disc, cached while the Earth stays put in LVLH); one pass draws the meshes with Lambert +
Blinn-Phong lighting from the Sun, Earth-shine from the whole sunlit part of the disc (occluded
like the Sun, in the colour of the ground and clouds under it) and a small ambient term, and one
pass draws the background on the pixels left uncovered (black space with an analytic Earth, or a
Perlin backdrop). The id pass (its own flat shader) writes each part's id into the red channel
instead of a colour, for label checks. Performance notes for llvmpipe are in docs/synthetic.md.

A scene may carry a randomised look (oibar_hil.randomize, issue 58 part 3): the same passes with
the mesh shader compiled with LOOK defined (per-part materials with a procedural texture, spot
lamps each with a perspective shadow map, drawn ambient, Sun and Earth-shine scales), one of
several backdrops, and an optics pass after them (vignetting, a residual lens distortion).
Without one, every pass is what it was, pixel for pixel.

World coordinates are LVLH metres (the station flies LVLH-hold). The Earth is drawn by
ray-sphere intersection in the background shader rather than as a mesh: its 6371 km radius
would wreck the depth precision of a metre-scale scene, and the limb is exact this way.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from oibar.geometry.camera import PinholeCamera

from .camera import R_GL_CV, gl_projection
from .meshes import ID_ADAPTER, ID_MODULE, ID_OTHER_FIXTURE, Part
from .randomize import MAX_LAMPS, LookParams
from .textures import (
    box_downsample,
    earth_ground,
    earth_texture,
    lab_clutter_background,
    periodic_noise3d,
    perlin_background,
    sample_equirect,
    star_background,
)

EARTH_RADIUS_KM = 6371.0
# Where the Earth's centre is when a caller gives none: straight below (LVLH +Z), 420 km down.
DEFAULT_EARTH_CENTER_LVLH_KM = (0.0, 0.0, EARTH_RADIUS_KM + 420.0)

_MESH_VS = """
#version 330
uniform mat4 u_vp;
uniform mat4 u_light_vp_near;      // cascade 0 (around the berthing fixture)
in vec3 in_pos; in vec3 in_nrm; in vec4 in_col;
out vec3 v_pos; out vec3 v_nrm; out vec4 v_col;
// Near-cascade shadow-map coordinates of the vertex ([0, 1]^3) and the image of its normal: both
// are affine in the world position/normal, so interpolating them is exact and the fragment shader
// only adds the normal offset instead of doing 4x4 transforms per pixel. The far cascade is the
// same light view scaled about the focus (same depth range), so it follows from these.
out vec3 v_s0; out vec3 v_ds0;
// The Earth's shadow-map coordinates of the vertex, offset 1 cm along its normal: affine too.
uniform mat4 u_earth_vp[EARTH_SAMPLES];
out vec3 v_e[EARTH_SAMPLES];
#ifdef LOOK
// A randomised look (oibar_hil.randomize): each vertex names its material slot, and each spot
// lamp's shadow-map coordinates are interpolated as homogeneous clip coordinates (affine in
// position; the fragment divides), offset ~1.5 shadow texels along the normal at the vertex's
// distance from the lamp.
in float in_slot;
flat out int v_slot;
#if N_LAMPS > 0
uniform mat4 u_lamp_vp[N_LAMPS];
uniform vec3 u_lamp_pos[N_LAMPS];
uniform float u_lamp_texel[N_LAMPS];   // one shadow texel per metre from the lamp
out vec4 v_l[N_LAMPS];
#endif
#endif
void main() {
    v_pos = in_pos; v_nrm = in_nrm; v_col = in_col;
#ifdef LOOK
    v_slot = int(in_slot + 0.5);
#if N_LAMPS > 0
    vec3 nn = normalize(in_nrm);
    for (int k = 0; k < N_LAMPS; ++k) {
        float off = 1.5 * u_lamp_texel[k] * length(u_lamp_pos[k] - in_pos);
        v_l[k] = u_lamp_vp[k] * vec4(in_pos + off * nn, 1.0);
    }
#endif
#endif
    v_s0 = (u_light_vp_near * vec4(in_pos, 1.0)).xyz * 0.5 + 0.5;
    v_ds0 = mat3(u_light_vp_near) * in_nrm * 0.5;
    vec3 p_off = in_pos + 0.01 * normalize(in_nrm);
    for (int k = 0; k < EARTH_SAMPLES; ++k) v_e[k] = (u_earth_vp[k] * vec4(p_off, 1.0)).xyz * 0.5 + 0.5;
    gl_Position = u_vp * vec4(in_pos, 1.0);
}
"""

_MESH_FS = """
#version 330
uniform vec3 u_sun_dir;          // unit, towards the Sun
// The Earth as an extended light: EARTH_SAMPLES directions over its disc (139 deg across from
// LEO), each with its own shadow map and a weight (the radiance of the Earth seen there, sunlit
// or not, times its share of the disc's solid angle).
uniform vec3 u_earth_l[EARTH_SAMPLES];      // unit, towards that patch of the Earth
uniform vec3 u_earth_w[EARTH_SAMPLES];      // RGB irradiance weight (Sun = 1)
uniform vec3 u_focus;                       // the centre of those maps
uniform float u_earth_reach2;               // squared distance from it beyond which no map holds a point
in vec3 v_e[EARTH_SAMPLES];                 // the point in each map ([0, 1]^3)
uniform float u_earth_texel_depth;          // one texel of those maps in their depth units
uniform sampler2DShadow u_earth_shadow;     // atlas: EARTH_TILES x EARTH_TILES maps
uniform vec3 u_cam_pos;
uniform float u_sun_intensity;
uniform float u_ambient;
uniform float u_exposure;        // the sensor: scene radiance x exposure, clipped, then 1 / gamma
uniform float u_gamma;
uniform vec2 u_texel_depth;      // one shadow texel in shadow-depth units: near, far cascade
uniform float u_bias_texels;     // depth bias in texels at normal incidence
uniform float u_max_slope;       // the bias grows with tan(incidence) up to this
uniform float u_atlas_margin;    // half a texel of one cascade: keeps the 2x2 PCF inside it
uniform float u_far_scale;       // near / far cascade half-extent
uniform sampler2DShadow u_shadow; // atlas: cascade 0 in the left half, cascade 1 in the right
in vec3 v_pos; in vec3 v_nrm; in vec4 v_col;
in vec3 v_s0; in vec3 v_ds0;
#ifdef LOOK
flat in int v_slot;
uniform vec4 u_surf[LOOK_SLOTS];     // per material slot: shininess, grain, bump, banding
uniform vec4 u_texp[LOOK_SLOTS];     // fBm cycles per metre, stretch along X_t, band period (m), -
uniform mat3 u_R_t_world;            // LVLH -> the fixture's frame F_t (textures stick to it)
uniform sampler3D u_noise;           // periodic fBm: R grain, GBA bump vector
// N_LAMPS spot lamps (a program per count: a look without lamps pays nothing for them)
#if N_LAMPS > 0
in vec4 v_l[N_LAMPS];
uniform vec3 u_lamp_pos[N_LAMPS];
uniform vec3 u_lamp_dir[N_LAMPS];    // unit, along the beam
uniform vec3 u_lamp_i[N_LAMPS];      // intensity x tint: irradiance = u_lamp_i / distance^2
uniform vec2 u_lamp_cos[N_LAMPS];    // cos(cut-off), cos(cut-off - soft edge)
uniform sampler2DShadow u_lamp_shadow;   // MAX_LAMPS perspective maps side by side
uniform float u_lamp_margin;         // half a texel of one map
#endif
#endif
out vec4 f_color;
bool inside(vec3 s) {
    return s.x > u_atlas_margin && s.x < 1.0 - u_atlas_margin && s.y > u_atlas_margin && s.y < 1.0 - u_atlas_margin
        && s.z < 1.0;
}
void main() {
    float inv_len = inversesqrt(dot(v_nrm, v_nrm));
    vec3 n = v_nrm * inv_len;
    vec3 view = normalize(u_cam_pos - v_pos);
    if (dot(n, view) < 0.0) { n = -n; inv_len = -inv_len; }   // thin panels are seen from both sides
#ifdef LOOK
    // the material's procedural texture, fixed to the fixture: fBm grain on the albedo (stretched
    // along X_t for brushed metal), banding along Y_t faded out where finer than a pixel (no
    // moire), a bumped normal (crinkled foil)
    vec4 surf = u_surf[v_slot];
    vec4 tp = u_texp[v_slot];
    vec3 pt = u_R_t_world * (v_pos - u_focus);
    vec4 nz = texture(u_noise, pt * tp.x * vec3(1.0 / tp.y, 1.0, 1.0)) * 2.0 - 1.0;
    float band = pt.y / tp.z;
    float band_w = surf.w * clamp(1.0 - 2.0 * fwidth(band), 0.0, 1.0);
    vec3 albedo = v_col.rgb * max(1.0 + surf.y * nz.r + band_w * sin(6.2831853 * band), 0.0);
    n = normalize(n + surf.z * nz.gba);
    float shin = surf.x;
#endif
    float ndl = max(dot(n, u_sun_dir), 0.0);
    // Normal-offset lookup (2 mm near, 2 cm far: a few texels of each cascade) plus a depth bias
    // of about a texel, scaled with the slope of the surface to the light: enough against shadow
    // acne, and small enough that an occluder of 1 cm still shades (a constant bias in depth
    // units hid every occluder closer than ~12 cm along the light: rim, bosses, connector);
    // one hardware-filtered (2x2 PCF) tap in whichever cascade holds the point.
    vec3 s0 = v_s0 + (0.002 * inv_len) * v_ds0;
    vec3 s1 = v_s0 + (0.02 * inv_len) * v_ds0;
    s1.xy = (s1.xy - 0.5) * u_far_scale + 0.5;
    bool near = inside(s0);
    vec3 s = near ? vec3(s0.xy * vec2(0.5, 1.0), s0.z) : vec3(s1.xy * vec2(0.5, 1.0) + vec2(0.5, 0.0), s1.z);
    float slope = min(sqrt(max(1.0 - ndl * ndl, 0.0)) / max(ndl, 1e-3), u_max_slope);
    float bias = u_bias_texels * (1.0 + slope) * (near ? u_texel_depth.x : u_texel_depth.y);
    float lit = texture(u_shadow, vec3(s.xy, s.z - bias));
    lit = (near || inside(s1)) ? lit : 1.0;    // (irrelevant where ndl == 0)
    vec3 h = normalize(u_sun_dir + view);
#ifdef LOOK
    float spec = ndl > 0.0 ? pow(max(dot(n, h), 0.0), shin) * v_col.a : 0.0;
#else
    float spec = ndl > 0.0 ? pow(max(dot(n, h), 0.0), 48.0) * v_col.a : 0.0;
#endif
    // Earth-shine: each sample's cosine, occluded through its own shadow map (1 cm normal offset,
    // about a texel, and a slope-scaled depth bias, as for the Sun) near the fixture; unoccluded
    // beyond the maps' reach.
    vec3 earth = vec3(0.0);
    vec3 dp = v_pos - u_focus;
    float r2 = dot(dp, dp) / u_earth_reach2;
    bool mapped = r2 < 1.0;
    // towards the maps' edge the occlusion fades out, so their reach draws no line
    float fade = smoothstep(0.5, 1.0, r2);
    for (int k = 0; k < EARTH_SAMPLES; ++k) {
        float ndk = max(dot(n, u_earth_l[k]), 0.0);
        float vis = 1.0;
        if (mapped && ndk > 0.0) {
            vec3 e = v_e[k];
            float slope = min(sqrt(max(1.0 - ndk * ndk, 0.0)) / max(ndk, 1e-3), u_max_slope);
            vec2 tile = vec2(float(k % EARTH_TILES), float(k / EARTH_TILES));
            vec2 uv = (tile + clamp(e.xy, 0.5 / EARTH_TILE_PX, 1.0 - 0.5 / EARTH_TILE_PX)) / float(EARTH_TILES);
            float z = e.z - (1.0 + slope) * u_earth_texel_depth;
            // four filtered taps 1.5 texels apart: the penumbra of a light 139 deg wide, roughly
            vec2 o = 1.5 / (EARTH_TILE_PX * float(EARTH_TILES)) * vec2(1.0, -1.0);
#if EARTH_TAPS == 4
            vis = e.z < 1.0 ? 0.25 * (texture(u_earth_shadow, vec3(uv + o.xx, z))
                                    + texture(u_earth_shadow, vec3(uv + o.yy, z))
                                    + texture(u_earth_shadow, vec3(uv + o.xy, z))
                                    + texture(u_earth_shadow, vec3(uv + o.yx, z)))
                            : 1.0;
#else
            vis = e.z < 1.0 ? texture(u_earth_shadow, vec3(uv, z)) : 1.0;
#endif
            vis = mix(vis, 1.0, fade);
        }
        earth += u_earth_w[k] * ndk * vis;
    }
#ifdef LOOK
    // spot lamps: inverse square, a soft-edged cone, each its own shadow map (one filtered tap)
    vec3 lamp_d = vec3(0.0), lamp_s = vec3(0.0);
#if N_LAMPS > 0
    for (int k = 0; k < N_LAMPS; ++k) {
        vec3 L = u_lamp_pos[k] - v_pos;
        float d2 = dot(L, L);
        vec3 l = L * inversesqrt(d2);
        float ndk = max(dot(n, l), 0.0);
        float cone = smoothstep(u_lamp_cos[k].x, u_lamp_cos[k].y, dot(-l, u_lamp_dir[k]));
        vec3 sl = v_l[k].xyz / v_l[k].w * 0.5 + 0.5;
        bool in_map = v_l[k].w > 0.0 && sl.x > u_lamp_margin && sl.x < 1.0 - u_lamp_margin
            && sl.y > u_lamp_margin && sl.y < 1.0 - u_lamp_margin && sl.z < 1.0;
        float vis = in_map ? texture(u_lamp_shadow, vec3((sl.x + float(k)) / float(MAX_LAMPS), sl.y, sl.z)) : 1.0;
        vec3 e = u_lamp_i[k] * (cone * vis / d2);
        lamp_d += e * ndk;
        vec3 hk = normalize(l + view);
        lamp_s += e * (ndk > 0.0 ? pow(max(dot(n, hk), 0.0), shin) * v_col.a : 0.0);
    }
#endif
    vec3 c = albedo * (u_ambient + earth + u_sun_intensity * ndl * lit + lamp_d)
           + vec3(spec * lit * u_sun_intensity) + lamp_s;
#else
    vec3 c = v_col.rgb * (u_ambient + earth + u_sun_intensity * ndl * lit)
           + vec3(spec * lit * u_sun_intensity);
#endif
    f_color = vec4(pow(clamp(u_exposure * c, 0.0, 1.0), vec3(1.0 / u_gamma)), 1.0);
}
"""

# Label pass: part ids in the red channel, nothing else computed.
_ID_VS = """
#version 330
uniform mat4 u_vp;
in vec3 in_pos; in float in_id;
flat out float v_id;
void main() { v_id = in_id; gl_Position = u_vp * vec4(in_pos, 1.0); }
"""

_ID_FS = """
#version 330
flat in float v_id;
out vec4 f_color;
void main() { f_color = vec4(v_id / 255.0, 0.0, 0.0, 1.0); }
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
uniform mat3 u_R_world_cam;       // OpenCV camera axes -> LVLH
uniform vec4 u_intr;              // fx, fy, cx, cy (pixel-corner convention)
uniform vec2 u_size;              // width, height in pixels
in vec2 in_xy;
out vec3 v_dir;                   // viewing ray in LVLH (not normalised: linear across the screen)
// Drawn after the meshes at the far plane with depth test LEQUAL, so only uncovered pixels
// pay for the background shader (early-z rejects the rest).
void main() {
    vec2 px = vec2((in_xy.x + 1.0) * 0.5 * u_size.x, (1.0 - in_xy.y) * 0.5 * u_size.y);
    v_dir = u_R_world_cam * vec3((px.x - u_intr.z) / u_intr.x, (px.y - u_intr.w) / u_intr.y, 1.0);
    gl_Position = vec4(in_xy, 1.0, 1.0);
}
"""

_EQUIRECT = """
const float PI = 3.14159265358979;
vec2 equirect(vec3 d) {
    return vec2(atan(d.y, d.x) / (2.0 * PI) + 0.5, 0.5 - asin(clamp(d.z, -1.0, 1.0)) / PI);
}
"""

# The Perlin backdrop is fixed to the LVLH frame so it moves like a distant scene.
_PERLIN_FS = (
    """
#version 330
uniform sampler2D u_tex;
uniform float u_exposure;
uniform float u_gamma;
in vec3 v_dir;
out vec4 f_color;
"""
    + _EQUIRECT
    + """
// a display-referred backdrop: exposure scales it as the sensor would its radiance
void main() {
    vec3 t = texture(u_tex, equirect(normalize(v_dir))).rgb;
    f_color = vec4(clamp(t * pow(u_exposure, 1.0 / u_gamma), 0.0, 1.0), 1.0);
}
"""
)

# Space and the Earth: exact ray-sphere intersection per pixel. The per-frame constants
# (|c|^2 - R^2, 1/|c|, the limb angle) come in as uniforms.
_EARTH_FS = (
    """
#version 330
uniform vec3 u_sun_dir;
uniform vec3 u_earth_center_km;   // LVLH, from the station
uniform float u_c2_minus_r2;      // |c|^2 - R_earth^2
uniform float u_inv_clen;         // 1 / |c|
uniform float u_limb;             // angular radius of the Earth seen from the station
uniform mat3 u_R_ecef_world;
uniform sampler2D u_tex;
uniform float u_exposure;
uniform float u_gamma;
in vec3 v_dir;
out vec4 f_color;
"""
    + _EQUIRECT
    + """
void main() {
    vec3 d = normalize(v_dir);
    vec3 c = u_earth_center_km;
    float b = dot(d, c);
    float disc = b * b - u_c2_minus_r2;
    vec3 col = vec3(0.0);
    if (disc > 0.0 && b > 0.0) {
        float t = b - sqrt(disc);
        vec3 n = normalize(t * d - c);
        vec4 g = texture(u_tex, equirect(u_R_ecef_world * n));
        vec3 surf = mix(g.rgb, vec3(0.95), g.a);
        float ndl = max(dot(n, u_sun_dir), 0.0);
        // Thin blue haze towards the limb, where the line of sight grazes the atmosphere.
        float graze = 1.0 - clamp(-dot(n, d), 0.0, 1.0);
        col = surf * (0.02 + 1.1 * ndl) + vec3(0.25, 0.45, 0.9) * (graze * graze * graze) * (0.1 + ndl);
    } else {
        // Glow just above the limb.
        float above = acos(clamp(b * u_inv_clen, -1.0, 1.0)) - u_limb;
        if (above > 0.0 && above < 0.03) {
            float sunlit = max(dot(d, u_sun_dir), 0.0);
            col = vec3(0.2, 0.4, 0.9) * (1.0 - above / 0.03) * (0.15 + 0.5 * sunlit);
        }
    }
    f_color = vec4(pow(clamp(u_exposure * col, 0.0, 1.0), vec3(1.0 / u_gamma)), 1.0);
}
"""
)


# A randomised look's optics, after the scene: radial lens distortion (the canonical camera's
# k1, OpenCV's model: x_d = x_u (1 + k1 |x_u|^2)) by resampling the pinhole image, and
# vignetting as a gain on the sensor's linear signal, 1 - v (r / r_corner)^2.
_POST_VS = """
#version 330
in vec2 in_xy;
void main() { gl_Position = vec4(in_xy, 0.0, 1.0); }
"""

_POST_FS = """
#version 330
uniform sampler2D u_img;
uniform vec4 u_intr;              // fx, fy, cx, cy (pixel-corner convention, rows from the top)
uniform vec2 u_size;
uniform float u_k1;
uniform float u_vignetting;
uniform float u_r_corner2;        // the corner's squared normalised radius
uniform float u_gamma;
out vec4 f_color;
void main() {
    vec2 px = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
    vec2 xd = (px - u_intr.zw) / u_intr.xy;
    // the pinhole point the lens brings here (fixed-point inverse of the radial model)
    vec2 xu = xd;
    for (int i = 0; i < 4; ++i) xu = xd / (1.0 + u_k1 * dot(xu, xu));
    vec2 src = xu * u_intr.xy + u_intr.zw;
    vec3 c = texture(u_img, vec2(src.x / u_size.x, 1.0 - src.y / u_size.y)).rgb;
    // a gain g on the linear signal is g^(1 / gamma) on the encoded one
    float g = 1.0 - u_vignetting * dot(xd, xd) / u_r_corner2;
    f_color = vec4(c * pow(g, 1.0 / u_gamma), 1.0);
}
"""

LOOK_SLOTS = 8  # material slots of a randomised look: 0 as built, then the fixture's parts
LAMP_SHADOW_PX = 1024  # side of each spot lamp's shadow map


@dataclass(frozen=True)
class RenderSettings:
    shadow_map_px: int = 2048
    shadow_near_half_extent_m: float = 0.6  # cascade around the fixture: ~0.6 mm texels
    shadow_far_half_extent_m: float = 20.0  # cascade around the port: ~2 cm texels
    shadow_depth_m: float = 120.0
    shadow_bias_texels: float = 1.0  # depth bias at normal incidence, in texels of each cascade
    shadow_max_slope: float = 5.0  # the bias grows with tan(incidence) up to this factor (+1)
    msaa_samples: int = 0  # off: ~2.5x faster on llvmpipe, labels unaffected
    sun_intensity: float = 1.0
    ambient: float = 0.03
    earth_samples: int = 6  # patches of the Earth's disc, each a shadow-mapped direction
    earth_shadow_px: int = 512  # side of each of those maps
    earth_shadow_taps: int = 4  # filtered taps per sample (1 or 4): 4 soften its penumbra
    earth_shadow_half_extent_m: float = 3.0  # around the fixture: 12 mm texels (Earth-shine is soft)
    exposure: float = 1.0  # scene radiance (Sun-lit white = 1) to the sensor's full scale, linear
    gamma: float = 2.2  # the sensor's output encoding
    noise_sigma_dn: float = 0.0  # optional sensor noise (8-bit digital numbers)
    blur_sigma_px: float = 0.0  # optional optical blur (Gaussian)


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


def crease_normals(
    vertices: np.ndarray, faces: np.ndarray, crease_deg: float = 35.0
) -> tuple[np.ndarray, np.ndarray]:
    """Per-corner normals: area-weighted average of the faces around a vertex whose normals are
    within `crease_deg` of the corner's own face, so cylinders look round and box edges stay
    sharp. Returns unshared corner vertices (3F, 3) and normals (3F, 3)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # |cross| = 2 * area
    area2 = np.linalg.norm(cross, axis=1)
    n_face = cross / np.maximum(area2, 1e-30)[:, None]
    corner_vertex = f.reshape(-1)
    corner_face = np.repeat(np.arange(len(f)), 3)
    order = np.argsort(corner_vertex, kind="stable")
    sorted_v = corner_vertex[order]
    start = np.searchsorted(sorted_v, np.arange(len(v)), side="left")
    deg = np.bincount(corner_vertex, minlength=len(v))
    rep = deg[corner_vertex]  # neighbours of each corner
    owner = np.repeat(np.arange(len(corner_vertex)), rep)
    offs = np.arange(rep.sum()) - np.repeat(np.cumsum(rep) - rep, rep)
    nb_face = corner_face[order[start[corner_vertex[owner]] + offs]]
    keep = np.einsum("ij,ij->i", n_face[corner_face[owner]], n_face[nb_face]) >= np.cos(
        np.radians(crease_deg)
    )
    acc = np.zeros((len(corner_vertex), 3))
    np.add.at(acc, owner[keep], cross[nb_face[keep]])
    normals = acc / np.maximum(np.linalg.norm(acc, axis=1), 1e-30)[:, None]
    return v[corner_vertex], normals


def _vertex_data(parts: list[Part], slots: list[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Interleaved float32 (pos3, nrm3, rgb+spec4, id1[, slot1]) and uint32 indices; `slots`, a
    material slot per part, adds the last column (a randomised look)."""
    cols = 11 if slots is None else 12
    verts = []
    for i, p in enumerate(parts):
        pos, nrm = crease_normals(p.mesh.vertices, p.mesh.faces)
        v = np.empty((len(pos), cols), dtype=np.float32)
        v[:, 0:3] = pos
        v[:, 3:6] = nrm
        v[:, 6:9] = p.rgb
        v[:, 9] = p.specular
        v[:, 10] = p.part_id
        if slots is not None:
            v[:, 11] = slots[i]
        verts.append(v)
    data = np.concatenate(verts)
    # Share identical corners (same position, normal, colour, id): ~4x fewer vertices to shade,
    # while the triangle order, and so the rasterised result, stays the same.
    uniq, first, inverse = np.unique(
        data.view(np.dtype((np.void, data.dtype.itemsize * cols))).ravel(),
        return_index=True,
        return_inverse=True,
    )
    return data[first], inverse.astype(np.uint32).ravel()


def view_matrix(R_world_cam: np.ndarray, p_world_cam: np.ndarray) -> np.ndarray:
    """World -> GL eye coordinates for a camera with OpenCV axes R_world_cam at p_world_cam."""
    V = np.eye(4)
    V[:3, :3] = R_GL_CV @ R_world_cam.T
    V[:3, 3] = -V[:3, :3] @ p_world_cam
    return V


def light_matrix(sun_dir: np.ndarray, focus: np.ndarray, half_extent_m: float, depth_m: float) -> np.ndarray:
    """Orthographic view-projection of the Sun, centred on `focus`."""
    z = sun_dir / np.linalg.norm(sun_dir)  # eye looks along -z, i.e. away from the Sun
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    V = np.eye(4)
    V[:3, :3] = np.stack([x, y, z])
    V[:3, 3] = -V[:3, :3] @ focus
    s, d = half_extent_m, depth_m
    P = np.diag([1 / s, 1 / s, -1 / d, 1.0])  # z_eye in [-d, d] -> ndc [1, -1]
    return P @ V


def spot_matrix(
    pos: np.ndarray, direction: np.ndarray, fov_deg: float, near_m: float, far_m: float
) -> np.ndarray:
    """Perspective view-projection of a spot lamp at `pos` looking along `direction`."""
    z = -np.asarray(direction, float) / np.linalg.norm(direction)  # eye looks along -z
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    V = np.eye(4)
    V[:3, :3] = np.stack([x, y, z])
    V[:3, 3] = -V[:3, :3] @ np.asarray(pos, float)
    f = 1.0 / np.tan(np.radians(fov_deg) / 2)
    n, fa = near_m, far_m
    P = np.array(
        [[f, 0, 0, 0], [0, f, 0, 0], [0, 0, (fa + n) / (n - fa), 2 * fa * n / (n - fa)], [0, 0, -1, 0]]
    )
    return P @ V


def fibonacci_disc(earth_c_km: np.ndarray, n: int) -> np.ndarray:
    """`n` unit directions (LVLH) spread evenly in solid angle over the Earth's disc seen from
    the station (a Fibonacci spiral on the cap of half-angle asin(R / |c|))."""
    c = np.asarray(earth_c_km, float)
    e = c / np.linalg.norm(c)
    cos_a = np.sqrt(max(0.0, 1.0 - float(EARTH_RADIUS_KM / np.linalg.norm(c)) ** 2))
    i = np.arange(n) + 0.5
    cos_t = 1.0 - i / n * (1.0 - cos_a)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t**2))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    up = np.array([1.0, 0.0, 0.0]) if abs(e[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, e)
    x /= np.linalg.norm(x)
    y = np.cross(e, x)
    d = cos_t[:, None] * e + (sin_t * np.cos(phi))[:, None] * x + (sin_t * np.sin(phi))[:, None] * y
    out: np.ndarray = d / np.linalg.norm(d, axis=1, keepdims=True)
    return out


# The disc's radiance is integrated over this many directions (about 2 deg apart from LEO): the
# ground's colour changes on that scale, so fewer (512) left a patch's colour to a few texels.
EARTH_FINE_SAMPLES = 4096
# Earth-shine reads the Earth's texture averaged over blocks of this many texels a side (0.7 deg
# at 2048 x 1024): each direction then stands for its neighbourhood, not one texel of cloud or sea.
EARTH_SHINE_TEXEL_BLOCK = 4


@lru_cache(maxsize=1)
def earth_rgba() -> np.ndarray:
    """The Earth's texture as both renderers draw it (2048 x 1024 RGBA; built once a process,
    ~2 s, read-only)."""
    tex = earth_texture(width=2048, height=1024)
    tex.flags.writeable = False
    return tex


@lru_cache(maxsize=1)
def earth_shine_ground() -> np.ndarray:
    """The Earth's albedo (ground and clouds, RGB) that Earth-shine reads: `earth_rgba`'s,
    averaged over EARTH_SHINE_TEXEL_BLOCK texels a side."""
    out = box_downsample(earth_ground(earth_rgba()), EARTH_SHINE_TEXEL_BLOCK)
    out.flags.writeable = False
    return out


class EarthLight:
    """The Earth as an extended light seen from the station: its disc cut into `n` patches of
    equal solid angle (each a shadow-mapped direction, the mean of its part of a fine spiral),
    and each patch's RGB irradiance weight for a Sun direction (Sun = 1): the integral over the
    patch of a Lambertian Earth's radiance, albedo / pi * max(n_earth . sun, 0), with the albedo
    of the ground (and clouds) each fine direction meets, read from `ground` (an equirectangular
    RGB map in ECEF, `earth_shine_ground` unless told): the colour Mitsuba's environment map
    gives the path tracer. A surface facing a fully sunlit Earth of albedo 0.3 below gets about
    0.3 x sin^2(disc half-angle), 0.26 at 420 km."""

    def __init__(self, earth_c_km: np.ndarray, n: int, ground: np.ndarray | None = None):
        c = np.asarray(earth_c_km, float)
        self.ground = earth_shine_ground() if ground is None else np.asarray(ground, float)
        fine = fibonacci_disc(c, EARTH_FINE_SAMPLES)
        coarse = fibonacci_disc(c, n)
        self.patch = np.argmax(fine @ coarse.T, axis=1)
        dirs = np.stack([fine[self.patch == k].sum(0) for k in range(n)])
        self.dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        clen = float(np.linalg.norm(c))
        b = fine @ c
        t = b - np.sqrt(np.maximum(b * b - (clen * clen - EARTH_RADIUS_KM**2), 0.0))
        self.n_earth = (
            t[:, None] * fine - c
        ) / EARTH_RADIUS_KM  # the Earth's normal where each fine ray meets it
        cos_a = np.sqrt(max(0.0, 1.0 - (EARTH_RADIUS_KM / clen) ** 2))
        self.d_omega = 2.0 * np.pi * (1.0 - cos_a) / EARTH_FINE_SAMPLES

    def radiance(self, sun: np.ndarray, R_ecef_lvlh: np.ndarray | None = None) -> np.ndarray:
        """(EARTH_FINE_SAMPLES, 3): the Earth's RGB radiance (Sun = 1) along each fine direction
        for the Sun direction `sun` (LVLH), the ground under the disc placed by `R_ecef_lvlh`
        (identity: ECEF axes along LVLH's)."""
        n_ecef = self.n_earth if R_ecef_lvlh is None else self.n_earth @ np.asarray(R_ecef_lvlh, float).T
        albedo = sample_equirect(self.ground, n_ecef)
        out: np.ndarray = albedo / np.pi * np.maximum(self.n_earth @ np.asarray(sun, float), 0.0)[:, None]
        return out

    def weights(self, sun: np.ndarray, R_ecef_lvlh: np.ndarray | None = None) -> np.ndarray:
        """(n, 3): each patch's RGB irradiance weight (`radiance` summed over the patch)."""
        radiance = self.radiance(sun, R_ecef_lvlh)
        w: np.ndarray = np.stack(
            [
                np.bincount(self.patch, radiance[:, ch] * self.d_omega, minlength=len(self.dirs))
                for ch in range(3)
            ],
            axis=1,
        )
        return w


class Renderer:
    def __init__(self, camera: PinholeCamera | None = None, settings: RenderSettings | None = None, ctx=None):
        import moderngl

        self.camera = camera or PinholeCamera()
        self.settings = settings or RenderSettings()
        self.ctx = ctx or create_context()
        c, s = self.ctx, self.settings
        W, H = self.camera.width_px, self.camera.height_px
        self.earth_tiles = int(np.ceil(np.sqrt(s.earth_samples)))
        defines = (
            f"#define EARTH_SAMPLES {s.earth_samples}\n#define EARTH_TILES {self.earth_tiles}\n"
            f"#define EARTH_TILE_PX {float(s.earth_shadow_px)}\n#define EARTH_TAPS {s.earth_shadow_taps}\n"
        )
        self._defines = defines
        self.mesh_prog = self.default_mesh_prog = c.program(
            vertex_shader=_MESH_VS.replace("#version 330\n", "#version 330\n" + defines, 1),
            fragment_shader=_MESH_FS.replace("#version 330\n", "#version 330\n" + defines, 1),
        )
        self.id_prog = c.program(vertex_shader=_ID_VS, fragment_shader=_ID_FS)
        self.depth_prog = c.program(vertex_shader=_DEPTH_VS, fragment_shader=_DEPTH_FS)
        # One background program per kind, so neither pays for the other's instructions
        # (llvmpipe executes both sides of a branch under a mask).
        tri = c.buffer(np.array([-1, -1, 3, -1, -1, 3], dtype="f4").tobytes())
        self.bg_progs, self.bg_vaos = {}, {}
        for kind, fs in (("iss", _EARTH_FS), ("perlin", _PERLIN_FS)):
            prog = c.program(vertex_shader=_BG_VS, fragment_shader=fs)
            self.bg_progs[kind] = prog
            self.bg_vaos[kind] = c.vertex_array(prog, [(tri, "2f", "in_xy")])

        samples = s.msaa_samples
        self.fbo = c.framebuffer(
            color_attachments=[c.renderbuffer((W, H), 4, samples=samples)],
            depth_attachment=c.depth_renderbuffer((W, H), samples=samples),
        )
        self.resolve_fbo = (
            c.framebuffer(color_attachments=[c.renderbuffer((W, H), 4)]) if samples else self.fbo
        )

        # Both cascades in one depth texture (near | far), so the mesh shader needs a single
        # filtered shadow tap per pixel, not one per cascade.
        n = s.shadow_map_px
        self.shadow_tex = c.depth_texture((2 * n, n))
        self.shadow_tex.compare_func = "<="
        self.shadow_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)  # 2x2 PCF in hardware
        self.shadow_tex.repeat_x = self.shadow_tex.repeat_y = False
        self.shadow_fbo = c.framebuffer(depth_attachment=self.shadow_tex)
        self._shadow_key: tuple[object, ...] | None = None
        self._light_vp = [np.eye(4), np.eye(4)]
        # The Earth's shadow maps, one tile per sample direction (made when the Earth moves in
        # LVLH or the scene changes: once per scene for a station in LVLH hold).
        m = s.earth_shadow_px * self.earth_tiles
        self.earth_shadow_tex = c.depth_texture((m, m))
        self.earth_shadow_tex.compare_func = "<="
        self.earth_shadow_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.earth_shadow_tex.repeat_x = self.earth_shadow_tex.repeat_y = False
        self.earth_shadow_fbo = c.framebuffer(depth_attachment=self.earth_shadow_tex)
        self._earth_key: tuple[object, ...] | None = None
        self._earth: EarthLight | None = None
        self._earth_l = np.zeros((s.earth_samples, 3))
        self._earth_vp = np.zeros((s.earth_samples, 4, 4))

        self._earth_tex: Any = None  # built on first use: ~1 s of noise, not needed for `perlin`
        self.bg_tex: Any = None
        self.background = "iss"
        # moderngl objects, made by load_scene
        self.mesh_vao: Any = None
        self.depth_vao: Any = None
        self.id_vao: Any = None
        self._vbo: Any = None
        self._ibo: Any = None
        self.focus = np.zeros(3)
        self.gl_renderer = c.info.get("GL_RENDERER", "unknown")
        # A randomised look (oibar_hil.randomize): its programs, maps and textures are made for
        # the first scene that has one; a scene without one renders exactly as before.
        self.look: LookParams | None = None
        self._look_gl: dict[str, Any] = {}
        self._R_lvlh_t = np.eye(3)
        self._lamp_key: tuple[object, ...] | None = None
        self._lamp_vp = np.tile(np.eye(4), (MAX_LAMPS, 1, 1))
        self._lamp_texel = np.zeros(MAX_LAMPS)

    def _look_programs(self) -> dict[str, Any]:
        """The randomised look's mesh program (the mesh shader with LOOK defined), the optics
        pass, the spot lamps' shadow atlas and the frame buffers the optics pass reads and
        writes: made once, on first use."""
        import moderngl

        g = self._look_gl
        if g:
            return g
        c = self.ctx
        W, H = self.camera.width_px, self.camera.height_px
        g["mesh"] = {}
        g["post"] = c.program(vertex_shader=_POST_VS, fragment_shader=_POST_FS)
        tri = c.buffer(np.array([-1, -1, 3, -1, -1, 3], dtype="f4").tobytes())
        g["post_vao"] = c.vertex_array(g["post"], [(tri, "2f", "in_xy")])
        n = LAMP_SHADOW_PX
        g["lamp_tex"] = c.depth_texture((MAX_LAMPS * n, n))
        g["lamp_tex"].compare_func = "<="
        g["lamp_tex"].filter = (moderngl.LINEAR, moderngl.LINEAR)
        g["lamp_tex"].repeat_x = g["lamp_tex"].repeat_y = False
        g["lamp_fbo"] = c.framebuffer(depth_attachment=g["lamp_tex"])
        g["src_tex"] = c.texture((W, H), 4)
        g["src_tex"].filter = (moderngl.LINEAR, moderngl.LINEAR)
        g["src_tex"].repeat_x = g["src_tex"].repeat_y = False
        g["src_fbo"] = c.framebuffer(
            color_attachments=[g["src_tex"]], depth_attachment=c.depth_renderbuffer((W, H))
        )
        g["out_fbo"] = c.framebuffer(color_attachments=[c.renderbuffer((W, H), 4)])
        return g

    def _look_mesh_program(self, n_lamps: int) -> Any:
        """The mesh shader with LOOK defined, for `n_lamps` lamps (compiled once per count)."""
        progs = self._look_programs()["mesh"]
        if n_lamps not in progs:
            defines = self._defines + (
                f"#define LOOK 1\n#define N_LAMPS {n_lamps}\n#define MAX_LAMPS {MAX_LAMPS}\n"
                f"#define LOOK_SLOTS {LOOK_SLOTS}\n"
            )
            progs[n_lamps] = self.ctx.program(
                vertex_shader=_MESH_VS.replace("#version 330\n", "#version 330\n" + defines, 1),
                fragment_shader=_MESH_FS.replace("#version 330\n", "#version 330\n" + defines, 1),
            )
        return progs[n_lamps]

    def _texture(self, img: np.ndarray):
        import moderngl

        h, w, comps = img.shape
        tex = self.ctx.texture((w, h), comps, np.ascontiguousarray(img).tobytes())
        tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
        tex.repeat_x, tex.repeat_y = True, False
        return tex

    # The public GL entry points make this renderer's context current first: a process may hold
    # several (the dataset writer's cached one, a rig camera, a test's), and GL calls issued
    # while another one, or none, is current crash inside the driver instead of raising.
    def load_scene(
        self,
        parts: list[Part],
        background: str,
        focus_lvlh: np.ndarray,
        perlin_seed: int | None = None,
        look: LookParams | None = None,
        R_lvlh_t: np.ndarray | None = None,
    ):
        """Upload the meshes; `focus_lvlh` centres the shadow map (the target port, the fixture's
        origin). `look`: a randomised look (oibar_hil.randomize) for every frame of this scene;
        `R_lvlh_t`, the fixture's axes, places its lamps and textures (default: LVLH's)."""
        with self.ctx:
            self._load_scene(parts, background, focus_lvlh, perlin_seed, look, R_lvlh_t)

    def render(
        self,
        R_lvlh_cam: np.ndarray,
        p_lvlh_cam: np.ndarray,
        sun_lvlh: np.ndarray,
        R_ecef_lvlh: np.ndarray | None = None,
        earth_center_lvlh_km: np.ndarray | None = None,
        mode: str = "shaded",
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """One frame as (H, W, 3) uint8, row 0 at the top. mode 'id' returns part ids in
        channel 0 and no background, lighting, noise or blur."""
        with self.ctx:
            return self._render(
                R_lvlh_cam, p_lvlh_cam, sun_lvlh, R_ecef_lvlh, earth_center_lvlh_km, mode, rng
            )

    def _load_scene(
        self,
        parts: list[Part],
        background: str,
        focus_lvlh: np.ndarray,
        perlin_seed: int | None,
        look: LookParams | None = None,
        R_lvlh_t: np.ndarray | None = None,
    ) -> None:
        for obj in (self.mesh_vao, self.depth_vao, self.id_vao, self._vbo, self._ibo):
            if obj is not None:
                obj.release()
        # Target fixture first, station last: front-to-back order lets early-z skip hidden work.
        parts = sorted(parts, key=lambda p: (p.part_id >= ID_ADAPTER, p.part_id >= ID_MODULE))
        self.look = look
        self._R_lvlh_t = np.eye(3) if R_lvlh_t is None else np.asarray(R_lvlh_t, float)
        self._lamp_key = None
        if look is None:
            self.mesh_prog = self.default_mesh_prog
            data, idx = _vertex_data(parts)
            mesh_fmt, id_fmt, depth_fmt = "3f 3f 4f 4x", "3f 28x 1f", "3f 32x"
            attrs: tuple[str, ...] = ("in_pos", "in_nrm", "in_col")
        else:
            self.mesh_prog = self._look_mesh_program(len(look.lamps))
            parts, slots = self._look_materials(parts, look)
            data, idx = _vertex_data(parts, slots)
            mesh_fmt, id_fmt, depth_fmt = "3f 3f 4f 4x 1f", "3f 28x 1f 4x", "3f 36x"
            attrs = ("in_pos", "in_nrm", "in_col", "in_slot")
        vbo = self._vbo = self.ctx.buffer(data.tobytes())
        ibo = self._ibo = self.ctx.buffer(idx.tobytes())
        self.mesh_vao = self.ctx.vertex_array(
            self.mesh_prog, [(vbo, mesh_fmt, *attrs)], index_buffer=ibo, index_element_size=4
        )
        self.id_vao = self.ctx.vertex_array(
            self.id_prog, [(vbo, id_fmt, "in_pos", "in_id")], index_buffer=ibo, index_element_size=4
        )
        self.depth_vao = self.ctx.vertex_array(
            self.depth_prog, [(vbo, depth_fmt, "in_pos")], index_buffer=ibo, index_element_size=4
        )
        self.background = background
        self.focus = np.asarray(focus_lvlh, dtype=float)
        if look is not None:
            self._load_look_textures(look)
        elif background == "perlin":
            if perlin_seed is None:
                raise ValueError("the perlin background needs a seed")
            self.bg_tex = self._texture(perlin_background(perlin_seed))
        else:
            if self._earth_tex is None:
                self._earth_tex = self._texture(earth_rgba())
            self.bg_tex = self._earth_tex
        self._shadow_key = None
        self._earth_key = None
        self.triangles = int(len(idx))

    @staticmethod
    def _look_materials(parts: list[Part], look: LookParams) -> tuple[list[Part], list[int]]:
        """The target fixture's parts in the look's materials (colour and specular in the vertex
        data, the rest by material slot); everything else keeps its own (slot 0). The other
        ports' fixtures share the parts' names but not their id, and stay as built."""
        names = [name for name, _ in look.materials]
        out, slots = [], []
        for p in parts:
            m = look.material(p.name) if p.part_id != ID_OTHER_FIXTURE else None
            if m is None:
                out.append(p)
                slots.append(0)
                continue
            rgb, spec = (p.rgb, p.specular) if m.kind == "as_built" else (m.rgb, m.specular)
            out.append(Part(p.mesh, tuple(rgb), float(spec), p.part_id, p.name))
            slots.append(1 + names.index(p.name))
        return out, slots

    def _load_look_textures(self, look: LookParams) -> None:
        """The look's material table, its fBm volume and its backdrop."""
        import moderngl

        mp = self.mesh_prog
        surf = np.zeros((LOOK_SLOTS, 4), dtype="f4")
        texp = np.zeros((LOOK_SLOTS, 4), dtype="f4")
        surf[0] = (48.0, 0.0, 0.0, 0.0)  # as built: the default shader's shininess, no texture
        texp[0] = (1.0, 1.0, 1.0, 0.0)
        for i, (_, m) in enumerate(look.materials):
            surf[i + 1] = (m.shininess, m.grain, m.bump, m.banding)
            texp[i + 1] = (m.scale_per_m, m.stretch, m.band_period_m, 0.0)
        mp["u_surf"].write(surf.tobytes())
        mp["u_texp"].write(texp.tobytes())
        mp["u_R_t_world"].write(_m3(self._R_lvlh_t.T))
        if "noise" in self._look_gl:
            self._look_gl["noise"].release()
        vol = periodic_noise3d(look.seed)
        noise = self.ctx.texture3d(vol.shape[:3], 4, np.ascontiguousarray(vol).tobytes())
        noise.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        noise.repeat_x = noise.repeat_y = noise.repeat_z = True
        noise.build_mipmaps()
        self._look_gl["noise"] = noise
        if look.backdrop == "earth":
            if self._earth_tex is None:
                self._earth_tex = self._texture(earth_rgba())
            self.bg_tex = self._earth_tex
        elif look.backdrop == "perlin":
            self.bg_tex = self._texture(perlin_background(look.backdrop_seed))
        elif look.backdrop == "stars":
            self.bg_tex = self._texture(star_background(look.backdrop_seed))
        elif look.backdrop == "clutter":
            self.bg_tex = self._texture(lab_clutter_background(look.backdrop_seed))
        else:
            self.bg_tex = None

    def _lamps(self, R_lvlh_cam: np.ndarray, p_lvlh_cam: np.ndarray) -> list[dict[str, Any]]:
        """This frame's spot lamps in LVLH: position, beam axis, intensity (its irradiance at the
        aim point is the look's, whatever the distance) and cosines of its cone."""
        assert self.look is not None
        out = []
        for lamp in self.look.lamps:
            p = np.asarray(lamp.position_m, float)
            pos = p_lvlh_cam + R_lvlh_cam @ p if lamp.mount == "camera" else self.focus + self._R_lvlh_t @ p
            aim = self.focus + self._R_lvlh_t @ np.asarray(lamp.aim_m, float)
            axis = aim - pos
            dist = float(np.linalg.norm(axis))
            out.append(
                {
                    "pos": pos,
                    "dir": axis / dist,
                    "dist": dist,
                    "i": np.asarray(lamp.rgb) * lamp.irradiance * dist * dist * self.settings.sun_intensity,
                    "cos": (
                        float(np.cos(np.radians(lamp.cone_deg))),
                        float(np.cos(np.radians(lamp.cone_deg - lamp.soft_deg))),
                    ),
                    "fov_deg": min(2.0 * lamp.cone_deg + 4.0, 150.0),
                }
            )
        return out

    def _update_lamp_shadows(self, lamps: list[dict[str, Any]]) -> None:
        """Each lamp's perspective shadow map (re-rendered when a lamp moves: every frame for a
        lamp on the camera, once per scene for one fixed in the lab)."""
        key = tuple(tuple(np.round(np.concatenate([lp["pos"], lp["dir"]]), 9)) for lp in lamps)
        if not lamps or key == self._lamp_key:
            return
        g = self._look_gl
        self.ctx.enable(self.ctx.DEPTH_TEST | self.ctx.CULL_FACE)
        self.ctx.polygon_offset = (1.5, 2.0)
        n = LAMP_SHADOW_PX
        g["lamp_fbo"].use()
        g["lamp_fbo"].clear(depth=1.0)
        for k, lp in enumerate(lamps):
            # the near plane well in front of anything lit, the far one past the station behind
            self._lamp_vp[k] = spot_matrix(lp["pos"], lp["dir"], lp["fov_deg"], 0.05, lp["dist"] + 80.0)
            self._lamp_texel[k] = 2.0 * np.tan(np.radians(lp["fov_deg"]) / 2) / n
            g["lamp_fbo"].viewport = (k * n, 0, n, n)
            self.depth_prog["u_light_vp"].write(_m4(self._lamp_vp[k]))
            self.depth_vao.render()
        self.ctx.polygon_offset = (0.0, 0.0)
        self._lamp_key = key

    def _update_shadow(self, sun_lvlh: np.ndarray) -> None:
        key = (tuple(np.round(sun_lvlh, 12)), tuple(self.focus))
        if key == self._shadow_key:
            return
        s = self.settings
        # Closed meshes: the surface nearest the Sun is always a front face, so culling back
        # faces leaves the depth map unchanged and halves the fill.
        self.ctx.enable(self.ctx.DEPTH_TEST | self.ctx.CULL_FACE)
        self.ctx.polygon_offset = (1.5, 2.0)  # slope-scaled bias
        n = s.shadow_map_px
        self.shadow_fbo.use()
        self.shadow_fbo.clear(depth=1.0)
        # Same light view, focus and depth range for both cascades, only the extent differs: the
        # mesh shader derives far-cascade coordinates from near ones with u_far_scale.
        for i, half in enumerate((s.shadow_near_half_extent_m, s.shadow_far_half_extent_m)):
            self._light_vp[i] = light_matrix(sun_lvlh, self.focus, half, s.shadow_depth_m)
            self.shadow_fbo.viewport = (i * n, 0, n, n)
            self.depth_prog["u_light_vp"].write(_m4(self._light_vp[i]))
            self.depth_vao.render()
        self.ctx.polygon_offset = (0.0, 0.0)
        self._shadow_key = key

    def _update_earth_shadow(self, earth_c_km: np.ndarray) -> None:
        """The sample directions over the Earth's disc and their shadow maps (cached)."""
        key = (tuple(np.round(earth_c_km, 6)), tuple(self.focus))
        if key == self._earth_key:
            return
        s = self.settings
        self._earth = EarthLight(earth_c_km, s.earth_samples)
        self._earth_l = self._earth.dirs
        self.ctx.enable(self.ctx.DEPTH_TEST | self.ctx.CULL_FACE)
        self.ctx.polygon_offset = (1.5, 2.0)
        m = s.earth_shadow_px
        self.earth_shadow_fbo.use()
        self.earth_shadow_fbo.clear(depth=1.0)
        for k, d in enumerate(self._earth_l):
            self._earth_vp[k] = light_matrix(d, self.focus, s.earth_shadow_half_extent_m, s.shadow_depth_m)
            self.earth_shadow_fbo.viewport = ((k % self.earth_tiles) * m, (k // self.earth_tiles) * m, m, m)
            self.depth_prog["u_light_vp"].write(_m4(self._earth_vp[k]))
            self.depth_vao.render()
        self.ctx.polygon_offset = (0.0, 0.0)
        self._earth_key = key

    def _render(
        self,
        R_lvlh_cam: np.ndarray,
        p_lvlh_cam: np.ndarray,
        sun_lvlh: np.ndarray,
        R_ecef_lvlh: np.ndarray | None,
        earth_center_lvlh_km: np.ndarray | None,
        mode: str,
        rng: np.random.Generator | None,
    ) -> np.ndarray:
        if self.mesh_vao is None:
            raise RuntimeError("load_scene() first")
        cam, s, ctx = self.camera, self.settings, self.ctx
        sun = np.asarray(sun_lvlh, dtype=float)
        sun = sun / np.linalg.norm(sun)
        earth_c = (
            np.array(DEFAULT_EARTH_CENTER_LVLH_KM)
            if earth_center_lvlh_km is None
            else np.asarray(earth_center_lvlh_km, float)
        )
        look = self.look if mode == "shaded" else None
        lamps: list[dict[str, Any]] = []
        if mode == "shaded":
            self._update_shadow(sun)
            self._update_earth_shadow(earth_c)
        if look is not None:
            lamps = self._lamps(np.asarray(R_lvlh_cam, float), np.asarray(p_lvlh_cam, float))
            self._update_lamp_shadows(lamps)
        R_ecef = np.eye(3) if R_ecef_lvlh is None else R_ecef_lvlh
        exposure = s.exposure if look is None else look.exposure

        optics = look is not None and (look.vignetting > 0 or look.distortion_k1 != 0)
        # the optics pass samples the frame: drawn straight into a texture (without MSAA), no copy
        fbo = self._look_gl["src_fbo"] if optics and not s.msaa_samples else self.fbo
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        # All meshes are closed with outward CCW faces: culling back faces halves the work.
        ctx.enable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.depth_func = "<="
        V = view_matrix(np.asarray(R_lvlh_cam, float), np.asarray(p_lvlh_cam, float))
        vp = _m4(gl_projection(cam) @ V)
        if mode == "id":
            self.id_prog["u_vp"].write(vp)
            self.id_vao.render()
        else:
            mp = self.mesh_prog
            mp["u_vp"].write(vp)
            mp["u_light_vp_near"].write(_m4(self._light_vp[0]))
            mp["u_far_scale"].value = s.shadow_near_half_extent_m / s.shadow_far_half_extent_m
            mp["u_sun_dir"].value = tuple(sun)
            mp["u_earth_l"].write(self._earth_l.astype("f4").tobytes())
            assert self._earth is not None  # _update_earth_shadow ran above
            w = self._earth.weights(sun, R_ecef) * s.sun_intensity
            if look is not None:
                w = w * look.earth_scale
            mp["u_earth_w"].write(w.astype("f4").tobytes())
            mp["u_earth_vp"].write(b"".join(_m4(M) for M in self._earth_vp))
            mp["u_focus"].value = tuple(self.focus)
            mp["u_earth_reach2"].value = s.earth_shadow_half_extent_m**2
            mp["u_earth_texel_depth"].value = s.earth_shadow_half_extent_m / (
                s.earth_shadow_px * s.shadow_depth_m
            )
            self.earth_shadow_tex.use(location=3)
            mp["u_earth_shadow"].value = 3
            mp["u_cam_pos"].value = tuple(np.asarray(p_lvlh_cam, float))
            mp["u_sun_intensity"].value = (
                s.sun_intensity if look is None else s.sun_intensity * look.sun_scale
            )
            mp["u_ambient"].value = s.ambient if look is None else look.ambient
            mp["u_exposure"].value, mp["u_gamma"].value = exposure, s.gamma
            n = s.shadow_map_px
            mp["u_texel_depth"].value = (
                s.shadow_near_half_extent_m / (n * s.shadow_depth_m),
                s.shadow_far_half_extent_m / (n * s.shadow_depth_m),
            )
            mp["u_bias_texels"].value = s.shadow_bias_texels
            mp["u_max_slope"].value = s.shadow_max_slope
            mp["u_atlas_margin"].value = 0.5 / s.shadow_map_px
            self.shadow_tex.use(location=2)
            mp["u_shadow"].value = 2
            if look is not None:
                self._set_look_uniforms(mp, lamps)
            self.mesh_vao.render()

            ctx.disable(ctx.CULL_FACE)
            kind: str | None = "perlin" if self.background == "perlin" else "iss"
            bg_exposure = exposure
            if look is not None:
                kind = {"black": None, "earth": "iss"}.get(look.backdrop, "perlin")
                # a display-referred backdrop: its gain applies after the sensor's encoding
                bg_exposure = exposure * look.backdrop_gain**s.gamma
            if kind is not None:
                self._draw_background(kind, R_lvlh_cam, sun, earth_c, R_ecef, bg_exposure)

        if look is not None and optics:
            img = self._optics(look, copy=fbo is self.fbo)
            return apply_sensor_effects(img, s.noise_sigma_dn, s.blur_sigma_px, rng)
        if self.resolve_fbo is not self.fbo:
            ctx.copy_framebuffer(self.resolve_fbo, self.fbo)
        raw = self.resolve_fbo.read(components=3, alignment=1)
        img = np.frombuffer(raw, dtype=np.uint8).reshape(cam.height_px, cam.width_px, 3)[::-1]
        if mode == "id":
            return np.ascontiguousarray(img)
        return apply_sensor_effects(np.ascontiguousarray(img), s.noise_sigma_dn, s.blur_sigma_px, rng)

    def _draw_background(
        self,
        kind: str,
        R_lvlh_cam: np.ndarray,
        sun: np.ndarray,
        earth_c: np.ndarray,
        R_ecef: np.ndarray,
        exposure: float,
    ) -> None:
        cam, s = self.camera, self.settings
        bp = self.bg_progs[kind]
        bp["u_R_world_cam"].write(_m3(R_lvlh_cam))
        bp["u_intr"].value = (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px)
        bp["u_size"].value = (float(cam.width_px), float(cam.height_px))
        bp["u_exposure"].value, bp["u_gamma"].value = exposure, s.gamma
        if kind == "iss":
            clen = float(np.linalg.norm(earth_c))
            bp["u_sun_dir"].value = tuple(sun)
            bp["u_earth_center_km"].value = tuple(earth_c)
            bp["u_c2_minus_r2"].value = clen * clen - EARTH_RADIUS_KM**2
            bp["u_inv_clen"].value = 1.0 / clen
            bp["u_limb"].value = float(np.arcsin(EARTH_RADIUS_KM / clen))
            bp["u_R_ecef_world"].write(_m3(R_ecef))
        self.bg_tex.use(location=1)
        bp["u_tex"].value = 1
        self.bg_vaos[kind].render()

    def _set_look_uniforms(self, mp: Any, lamps: list[dict[str, Any]]) -> None:
        g = self._look_gl
        g["noise"].use(location=5)
        mp["u_noise"].value = 5
        n = len(lamps)
        if n == 0:
            return

        def rows(key: str) -> bytes:
            return np.array([lp[key] for lp in lamps], "f4").tobytes()

        mp["u_lamp_pos"].write(rows("pos"))
        mp["u_lamp_dir"].write(rows("dir"))
        mp["u_lamp_i"].write(rows("i"))
        mp["u_lamp_cos"].write(rows("cos"))
        mp["u_lamp_vp"].write(b"".join(_m4(M) for M in self._lamp_vp[:n]))
        mp["u_lamp_texel"].write(self._lamp_texel[:n].astype("f4").tobytes())
        mp["u_lamp_margin"].value = 0.5 / LAMP_SHADOW_PX
        g["lamp_tex"].use(location=4)
        mp["u_lamp_shadow"].value = 4

    def _optics(self, look: LookParams, copy: bool) -> np.ndarray:
        """The look's lens distortion and vignetting on the frame just drawn (in the optics'
        source texture, or `copy` it there from the MSAA frame buffer); (H, W, 3) uint8."""
        g, cam, ctx = self._look_gl, self.camera, self.ctx
        if copy:
            ctx.copy_framebuffer(g["src_fbo"], self.fbo)
        g["out_fbo"].use()
        ctx.disable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        pp = g["post"]
        g["src_tex"].use(location=0)
        pp["u_img"].value = 0
        pp["u_intr"].value = (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px)
        pp["u_size"].value = (float(cam.width_px), float(cam.height_px))
        pp["u_k1"].value = look.distortion_k1
        pp["u_vignetting"].value = look.vignetting
        pp["u_r_corner2"].value = float((cam.cx_px**2 + cam.cy_px**2) / cam.fx_px**2)
        pp["u_gamma"].value = self.settings.gamma
        g["post_vao"].render()
        raw = g["out_fbo"].read(components=3, alignment=1)
        img = np.frombuffer(raw, dtype=np.uint8).reshape(cam.height_px, cam.width_px, 3)[::-1]
        return np.ascontiguousarray(img)

    def release(self) -> None:
        self.ctx.release()


def _gauss_kernel(sigma: float) -> np.ndarray:
    r = max(1, int(np.ceil(3 * sigma)))
    x = np.arange(-r, r + 1)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def apply_sensor_effects(
    img: np.ndarray, noise_sigma_dn: float, blur_sigma_px: float, rng: np.random.Generator | None
) -> np.ndarray:
    """Optional blur (separable Gaussian) then additive Gaussian read noise, both in 8-bit DN."""
    if blur_sigma_px <= 0 and noise_sigma_dn <= 0:
        return img
    out = img.astype(np.float32)
    if blur_sigma_px > 0:
        k = _gauss_kernel(blur_sigma_px)
        r = len(k) // 2
        pad = np.pad(out, ((r, r), (r, r), (0, 0)), mode="edge")
        tmp = sum(k[i] * pad[:, i : i + out.shape[1]] for i in range(len(k)))
        out = sum(k[i] * tmp[i : i + out.shape[0]] for i in range(len(k)))
    if noise_sigma_dn > 0:
        if rng is None:
            raise ValueError("sensor noise needs a seeded rng (determinism)")
        out = out + rng.normal(0.0, noise_sigma_dn, out.shape).astype(np.float32)
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


def set_llvmpipe_threads(n: int) -> None:
    """Mesa's CPU rasteriser reads LP_NUM_THREADS when the context is created."""
    os.environ.setdefault("LP_NUM_THREADS", str(n))
