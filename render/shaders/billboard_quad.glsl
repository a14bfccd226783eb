// Shared by billboard.glsl (GPU decode) and billboard_cpu.glsl (CPU decode): the quad
// geometry of billboards.geometry, so that both paths rasterise exactly the same pixels.
//
// A billboard is a square of edge u_size centred at its centre, turned toward the eye:
//   normal n = (cos φ cos ψ, cos φ sin ψ, sin φ)   (toward the eye)
//   right  r = (−sin ψ, cos ψ, 0)
//   up     u = (0, 0, 1), or n × r for spherical facing (u_spherical)
// where ψ, φ are the yaw and pitch of the vector from the centre to the eye. Texel
// (row, col) of a t×t tile lies at centre + ((col+½)/t − ½)·s·r + (½ − (row+½)/t)·s·u.

uniform mat4 u_projection;   // GL clip from GL eye
uniform mat4 u_view;         // GL eye from model coordinates (world − origin)
uniform vec3 u_eye;          // camera centre in model coordinates
uniform float u_size;        // billboard edge (m)
uniform bool u_spherical;    // quads also pitch toward the eye
uniform int u_tile;          // texels per tile side t

// Yaw ψ and pitch φ (radians) of the direction from `centre` toward the eye.
// Straight above or below the centre ψ is 0 (numpy's atan2(0, 0)).
vec2 view_angles(vec3 centre) {
    vec3 v = u_eye - centre;
    float h = length(v.xy);
    float yaw = h > 0.0 ? atan(v.y, v.x) : 0.0;
    float pitch = (h > 0.0 || v.z != 0.0) ? atan(v.z, h) : 0.0;
    return vec2(yaw, pitch);
}

// Corner of the triangle strip for gl_VertexID 0..3: (0,0), (1,0), (0,1), (1,1) along (right, up).
vec2 quad_corner(int vertex_id) {
    return vec2(float(vertex_id & 1), float((vertex_id >> 1) & 1));
}

// Clip-space position of `corner` of the quad at `centre` facing `angles`;
// `texel` receives the continuous tile coordinate (x = col, y = row, 0..t; row 0 at the top).
vec4 quad_vertex(vec3 centre, vec2 angles, vec2 corner, out vec2 texel) {
    float yaw = angles.x, pitch = angles.y;
    vec3 right = vec3(-sin(yaw), cos(yaw), 0.0);
    vec3 up = vec3(0.0, 0.0, 1.0);
    if (u_spherical) {
        vec3 n = vec3(cos(pitch) * cos(yaw), cos(pitch) * sin(yaw), sin(pitch));
        up = cross(n, right);
    }
    vec3 p = centre + (corner.x - 0.5) * u_size * right + (corner.y - 0.5) * u_size * up;
    texel = vec2(corner.x, 1.0 - corner.y) * float(u_tile);
    return u_projection * (u_view * vec4(p, 1.0));
}

// Integer texel (x = col, y = row) of an interpolated tile coordinate, clamped to the tile.
ivec2 tile_texel(vec2 texel) {
    return clamp(ivec2(floor(texel)), ivec2(0), ivec2(u_tile - 1));
}
