// Shared by the passes that write rectangles of an atlas (pre-blend, impostor clear): the
// clip-space corner gl_VertexID (0..3 of a triangle strip) of the pixel rectangle at `origin`
// (bottom-left, pixels) of `extent` pixels in a target of `target_size` pixels, at NDC depth `z`.
#if defined VERTEX_SHADER
vec4 atlas_rect_corner(vec2 origin, vec2 extent, vec2 target_size, float z) {
    vec2 corner = vec2(float(gl_VertexID & 1), float((gl_VertexID >> 1) & 1));
    return vec4((origin + corner * extent) / target_size * 2.0 - 1.0, z, 1.0);
}
#endif
