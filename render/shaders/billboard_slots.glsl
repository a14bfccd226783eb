// Access to a model's slots on the GPU (render.resources): the slot table, the tile atlas
// and the coefficient pages. A slot is one tile (the mean or an eigen image) of one
// billboard with its dequantisation constants and, for eigen images, one coefficient row
// over the sampled directions.

uniform sampler2DArray u_tiles;    // atlas pages, one layer each: RGBA8 (normalised) or RGBA16F
uniform sampler2DArray u_coefs;    // coefficient pages, one layer each: R8 (normalised), R16F or R32F
uniform sampler2D u_slot_table;    // RGBA32F, 3 texels per slot: tile scale, tile offset, (coef scale, coef offset, k, billboard)
uniform int u_slots_per_row;       // slots per row of u_slot_table (and of the per-frame weight textures)
uniform int u_tiles_per_row;       // atlas layout
uniform int u_tiles_per_page;
uniform int u_d;                   // directions per coefficient row
uniform int u_rows_per_line;       // coefficient rows per texture row
uniform int u_rows_per_page;       // coefficient rows per page
uniform bool u_linear;             // bilinear texels within each tile (else the nearest texel)

// Texel (x, y) of `slot` in a texture with one texel per slot, u_slots_per_row per row.
ivec2 slot_texel(int slot) {
    int row = slot / u_slots_per_row;
    return ivec2(slot - row * u_slots_per_row, row);
}

// Entry `which` of the slot table: 0 tile scale, 1 tile offset, 2 (coef scale, coef offset, k, billboard):
// the slot holds eigen image k (0: the mean) of that billboard.
vec4 slot_entry(int slot, int which) {
    ivec2 t = slot_texel(slot);
    return texelFetch(u_slot_table, ivec2(t.x * 3 + which, t.y), 0);
}

// Where the tile of `slot` lies in the atlas pages: (top-left texel x, y, page).
ivec3 tile_address(int slot) {
    int page = slot / u_tiles_per_page;
    int rest = slot - page * u_tiles_per_page;
    int row = rest / u_tiles_per_row;
    return ivec3(ivec2(rest - row * u_tiles_per_row, row) * u_tile, page);
}
// Quantised value q of the tile in `slot` (dequantised: offset + scale·q) at the continuous tile
// coordinate `texel` (0…t): the nearest texel, or bilinear within the tile (u_linear). The
// decode is linear in q, so filtering q filters the decoded colour.
vec4 tile_q(int slot, vec2 texel) {
    ivec3 tile = tile_address(slot);
    if (u_linear) {
        vec2 size = vec2(textureSize(u_tiles, 0).xy);
        return texture(u_tiles, vec3(tile_point(tile.xy, texel) / size, float(tile.z)));
    }
    return texelFetch(u_tiles, ivec3(tile.xy + tile_texel(texel), tile.z), 0);
}

// Weight w = Σ_c weights_c · (coef_offset + coef_scale·q_c) of the eigen tile in `slot` over
// the sampled directions `dirs` (q_c from the coefficient pages).
float coef_weight(int slot, ivec4 dirs, vec4 weights) {
    int page = slot / u_rows_per_page;
    int rest = slot - page * u_rows_per_page;
    int row = rest / u_rows_per_line;
    int x = (rest - row * u_rows_per_line) * u_d;
    vec4 q;
    q.x = texelFetch(u_coefs, ivec3(x + dirs.x, row, page), 0).r;
    q.y = texelFetch(u_coefs, ivec3(x + dirs.y, row, page), 0).r;
    if (weights.z != 0.0 || weights.w != 0.0) {
        q.z = texelFetch(u_coefs, ivec3(x + dirs.z, row, page), 0).r;
        q.w = texelFetch(u_coefs, ivec3(x + dirs.w, row, page), 0).r;
    } else {
        q.zw = vec2(0.0);
    }
    vec4 c = slot_entry(slot, 2);
    return dot(weights, vec4(c.y) + c.x * q);
}
