#version 330 core
// Billboards with eigen-texture decode on the GPU: one instanced draw of triangle strips
// (4 vertices per billboard, corners from gl_VertexID; no vertex buffer, only instances).
//
// Per instance: centre (model coordinates), base yaw, first slot, rank and kind. The vertex
// stage turns a billboard toward the eye and leaves a layer block fixed. The view-dependent part of the decode (direction
// interpolation and eigen weights) has been done per slot by billboard_weights.glsl, so
// the fragment stage is colour = clamp(C + Σ_{k=0..r} T_k·q_k, 0, 1) with q_k the
// texel of tile k: two fetches per tile. Alpha < 0.5 is discarded. Texels are bilinear
// within each tile (u_linear) or the nearest one, as in the CPU decode path.

#include "billboard_quad.glsl"
#include "billboard_slots.glsl"

#if defined VERTEX_SHADER

in vec3 in_centre;       // model coordinates (m)
in float in_base_yaw;    // world yaw (radians) a layer block faces
in ivec2 in_slot;        // (first slot, rank)
in int in_kind;          // 0 billboard, 1 facade block, 2 ground block

out vec2 v_texel;
flat out ivec2 v_slot;

void main() {
    v_slot = in_slot;
    gl_Position = quad_vertex(in_centre, quad_angles(in_centre, in_base_yaw, in_kind), in_kind,
                              quad_corner(gl_VertexID), v_texel);
}

#elif defined FRAGMENT_SHADER

uniform sampler2D u_slot_terms;   // RGBA32F, one texel per slot: T_k (weights pass)
uniform sampler2D u_slot_const;   // RGBA32F, one texel per slot: C at each billboard's first slot

in vec2 v_texel;
flat in ivec2 v_slot;

out vec4 f_color;

void main() {
    int first = v_slot.x;
    vec4 colour = texelFetch(u_slot_const, slot_texel(first), 0);
    for (int k = 0; k <= v_slot.y; ++k) {
        colour += texelFetch(u_slot_terms, slot_texel(first + k), 0) * tile_q(first + k, v_texel);
    }
    colour = clamp(colour, 0.0, 1.0);
    if (colour.a < 0.5) discard;
    f_color = vec4(colour.rgb, 1.0);
}

#endif
