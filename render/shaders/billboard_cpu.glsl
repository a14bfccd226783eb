#version 330 core
// Billboards whose textures were decoded on the CPU this frame (the paper's baseline):
// the same instanced quads as billboard.glsl, textured from a per-frame RGBA8 atlas
// with one tile per drawn billboard; alpha < 0.5 is discarded.

#include "billboard_quad.glsl"

#if defined VERTEX_SHADER

in vec3 in_centre;     // model coordinates (m)
in float in_base_yaw;  // world yaw (radians) a layer block faces
in int in_tile;        // tile index in the frame atlas
in int in_kind;        // 0 billboard, 1 facade block, 2 ground block

out vec2 v_texel;
flat out int v_tile;

void main() {
    v_tile = in_tile;
    gl_Position = quad_vertex(in_centre, quad_angles(in_centre, in_base_yaw, in_kind), in_kind,
                              quad_corner(gl_VertexID), v_texel);
}

#elif defined FRAGMENT_SHADER

uniform sampler2DArray u_frame_tiles;   // RGBA8 (normalised), one layer per page
uniform int u_tiles_per_row;
uniform int u_tiles_per_page;

in vec2 v_texel;
flat in int v_tile;

out vec4 f_color;

void main() {
    ivec2 texel = tile_texel(v_texel);
    int page = v_tile / u_tiles_per_page;
    int rest = v_tile - page * u_tiles_per_page;
    int row = rest / u_tiles_per_row;
    int col = rest - row * u_tiles_per_row;
    vec4 colour = texelFetch(u_frame_tiles, ivec3(col * u_tile + texel.x, row * u_tile + texel.y, page), 0);
    if (colour.a < 0.5) discard;
    f_color = vec4(colour.rgb, 1.0);
}

#endif
