#version 330 core
// The sky behind the model: a full-screen triangle drawn first (depth test off, so it
// writes no depth), each pixel coloured by the world elevation of its view ray.
// The sky is a row of bins (billboards.sky: mean colour per equal band of elevation
// between u_elevation.x and u_elevation.y radians); the colour is linear between bin
// centres and the end bins' colours beyond them, like numpy's interp
// (billboards.sky.Sky.colour). Bins are fetched by texelFetch and mixed here, so the
// result does not depend on the driver's filtering of float textures.

uniform mat3 u_world_from_pixel;   // R·K⁻¹: OpenCV pixel (u, v, 1) → world ray direction
uniform float u_height;            // framebuffer height (pixels), for OpenCV's top-down rows
uniform vec2 u_elevation;          // elevation range of the bins (radians): low, high
uniform int u_bins;                // number of bins
uniform sampler2D u_sky;           // RGBA32F, u_bins × 1: bin colours

#if defined VERTEX_SHADER

void main() {   // one triangle covering the viewport
    vec2 corner = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(corner * 2.0 - 1.0, 1.0, 1.0);
}

#elif defined FRAGMENT_SHADER

out vec4 f_color;

void main() {
    // gl_FragCoord is the pixel centre (i + ½) counted from the bottom; OpenCV centres are integers from the top
    vec2 pixel = vec2(gl_FragCoord.x - 0.5, u_height - gl_FragCoord.y - 0.5);
    vec3 ray = u_world_from_pixel * vec3(pixel, 1.0);
    float elevation = atan(ray.z, length(ray.xy));
    float x = (elevation - u_elevation.x) / (u_elevation.y - u_elevation.x) * float(u_bins) - 0.5;
    x = clamp(x, 0.0, float(u_bins - 1));
    int i0 = int(floor(x));
    int i1 = min(i0 + 1, u_bins - 1);
    vec3 c0 = texelFetch(u_sky, ivec2(i0, 0), 0).rgb;
    vec3 c1 = texelFetch(u_sky, ivec2(i1, 0), 0).rgb;
    f_color = vec4(mix(c0, c1, x - float(i0)), 1.0);
}

#endif
