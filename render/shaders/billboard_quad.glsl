// Shared by billboard.glsl (GPU decode) and billboard_cpu.glsl (CPU decode): the quad
// geometry of billboards.geometry, so that both paths rasterise exactly the same pixels.
//
// Every quad is a square centred at its centre, of its own edge `size` (the model's voxel size
// for a billboard and block size for a block of the facade layer, halved each time the quad was
// split: ground near the path, billboards.resolution). A billboard (kind 0) turns
// toward the eye:
//   normal n = (cos φ cos ψ, cos φ sin ψ, sin φ)   (toward the eye)
//   right  r = (−sin ψ, cos ψ, 0)
//   up     u = (0, 0, 1), or n × r for spherical facing (u_spherical)
// where ψ, φ are the yaw and pitch of the vector from the centre to the eye. Blocks of the
// facade layer stay fixed at ψ = base yaw: a facade block (kind 1) and a planar leaf (kind 3,
// billboards.planes) are vertical with the same r and u; a ground block (kind 2) lies flat with
// u = (−cos ψ, −sin ψ, 0), so its rows run
// away from the capture path. Texel (row, col) of a t×t tile lies at
// centre + ((col+½)/t − ½)·s·r + (½ − (row+½)/t)·s·u. A ground block is drawn
// GROUND_OVERLAP of its edge larger on every side, repeating its border texels: on a
// sloping road each block's far edge is a small step above the next block, and seen from
// a car such steps would be cracks of background. The ground is a height field: a ground
// block's corners rise `corner_dz` (x−y−, x+y−, x−y+, x+y+, world order) above its centre,
// bilinear in the world x and y fractions of the block (billboards.geometry.surface_dz), the
// corners neighbours share at one height; every other quad passes zeros.

uniform mat4 u_projection;   // GL clip from GL eye
uniform mat4 u_view;         // GL eye from model coordinates (world − origin)
uniform vec3 u_eye;          // camera centre in model coordinates
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

const int KIND_BILLBOARD = 0;
const int KIND_GROUND = 2;
const float GROUND_OVERLAP = 0.08;

// The angles a quad faces: toward the eye for billboards, the base yaw for layer blocks.
vec2 quad_angles(vec3 centre, float base_yaw, int kind) {
    return kind == KIND_BILLBOARD ? view_angles(centre) : vec2(base_yaw, 0.0);
}

// Corner of the triangle strip for gl_VertexID 0..3: (0,0), (1,0), (0,1), (1,1) along (right, up).
vec2 quad_corner(int vertex_id) {
    return vec2(float(vertex_id & 1), float((vertex_id >> 1) & 1));
}

// Clip-space position of `corner` of the quad of `kind` and edge `size` (m) at `centre` facing
// `angles`, `blocks` blocks tall (a slit of the facade layer: a column of facade blocks,
// billboards.slits; 1 otherwise), its corners `corner_dz` above it (ground; zeros otherwise);
// `texel` receives the continuous tile coordinate (x = col, 0..t; y = row, 0..blocks·t from the top).
vec4 quad_vertex_run(vec3 centre, vec2 angles, int kind, float size, vec2 corner, int blocks, vec4 corner_dz,
                     out vec2 texel) {
    float yaw = angles.x, pitch = angles.y;
    vec3 right = vec3(-sin(yaw), cos(yaw), 0.0);
    vec3 up = vec3(0.0, 0.0, 1.0);
    if (kind == KIND_GROUND) {
        up = vec3(-cos(yaw), -sin(yaw), 0.0);
    } else if (u_spherical && kind == KIND_BILLBOARD) {
        vec3 n = vec3(cos(pitch) * cos(yaw), cos(pitch) * sin(yaw), sin(pitch));
        up = cross(n, right);
    }
    if (kind == KIND_GROUND) corner = (corner - 0.5) * (1.0 + 2.0 * GROUND_OVERLAP) + 0.5;
    vec3 p = centre + (corner.x - 0.5) * size * right + (corner.y - 0.5) * (size * float(blocks)) * up;
    vec2 f = (p.xy - centre.xy) / size + 0.5;
    p.z += mix(mix(corner_dz.x, corner_dz.y, f.x), mix(corner_dz.z, corner_dz.w, f.x), f.y);
    texel = vec2(corner.x, 1.0 - corner.y) * vec2(float(u_tile), float(u_tile * blocks));
#ifdef QUAD_PROJECTION
    return QUAD_PROJECTION * (u_view * vec4(p, 1.0));   // a program's own choice (several views in one draw)
#else
    return u_projection * (u_view * vec4(p, 1.0));
#endif
}

// quad_vertex_run of a single block.
vec4 quad_vertex(vec3 centre, vec2 angles, int kind, float size, vec2 corner, vec4 corner_dz, out vec2 texel) {
    return quad_vertex_run(centre, angles, kind, size, corner, 1, corner_dz, texel);
}

// Integer texel (x = col, y = row) of an interpolated tile coordinate, clamped to the tile.
ivec2 tile_texel(vec2 texel) {
    return clamp(ivec2(floor(texel)), ivec2(0), ivec2(u_tile - 1));
}

// Bilinear filtering that never reads a neighbouring tile: the sample point is kept between
// the tile's outer texel centres, so a tile's edge repeats its border texels.
// Returns the continuous texel coordinate inside a tile whose top-left texel is `origin`.
vec2 tile_point(ivec2 origin, vec2 texel) {
    return vec2(origin) + clamp(texel, vec2(0.5), vec2(float(u_tile) - 0.5));
}
