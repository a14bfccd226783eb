// View-direction interpolation shared by the GPU decode's weights pass: the fractional
// direction index of billboards.decode.direction_index (yaw relative to the base yaw
// wrapped to (−π, π], pitch, each mapped piecewise-linearly over the sampled angles and
// clamped), then the (up to) four neighbouring sampled directions and their bilinear
// weights, like billboards.decode.decode. Needs view_angles from billboard_quad.glsl.

uniform sampler2D u_directions;   // R32F (max(d_yaw, d_pitch), 2): row 0 yaw offsets, row 1 pitches
uniform int u_d_yaw;
uniform int u_d_pitch;
uniform bool u_interpolate;       // false: the nearest sampled direction only

const float PI = 3.14159265358979323846;

float table(int row, int i) {
    return texelFetch(u_directions, ivec2(i, row), 0).r;
}

// np.interp(x, table[row, :count], arange(count)): fractional index, clamped to [0, count − 1].
float table_index(int row, int count, float x) {
    if (x <= table(row, 0)) return 0.0;
    if (x >= table(row, count - 1)) return float(count - 1);
    int lo = 0, hi = count - 1;   // table[lo] < x < table[hi]
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        if (table(row, mid) <= x) lo = mid; else hi = mid;
    }
    float a = table(row, lo), b = table(row, hi);
    return float(lo) + (x - a) / (b - a);
}

// billboards.decode._bracket: neighbours (i0, i1) and the weight of i1.
void bracket(float index, int count, out int i0, out int i1, out float f) {
    float x = clamp(index, 0.0, float(count - 1));
    i0 = min(int(floor(x)), max(count - 2, 0));
    i1 = min(i0 + 1, count - 1);
    f = x - float(i0);
}

// Direction indices p·d_yaw + y of the 4 samples around the view from the eye to `centre`
// and their weights (nearest sample only, weight 1, without u_interpolate).
void direction_weights(vec3 centre, float base_yaw, out ivec4 dirs, out vec4 weights) {
    vec2 angles = view_angles(centre);
    float yaw = angles.x - base_yaw;
    yaw = PI - mod(PI - yaw, 2.0 * PI);   // wrapped to (−π, π]
    float yi = table_index(0, u_d_yaw, yaw);
    float pi = table_index(1, u_d_pitch, angles.y);
    int y0, y1, p0, p1;
    float fy, fp;
    bracket(yi, u_d_yaw, y0, y1, fy);
    bracket(pi, u_d_pitch, p0, p1, fp);
    if (!u_interpolate) {
        fy = fy < 0.5 ? 0.0 : 1.0;
        fp = fp < 0.5 ? 0.0 : 1.0;
    }
    dirs = ivec4(p0 * u_d_yaw + y0, p0 * u_d_yaw + y1, p1 * u_d_yaw + y0, p1 * u_d_yaw + y1);
    weights = vec4((1.0 - fy) * (1.0 - fp), fy * (1.0 - fp), (1.0 - fy) * fp, fy * fp);
}
