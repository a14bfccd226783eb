#version 330 core
// Weights pass of the GPU decode, run once per view before billboard.glsl draws. The decode
//   colour = clamp(mean + Σ_k w_k·V_k, 0, 1),  tile texels dequantised as offset + scale·q,
// is, for a given view, colour = C + Σ_{k=0..r} T_k·q_k with per-slot constants
//   T_k = w_k·scale_k (w_0 = 1 for the mean)  and  C = Σ_k w_k·offset_k.
// This pass computes them once per slot instead of once per fragment: a full-screen
// triangle over two RGBA32F targets with one texel per slot (the slot table's layout),
// T_k in the first, C at each billboard's first slot in the second. A fragment pass,
// not a vertex pass, because llvmpipe runs vertex shaders on one thread only.

#include "billboard_quad.glsl"
#include "billboard_slots.glsl"
#include "billboard_directions.glsl"

uniform sampler2D u_instance_table;   // RGBA32F, one texel per billboard: centre (model coordinates), base yaw
uniform int u_num_slots;

#if defined VERTEX_SHADER

void main() {   // one triangle covering the viewport
    vec2 corner = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(corner * 2.0 - 1.0, 0.0, 1.0);
}

#elif defined FRAGMENT_SHADER

layout(location = 0) out vec4 f_term;
layout(location = 1) out vec4 f_const;

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    int slot = p.y * u_slots_per_row + p.x;
    f_term = vec4(0.0);
    f_const = vec4(0.0);
    if (slot >= u_num_slots) return;
    vec4 owner = slot_entry(slot, 2);   // (coef scale, coef offset, k, billboard)
    int k = int(owner.z);
    vec4 instance = texelFetch(u_instance_table, slot_texel(int(owner.w)), 0);
    ivec4 dirs;
    vec4 weights;
    direction_weights(instance.xyz, instance.w, dirs, weights);
    f_term = (k == 0 ? 1.0 : coef_weight(slot, dirs, weights)) * slot_entry(slot, 0);
    if (k == 0) {   // the billboard's eigen slots follow, numbered k = 1, 2, …; the next mean has k = 0
        f_const = slot_entry(slot, 1);
        for (int j = 1; slot + j < u_num_slots && int(slot_entry(slot + j, 2).z) == j; ++j) {
            f_const += coef_weight(slot + j, dirs, weights) * slot_entry(slot + j, 1);
        }
    }
}

#endif
