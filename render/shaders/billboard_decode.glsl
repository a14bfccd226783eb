#version 330 core
// Decode pass of the GPU decode: tiles of billboards at single sampled directions, written
// into the decoded atlas that billboard.glsl draws from. One instance per tile to decode, a
// t×t-pixel quad at its place in the atlas; each fragment is one texel:
//   colour = mean + Σ_{k=1..r} w_k·V_k,   tiles dequantised as offset + scale·q,
//   w_k = coef_offset + coef_scale·q_k(direction),
// unclamped (the blend of directions clamps), r the billboard's rank or less (level of detail).

#include "billboard_quad.glsl"
#include "billboard_slots.glsl"
#include "atlas_rect.glsl"

#if defined VERTEX_SHADER

in ivec2 in_origin;    // top-left texel of the tile in the decoded atlas
in ivec2 in_slot;      // (first slot, eigen images to add)
in int in_direction;   // sampled direction index p·d_yaw + y

uniform vec2 u_decoded_size;   // atlas (width, height) in texels

flat out ivec2 v_slot;
flat out int v_direction;
flat out ivec2 v_origin;

void main() {
    v_origin = in_origin;
    v_slot = in_slot;
    v_direction = in_direction;
    gl_Position = atlas_rect_corner(vec2(in_origin), vec2(u_tile), u_decoded_size, 0.0);
}

#elif defined FRAGMENT_SHADER

flat in ivec2 v_slot;
flat in int v_direction;
flat in ivec2 v_origin;

out vec4 f_colour;

void main() {
    vec2 texel = vec2(ivec2(gl_FragCoord.xy) - v_origin) + 0.5;   // (col, row) centre; u_linear is off
    int first = v_slot.x;
    vec4 colour = slot_entry(first, 1) + slot_entry(first, 0) * tile_q(first, texel);
    ivec4 dirs = ivec4(v_direction);
    vec4 only = vec4(1.0, 0.0, 0.0, 0.0);
    for (int k = 1; k <= v_slot.y; ++k) {
        int slot = first + k;
        colour += coef_weight(slot, dirs, only) * (slot_entry(slot, 1) + slot_entry(slot, 0) * tile_q(slot, texel));
    }
    f_colour = colour;
}

#endif
