#version 330
// Occlusion culling (render/occlusion.py), two programs in one file:
//
// default   screen-aligned query rectangles: in_pos is already in NDC (x, y, depth); the
//           culler draws them with colour and depth writes off inside occlusion queries.
// BOXES     axis-aligned boxes as flat-coloured, depth-tested solids (BoxRenderer in
//           tests/boxes.py: the occlusion tests' scene). One instance per box; the 36 vertices of
//           the 12 triangles come from gl_VertexID.

#if defined VERTEX_SHADER

#if defined BOXES
uniform mat4 u_view_proj;   // GL clip from model coordinates
in vec3 in_min;             // per instance: box min corner
in vec3 in_max;             // per instance: box max corner
in vec3 in_colour;          // per instance: flat colour in [0, 1]
flat out vec3 v_colour;

// Corner k of the unit cube is (k & 1, (k >> 1) & 1, (k >> 2) & 1).
const int CORNER[36] = int[36](
    0, 4, 6, 0, 6, 2,   // −x
    1, 3, 7, 1, 7, 5,   // +x
    0, 1, 5, 0, 5, 4,   // −y
    2, 6, 7, 2, 7, 3,   // +y
    0, 2, 3, 0, 3, 1,   // −z
    4, 5, 7, 4, 7, 6);  // +z

void main() {
    int k = CORNER[gl_VertexID];
    vec3 t = vec3(float(k & 1), float((k >> 1) & 1), float((k >> 2) & 1));
    gl_Position = u_view_proj * vec4(mix(in_min, in_max, t), 1.0);
    v_colour = in_colour;
}
#else
in vec3 in_pos;             // NDC x, y and depth of a rectangle corner
void main() {
    gl_Position = vec4(in_pos, 1.0);
}
#endif

#elif defined FRAGMENT_SHADER

out vec4 f_colour;
#if defined BOXES
flat in vec3 v_colour;
void main() {
    f_colour = vec4(v_colour, 1.0);
}
#else
void main() {
    f_colour = vec4(1.0);   // masked off: only the depth test and the sample count matter
}
#endif

#endif
