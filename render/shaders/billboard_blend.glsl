#version 330 core
// Pre-blend pass of the GPU decode: for quads that are large on screen, the decoded tiles of
// the direction bracket are blended once per texel with this view's weights into the view
// atlas, so that their fragments fetch one texel instead of one per direction (render.gpu_decode).
// One instance per run (a slit's blocks lie one below the other in both atlases): a quad of
// t × blocks·t pixels at its place in the view atlas. The view atlas is RGBA8: the blend is
// clamped as it is stored, as the CPU decode clamps before filtering.

#include "atlas_rect.glsl"

#if defined VERTEX_SHADER

in ivec2 in_source;    // top-left texel of the block's storage slot 0 in the decoded atlas
in ivec2 in_target;    // top-left texel of its tile in the view atlas
in int in_blocks;      // blocks in the run
in vec4 in_weights;    // weight of each storage slot

uniform int u_tile;
uniform vec2 u_target_size;

flat out ivec2 v_source;
flat out ivec2 v_target;
flat out vec4 v_weights;

void main() {
    v_source = in_source;
    v_target = in_target;
    v_weights = in_weights;
    gl_Position = atlas_rect_corner(vec2(in_target), vec2(u_tile, u_tile * in_blocks), u_target_size, 0.0);
}

#elif defined FRAGMENT_SHADER

uniform sampler2D u_decoded;   // RGBA16F decoded atlas
uniform int u_tile;

flat in ivec2 v_source;
flat in ivec2 v_target;
flat in vec4 v_weights;

out vec4 f_colour;

void main() {
    ivec2 texel = ivec2(gl_FragCoord.xy) - v_target;
    ivec2 p = v_source + texel;   // branch-free (see billboard.glsl)
    vec4 colour = v_weights.x * texelFetch(u_decoded, p, 0) + v_weights.y * texelFetch(u_decoded, p + ivec2(u_tile, 0), 0);
#if STORAGE_SLOTS == 4
    colour += v_weights.z * texelFetch(u_decoded, p + ivec2(2 * u_tile, 0), 0)
            + v_weights.w * texelFetch(u_decoded, p + ivec2(3 * u_tile, 0), 0);
#endif
    f_colour = colour;
}

#endif
