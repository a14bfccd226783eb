#version 330 core
// Decode pass of the GPU decode: tiles of billboards at single sampled directions, written
// into the decoded atlas that billboard.glsl draws from. One instance per tile to decode, a
// point of u_tile pixels (glPointSize) over its t×t texels in the atlas; each fragment is one texel:
//   colour = mean + Σ_{k=1..r} w_k·V_k,   tiles dequantised as offset + scale·q,
//   w_k = coef_offset + coef_scale·q_k(direction),
// unclamped (the blend of directions clamps), r the billboard's rank or less (level of detail).
//
// On a CPU rasterizer a point covers whole 4×4 blocks and is one primitive where a quad is two
// half-covered triangles, and the mean's constants (where its tile lies, its dequantisation) are
// looked up once per tile in the vertex stage. Most tiles decode the mean alone (rank 0, or the
// mean level of detail). The eigen images' constants are looked up per fragment: as varyings
// each would cost every tile's primitive set-up more than it saves the few that have them.

#include "billboard_quad.glsl"
#include "billboard_slots.glsl"

#if defined VERTEX_SHADER

in ivec2 in_origin;    // top-left texel of the tile in the decoded atlas
in ivec2 in_slot;      // (first slot, eigen images to add)
in int in_direction;   // sampled direction index p·d_yaw + y

uniform vec2 u_decoded_size;   // atlas (width, height) in texels

flat out ivec2 v_slot;
flat out int v_direction;
flat out ivec2 v_origin;
flat out vec4 v_mean_scale;    // the mean's dequantisation
flat out vec4 v_mean_offset;
flat out ivec3 v_mean_tile;    // and its tile's address in the atlas pages

void main() {
    v_origin = in_origin;
    v_slot = in_slot;
    v_direction = in_direction;
    v_mean_scale = slot_entry(in_slot.x, 0);
    v_mean_offset = slot_entry(in_slot.x, 1);
    v_mean_tile = tile_address(in_slot.x);
    gl_PointSize = float(u_tile);   // WebGL sizes points here; the desktop's glPointSize is the same
    gl_Position = vec4((vec2(in_origin) + 0.5 * float(u_tile)) / u_decoded_size * 2.0 - 1.0, 0.0, 1.0);
}

#elif defined FRAGMENT_SHADER

flat in ivec2 v_slot;
flat in int v_direction;
flat in ivec2 v_origin;
flat in vec4 v_mean_scale;
flat in vec4 v_mean_offset;
flat in ivec3 v_mean_tile;

out vec4 f_colour;

void main() {
    ivec2 texel = ivec2(gl_FragCoord.xy) - v_origin;   // (col, row) in the tile
    vec4 colour = v_mean_offset + v_mean_scale * texelFetch(u_tiles, ivec3(v_mean_tile.xy + texel, v_mean_tile.z), 0);
    ivec4 dirs = ivec4(v_direction);
    vec4 only = vec4(1.0, 0.0, 0.0, 0.0);
    vec2 centre = vec2(texel) + 0.5;   // u_linear is off
    for (int k = 1; k <= v_slot.y; ++k) {
        int slot = v_slot.x + k;
        colour += coef_weight(slot, dirs, only) * (slot_entry(slot, 1) + slot_entry(slot, 0) * tile_q(slot, centre));
    }
    f_colour = colour;
}

#endif
