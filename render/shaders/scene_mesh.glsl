#version 330 core
// A data_synth scene drawn as its ground-truth meshes (render/scene_mesh.py): flat-shaded
// triangles, one colour per object, lit by a fixed sun plus ambient light. Positions are
// relative to the renderer's origin (float32).

uniform mat4 u_view_proj;   // GL clip from model coordinates

#if defined VERTEX_SHADER

in vec3 in_position;   // model coordinates (m)
in vec3 in_normal;     // unit face normal
in vec4 in_colour;     // object colour (normalised RGBA8)

flat out vec3 v_colour;

const vec3 SUN = vec3(0.40824829, 0.40824829, 0.81649658);   // normalise(1, 1, 2)

void main() {
    float light = 0.45 + 0.55 * max(dot(in_normal, SUN), 0.0);
    v_colour = in_colour.rgb * light;
    gl_Position = u_view_proj * vec4(in_position, 1.0);
}

#elif defined FRAGMENT_SHADER

flat in vec3 v_colour;
out vec4 f_color;

void main() {
    f_color = vec4(v_colour, 1.0);
}

#endif
