#version 330 core
// Billboards drawn from their decoded tiles: one instanced draw of triangle strips (4 vertices
// per quad, corners from gl_VertexID; no vertex buffer, only instances).
//
// Per instance: a run of a column of render.slits — a billboard, a ground block or a slit of
// `blocks` facade blocks — with its centre (model coordinates), base yaw and kind, the position
// of its first block in the decoded atlas, and the weights of the sampled directions held in
// each storage slot (render.view_brackets; computed for this view on the CPU). The vertex stage
// turns a billboard toward the eye and leaves layer blocks fixed. The fragment stage finds its
// block within the run and blends its decoded tiles: colour = clamp(Σ_s w_s·D_s, 0, 1), one
// fetch per slot in use, bilinear within the block's tile (u_linear) or the nearest texel,
// never reading a neighbouring tile. Alpha < 0.5 is discarded.

#include "billboard_quad.glsl"

#if defined VERTEX_SHADER

in vec3 in_centre;       // model coordinates (m)
in float in_base_yaw;    // world yaw (radians) a layer block faces
in int in_kind;          // 0 billboard, 1 facade block (or slit), 2 ground block
in int in_blocks;        // blocks in the run (1 unless a slit)
in vec2 in_origin;       // top-left texel of the run's top block, storage slot 0, in the decoded atlas
in vec4 in_weights;      // weight of each storage slot's direction

out vec2 v_texel;
flat out vec2 v_origin;
flat out float v_blocks;
flat out vec4 v_weights;

void main() {
    v_origin = in_origin;
    v_blocks = float(in_blocks);
    v_weights = in_weights;
    gl_Position = quad_vertex_run(in_centre, quad_angles(in_centre, in_base_yaw, in_kind), in_kind,
                                  quad_corner(gl_VertexID), in_blocks, v_texel);
}

#elif defined FRAGMENT_SHADER

// The decoded atlas (render.gpu_decode): a block's STORAGE_SLOTS tiles lie side by side, and the
// blocks of a run one below the other, so every address is an addition (integer division is
// slow per fragment on llvmpipe).
uniform sampler2D u_decoded;     // RGBA16F
uniform vec2 u_decoded_texel;    // 1 / atlas size
uniform bool u_linear;           // bilinear texels within each tile (else the nearest texel)

in vec2 v_texel;
flat in vec2 v_origin;
flat in float v_blocks;
flat in vec4 v_weights;

out vec4 f_color;

vec4 decoded(vec2 origin, vec2 texel) {
    if (u_linear) return texture(u_decoded, (origin + clamp(texel, vec2(0.5), vec2(float(u_tile) - 0.5))) * u_decoded_texel);
    return texelFetch(u_decoded, ivec2(origin) + tile_texel(texel), 0);
}

void main() {
    float t = float(u_tile);
    float block = clamp(floor(v_texel.y / t), 0.0, v_blocks - 1.0);
    vec2 texel = vec2(v_texel.x, v_texel.y - block * t);
    vec2 origin = v_origin + vec2(0.0, block * t);
    vec4 colour = vec4(0.0);
    if (v_weights.x != 0.0) colour += v_weights.x * decoded(origin, texel);
    if (v_weights.y != 0.0) colour += v_weights.y * decoded(origin + vec2(t, 0.0), texel);
#if STORAGE_SLOTS == 4
    if (v_weights.z != 0.0) colour += v_weights.z * decoded(origin + vec2(2.0 * t, 0.0), texel);
    if (v_weights.w != 0.0) colour += v_weights.w * decoded(origin + vec2(3.0 * t, 0.0), texel);
#endif
    colour = clamp(colour, 0.0, 1.0);
    if (colour.a < 0.5) discard;
    f_color = vec4(colour.rgb, 1.0);
}

#endif
