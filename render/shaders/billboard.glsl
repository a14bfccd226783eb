#version 330 core
// Billboards with eigen-texture decode on the GPU: one instanced draw of triangle strips
// (4 vertices per billboard, corners from gl_VertexID; no vertex buffer, only instances).
//
// Per instance: centre (model coordinates), base yaw, first slot and rank.
// Vertex stage: turns the quad toward the eye and finds the fractional view-direction
// index like billboards.model.direction_index (yaw relative to the base yaw wrapped to
// (−π, π], pitch, each mapped piecewise-linearly over the sampled angles and clamped),
// then the (up to) four neighbouring sampled directions and their bilinear weights,
// like billboards.model.decode.
// Fragment stage: texel = offset + scale·q for the mean and the first `rank` eigen
// tiles (q = texelFetch of a normalised RGBA8 or an RGBA16F array texture), weights
// w_k = Σ_c weight_c · (coef_offset + coef_scale·q_c) from the coefficient pages,
// colour = clamp(mean + Σ_k w_k·V_k, 0, 1); alpha < 0.5 is discarded. Nearest texel
// (texelFetch), no filtering, so it matches the CPU decode texel for texel.

#include "billboard_quad.glsl"

uniform sampler2D u_directions;   // R32F (max(d_yaw, d_pitch), 2): row 0 yaw offsets, row 1 pitches
uniform int u_d_yaw;
uniform int u_d_pitch;

#if defined VERTEX_SHADER

in vec3 in_centre;       // model coordinates (m)
in float in_base_yaw;    // radians
in ivec2 in_slot;        // (first slot, rank)

out vec2 v_texel;
flat out ivec2 v_slot;
flat out ivec4 v_dirs;   // direction indices p·d_yaw + y of the 4 bracketing samples
flat out vec4 v_dir_w;   // their weights

const float PI = 3.14159265358979323846;

float table(int row, int i) {
    return texelFetch(u_directions, ivec2(i, row), 0).r;
}

// np.interp(x, table[row, :count], arange(count)): fractional index, clamped to [0, count − 1].
float table_index(int row, int count, float x) {
    if (x <= table(row, 0)) return 0.0;
    if (x >= table(row, count - 1)) return float(count - 1);
    int lo = 0, hi = count - 1;   // table[lo] < x < table[hi]
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        if (table(row, mid) <= x) lo = mid; else hi = mid;
    }
    float a = table(row, lo), b = table(row, hi);
    return float(lo) + (x - a) / (b - a);
}

// billboards.model._bracket: neighbours (i0, i1) and the weight of i1.
void bracket(float index, int count, out int i0, out int i1, out float f) {
    float x = clamp(index, 0.0, float(count - 1));
    i0 = min(int(floor(x)), max(count - 2, 0));
    i1 = min(i0 + 1, count - 1);
    f = x - float(i0);
}

void main() {
    vec2 angles = view_angles(in_centre);
    float yaw = angles.x - in_base_yaw;
    yaw = PI - mod(PI - yaw, 2.0 * PI);   // wrapped to (−π, π]
    float yi = table_index(0, u_d_yaw, yaw);
    float pi = table_index(1, u_d_pitch, angles.y);
    int y0, y1, p0, p1;
    float fy, fp;
    bracket(yi, u_d_yaw, y0, y1, fy);
    bracket(pi, u_d_pitch, p0, p1, fp);
    v_dirs = ivec4(p0 * u_d_yaw + y0, p0 * u_d_yaw + y1, p1 * u_d_yaw + y0, p1 * u_d_yaw + y1);
    v_dir_w = vec4((1.0 - fy) * (1.0 - fp), fy * (1.0 - fp), (1.0 - fy) * fp, fy * fp);
    v_slot = in_slot;
    gl_Position = quad_vertex(in_centre, angles, quad_corner(gl_VertexID), v_texel);
}

#elif defined FRAGMENT_SHADER

uniform sampler2DArray u_tiles;    // atlas pages, one layer each: RGBA8 (normalised) or RGBA16F
uniform sampler2DArray u_coefs;    // coefficient pages, one layer each: R8 (normalised), R16F or R32F
uniform sampler2D u_slot_table;    // RGBA32F, 3 texels per slot: tile scale, tile offset, (coef scale, coef offset, 0, 0)
uniform int u_slots_per_row;       // slots per row of u_slot_table
uniform int u_tiles_per_row;       // atlas layout
uniform int u_tiles_per_page;
uniform int u_d;                   // directions per coefficient row
uniform int u_rows_per_line;       // coefficient rows per texture row
uniform int u_rows_per_page;       // coefficient rows per page

in vec2 v_texel;
flat in ivec2 v_slot;
flat in ivec4 v_dirs;
flat in vec4 v_dir_w;

out vec4 f_color;

vec4 slot_entry(int slot, int which) {
    int row = slot / u_slots_per_row;
    return texelFetch(u_slot_table, ivec2((slot - row * u_slots_per_row) * 3 + which, row), 0);
}

// Dequantised texel of the tile in `slot`.
vec4 tile_value(int slot, ivec2 texel) {
    int page = slot / u_tiles_per_page;
    int rest = slot - page * u_tiles_per_page;
    int row = rest / u_tiles_per_row;
    int col = rest - row * u_tiles_per_row;
    vec4 q = texelFetch(u_tiles, ivec3(col * u_tile + texel.x, row * u_tile + texel.y, page), 0);
    return slot_entry(slot, 1) + slot_entry(slot, 0) * q;
}

// Quantised coefficients q of `slot` at the four bracketing directions.
vec4 coef_q(int slot) {
    int page = slot / u_rows_per_page;
    int rest = slot - page * u_rows_per_page;
    int row = rest / u_rows_per_line;
    int x = (rest - row * u_rows_per_line) * u_d;
    vec4 q;
    q.x = texelFetch(u_coefs, ivec3(x + v_dirs.x, row, page), 0).r;
    q.y = texelFetch(u_coefs, ivec3(x + v_dirs.y, row, page), 0).r;
    if (v_dir_w.z != 0.0 || v_dir_w.w != 0.0) {
        q.z = texelFetch(u_coefs, ivec3(x + v_dirs.z, row, page), 0).r;
        q.w = texelFetch(u_coefs, ivec3(x + v_dirs.w, row, page), 0).r;
    } else {
        q.zw = vec2(0.0);
    }
    return q;
}

void main() {
    ivec2 texel = tile_texel(v_texel);
    int first = v_slot.x;
    vec4 colour = tile_value(first, texel);
    for (int k = 1; k <= v_slot.y; ++k) {
        int slot = first + k;
        vec4 c = slot_entry(slot, 2);
        float w = dot(v_dir_w, vec4(c.y) + c.x * coef_q(slot));
        colour += w * tile_value(slot, texel);
    }
    colour = clamp(colour, 0.0, 1.0);
    if (colour.a < 0.5) discard;
    f_color = vec4(colour.rgb, 1.0);
}

#endif
