#version 330 core
// Copies impostor images from the studio where they were drawn (with depth) into their tiles of
// a colour-only atlas (render.impostors.ImpostorStudio): a quad per image over its rectangle of
// the atlas, each texel fetched unfiltered from the same place of its studio tile.

#include "atlas_rect.glsl"

#if defined VERTEX_SHADER

in vec2 in_source;          // the image's origin in the studio (pixels)
in vec2 in_target;          // its origin in the atlas
in vec2 in_extent;          // its size
uniform vec2 u_target_size;

flat out ivec2 v_shift;     // studio texel = atlas texel + shift

void main() {
    v_shift = ivec2(in_source - in_target);
    gl_Position = atlas_rect_corner(in_target, in_extent, u_target_size, 0.0);
}

#elif defined FRAGMENT_SHADER

uniform sampler2D u_studio;

flat in ivec2 v_shift;
out vec4 f_colour;

void main() {
    f_colour = texelFetch(u_studio, ivec2(gl_FragCoord.xy) + v_shift, 0);
}

#endif
