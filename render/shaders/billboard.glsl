#version 330 core
// Billboards drawn from their decoded tiles: one instanced draw of triangle strips (4 vertices
// per quad, corners from gl_VertexID; no vertex buffer, only instances).
//
// Per instance: a run of a column of billboards.slits — a billboard, a ground block or a slit of
// `blocks` facade blocks — with its centre (model coordinates), base yaw, kind and edge, the position
// of its first block in the decoded atlas, and the weights of the sampled directions held in
// each storage slot (render.view_brackets; computed for this view on the CPU). The vertex stage
// turns a billboard toward the eye and leaves layer blocks fixed. The fragment stage blends the
// run's decoded tiles: colour = clamp(Σ_s w_s·D_s, 0, 1), one fetch per slot (or one fetch of
// the tiles pre-blended for this view), bilinear or the nearest texel. A run's blocks lie one
// below the other in the atlases, so its tiles form one texture of t × blocks·t texels,
// filtered across the edges between its blocks (neighbouring blocks of one facade column) and
// kept inside the run's outer texel centres, so it never reads another run's tiles. No
// per-fragment block index: on a CPU rasterizer every instruction of this stage counts.
// Alpha < 0.5 is discarded.

// MULTIVIEW 1: several views in one draw (impostor images, render.impostors): each instance
// names its view, whose projection maps into that view's tile of the target; fragments outside
// the tile are discarded.

#if MULTIVIEW
const int MAX_VIEWS = 32;
uniform mat4 u_view_projections[MAX_VIEWS];   // per view: GL clip (of the whole target) from GL eye
uniform vec4 u_view_rects[MAX_VIEWS];         // per view: its tile (x0, y0, x1, y1) in target pixels
#if defined VERTEX_SHADER
in int in_view;
#define QUAD_PROJECTION u_view_projections[in_view]
#endif
#endif

#include "billboard_quad.glsl"

#if defined VERTEX_SHADER

in vec3 in_centre;       // model coordinates (m)
in float in_base_yaw;    // world yaw (radians) a layer block faces
in int in_kind;          // 0 billboard, 1 facade block (or slit), 2 ground block, 3 plane (a planar leaf)
in float in_size;        // edge of the quad (a slit: of each of its blocks), m
in int in_blocks;        // blocks in the run (1 unless a slit)
in vec2 in_origin;       // top-left texel of the run's top block in the atlas drawn from (slot 0)
in vec4 in_weights;      // weight of each storage slot's direction (unused with VIEW)
in vec4 in_corner_dz;    // a ground block's corners above its centre (m; zeros otherwise)

out vec2 v_texel;
flat out vec2 v_origin;
flat out vec2 v_texel_max;
flat out vec4 v_weights;
#if MULTIVIEW
flat out vec4 v_rect;
#endif

void main() {
#if MULTIVIEW
    v_rect = u_view_rects[in_view];
#endif
    v_origin = in_origin;
    v_texel_max = vec2(float(u_tile), float(u_tile * in_blocks)) - 0.5;   // the run's last texel centre
    v_weights = in_weights;
    gl_Position = quad_vertex_run(in_centre, quad_angles(in_centre, in_base_yaw, in_kind), in_kind, in_size,
                                  quad_corner(gl_VertexID), in_blocks, in_corner_dz, v_texel);
}

#elif defined FRAGMENT_SHADER

// Branch-free (llvmpipe runs both sides of a branch on a flat input): compiled per source
// (DECODED: the STORAGE_SLOTS tiles of the bracket, blended here; VIEW: the view atlas, where
// large quads were blended once per texel) and per filter (LINEAR 1: bilinear within the
// run's tiles, 0: the nearest texel). In the atlases a block's slots lie side by side and the
// blocks of a run one below the other, so every address is an addition.
uniform sampler2D u_tiles_in;   // RGBA16F: the decoded atlas (DECODED) or the view atlas (VIEW)
uniform vec2 u_atlas_texel;     // 1 / its size

in vec2 v_texel;
flat in vec2 v_origin;
flat in vec2 v_texel_max;
flat in vec4 v_weights;
#if MULTIVIEW
flat in vec4 v_rect;
#endif

out vec4 f_color;

vec4 fetch(vec2 origin, vec2 texel) {
#if LINEAR
    return texture(u_tiles_in, (origin + clamp(texel, vec2(0.5), v_texel_max)) * u_atlas_texel);
#else
    return texelFetch(u_tiles_in, ivec2(origin) + clamp(ivec2(floor(texel)), ivec2(0), ivec2(v_texel_max)), 0);
#endif
}

void main() {
#if MULTIVIEW
    if (any(lessThan(gl_FragCoord.xy, v_rect.xy)) || any(greaterThanEqual(gl_FragCoord.xy, v_rect.zw))) discard;
#endif
    float t = float(u_tile);
#if VIEW
    vec4 colour = fetch(v_origin, v_texel);
#else
    vec4 colour = v_weights.x * fetch(v_origin, v_texel) + v_weights.y * fetch(v_origin + vec2(t, 0.0), v_texel);
#if STORAGE_SLOTS == 4
    colour += v_weights.z * fetch(v_origin + vec2(2.0 * t, 0.0), v_texel)
              + v_weights.w * fetch(v_origin + vec2(3.0 * t, 0.0), v_texel);
#endif
#endif
    colour = clamp(colour, 0.0, 1.0);
    if (colour.a < 0.5) discard;
    f_color = vec4(colour.rgb, 1.0);
}

#endif
