#version 330 core
// Clears the tiles of impostor images about to be made (render.impostors) in one draw: a quad
// per tile at the far plane, colour (0, 0, 0, 0), drawn with the depth test always passing.
// (Clearing tile by tile through the scissor costs a pass over the framebuffer each on llvmpipe.)

#include "atlas_rect.glsl"

#if defined VERTEX_SHADER

in vec4 in_rect;            // the tile (x0, y0, x1, y1) in pixels
uniform vec2 u_target_size;

void main() {
    gl_Position = atlas_rect_corner(in_rect.xy, in_rect.zw - in_rect.xy, u_target_size, 1.0);   // window depth 1
}

#elif defined FRAGMENT_SHADER

out vec4 f_colour;

void main() {
    f_colour = vec4(0.0);
}

#endif
