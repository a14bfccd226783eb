#version 330 core
// Impostors of far octree nodes (render.impostors): one quad per node, a plane through the
// node's centre facing the eye, textured with the node's image through the camera that made
// it (projective texturing: exact on the plane, perspective-correct). Texels outside the
// image or transparent (alpha < 0.5) are discarded.

#if defined VERTEX_SHADER

uniform mat4 u_projection;   // GL clip from GL eye
uniform mat4 u_view;         // GL eye from model coordinates

in vec3 in_corner0;          // bottom left, bottom right, top left, top right (model coordinates)
in vec3 in_corner1;
in vec3 in_corner2;
in vec3 in_corner3;
in vec4 in_image_x;          // rows 0, 1, 3 of the image's clip from model coordinates
in vec4 in_image_y;
in vec4 in_image_w;
in vec2 in_origin;           // texel origin of the node's image in the atlas
in vec2 in_extent;           // its size in texels

out vec3 v_image;            // image clip (x, y, w)
flat out vec2 v_origin;
flat out vec2 v_extent;

void main() {
    vec3 corner = gl_VertexID == 0 ? in_corner0 : gl_VertexID == 1 ? in_corner1 : gl_VertexID == 2 ? in_corner2 : in_corner3;
    vec4 p = vec4(corner, 1.0);
    v_image = vec3(dot(in_image_x, p), dot(in_image_y, p), dot(in_image_w, p));
    v_origin = in_origin;
    v_extent = in_extent;
    gl_Position = u_projection * (u_view * p);
}

#elif defined FRAGMENT_SHADER

uniform sampler2D u_atlas;    // RGBA8
uniform vec2 u_atlas_texel;   // 1 / atlas size

in vec3 v_image;
flat in vec2 v_origin;
flat in vec2 v_extent;

out vec4 f_color;

void main() {
    vec2 uv = v_image.xy / v_image.z * 0.5 + 0.5;
    if (any(lessThan(uv, vec2(0.0))) || any(greaterThan(uv, vec2(1.0)))) discard;
    vec2 texel = v_origin + clamp(uv * v_extent, vec2(0.5), v_extent - 0.5);
    vec4 colour = texture(u_atlas, texel * u_atlas_texel);   // transparent texels are (0, 0, 0, 0):
    if (colour.a < 0.5) discard;                              // the filtered colour is premultiplied
    f_color = vec4(colour.rgb / colour.a, 1.0);
}

#endif
