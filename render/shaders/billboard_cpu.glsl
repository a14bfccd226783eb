#version 330 core
// Billboards whose textures were decoded on the CPU this frame (the paper's baseline):
// the same instanced quads as billboard.glsl, textured from a per-frame RGBA8 atlas
// with one tile per drawn billboard; alpha < 0.5 is discarded.

#include "billboard_quad.glsl"

#if defined VERTEX_SHADER

in vec3 in_centre;     // model coordinates (m)
in float in_base_yaw;  // world yaw (radians) a layer block faces
in int in_tile;        // tile index in the frame atlas
in int in_kind;        // 0 billboard, 1 facade block, 2 ground block, 3 plane (a planar leaf)
in float in_size;      // edge of the quad (m)
in vec4 in_corner_dz;  // a ground block's corners above its centre (m; zeros otherwise)

out vec2 v_texel;
flat out int v_tile;

void main() {
    v_tile = in_tile;
    gl_Position = quad_vertex(in_centre, quad_angles(in_centre, in_base_yaw, in_kind), in_kind, in_size,
                              quad_corner(gl_VertexID), in_corner_dz, v_texel);
}

#elif defined FRAGMENT_SHADER

uniform sampler2DArray u_frame_tiles;   // RGBA8 (normalised), one layer per page
uniform int u_tiles_per_row;
uniform int u_tiles_per_page;
uniform bool u_linear;   // bilinear texels within each tile (else the nearest texel)

in vec2 v_texel;
flat in int v_tile;

out vec4 f_color;

void main() {
    int page = v_tile / u_tiles_per_page;
    int rest = v_tile - page * u_tiles_per_page;
    int row = rest / u_tiles_per_row;
    int col = rest - row * u_tiles_per_row;
    ivec2 origin = ivec2(col, row) * u_tile;
    vec4 colour;
    if (u_linear) {
        // Bilinear by hand from four fetches, weights from the tile coordinate alone: the same
        // wherever the tile lies in the frame atlas (that changes with the billboards drawn),
        // so culling never changes a pixel.
        vec2 p = tile_point(ivec2(0), v_texel) - 0.5;
        ivec2 k = ivec2(floor(p));
        vec2 f = p - vec2(k);
        ivec2 i = origin + k;
        ivec2 hi = origin + min(k + 1, ivec2(u_tile - 1));
        vec4 a = texelFetch(u_frame_tiles, ivec3(i, page), 0);
        vec4 b = texelFetch(u_frame_tiles, ivec3(hi.x, i.y, page), 0);
        vec4 c = texelFetch(u_frame_tiles, ivec3(i.x, hi.y, page), 0);
        vec4 d = texelFetch(u_frame_tiles, ivec3(hi, page), 0);
        colour = mix(mix(a, b, f.x), mix(c, d, f.x), f.y);
    } else {
        colour = texelFetch(u_frame_tiles, ivec3(origin + tile_texel(v_texel), page), 0);
    }
    if (colour.a < 0.5) discard;
    f_color = vec4(colour.rgb, 1.0);
}

#endif
