#version 330 core
// The viewer's heads-up display: one RGBA8 texture (text drawn on the CPU) blended over
// the frame in a pixel rectangle at the top-left corner.

uniform vec4 u_rect;         // x0, y0, x1, y1 in NDC
uniform sampler2D u_text;    // row 0 = top of the text image

#if defined VERTEX_SHADER

out vec2 v_uv;

void main() {
    vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1));
    v_uv = vec2(corner.x, 1.0 - corner.y);
    gl_Position = vec4(mix(u_rect.xy, u_rect.zw, corner), 0.0, 1.0);
}

#elif defined FRAGMENT_SHADER

in vec2 v_uv;
out vec4 f_color;

void main() {
    f_color = texture(u_text, v_uv);
}

#endif
