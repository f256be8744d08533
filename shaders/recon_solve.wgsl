// Guided filter, step 2 of 4: the vertical half of every window moment, then the window's
// linear model (depth.rs `guided_filter`, per window k). The column sums add offsets
// d = −r ..= r in ascending order with each moment's y weight; then, over the n_k valid pixels
// of the window, with the guide g = (R, G, B, dx/r, dy/r):
//   μ = mean g, p̄ = mean p, Σ = mean g gᵀ − μ μᵀ + diag(ε, ε, ε, ε_pos, ε_pos),
//   a_k = Σ⁻¹ (mean g p − μ p̄) by unpivoted Cholesky (zero when a pivot is not positive),
//   b_k = p̄ − a_k · μ.
// coefficients[i] = (n_k, n_k a_k.R, n_k a_k.G, n_k a_k.B),
// coefficients[n + i] = (n_k a_k.x, n_k a_k.y, n_k b_k, 0); all zero but n_k where n_k < 1.

@group(0) @binding(1) var<storage, read> kernel: array<f32>;
@group(0) @binding(2) var<storage, read> rows: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> coefficients: array<vec4<f32>>;

// The guide's five components: the colour (R, G, B) and the offset (x, y).
struct Guide5 {
    c: vec3<f32>,
    o: vec2<f32>,
}

// depth.rs `solve_spd` for the 5 × 5 symmetric system whose lower triangle is `s` (row-major:
// s00; s10 s11; s20 s21 s22; s30 …; s40 … s44): m = L Lᵀ, then L y = rhs, Lᵀ x = y. Written out
// term by term, every dot product adding its terms in ascending index order as the CPU's
// iterator sums do: llvmpipe keeps a looped version's arrays in memory and ran it at half the
// speed. `ok` is false where a pivot is not positive or the solution is not finite.
struct Solution {
    x: Guide5,
    ok: bool,
}

fn pivot_ok(p: f32) -> bool {
    return is_finite(p) && p > 0.0;
}

fn solve_spd(s: array<f32, 15>, rhs: Guide5) -> Solution {
    let p0 = s[0];
    let l00 = sqrt(p0);
    let l10 = s[1] / l00;
    let l20 = s[3] / l00;
    let l30 = s[6] / l00;
    let l40 = s[10] / l00;
    let p1 = s[2] - l10 * l10;
    let l11 = sqrt(p1);
    let l21 = (s[4] - l20 * l10) / l11;
    let l31 = (s[7] - l30 * l10) / l11;
    let l41 = (s[11] - l40 * l10) / l11;
    let p2 = s[5] - (l20 * l20 + l21 * l21);
    let l22 = sqrt(p2);
    let l32 = (s[8] - (l30 * l20 + l31 * l21)) / l22;
    let l42 = (s[12] - (l40 * l20 + l41 * l21)) / l22;
    let p3 = s[9] - ((l30 * l30 + l31 * l31) + l32 * l32);
    let l33 = sqrt(p3);
    let l43 = (s[13] - ((l40 * l30 + l41 * l31) + l42 * l32)) / l33;
    let p4 = s[14] - (((l40 * l40 + l41 * l41) + l42 * l42) + l43 * l43);
    let l44 = sqrt(p4);

    let y0 = rhs.c.x / l00;
    let y1 = (rhs.c.y - l10 * y0) / l11;
    let y2 = (rhs.c.z - (l20 * y0 + l21 * y1)) / l22;
    let y3 = (rhs.o.x - ((l30 * y0 + l31 * y1) + l32 * y2)) / l33;
    let y4 = (rhs.o.y - (((l40 * y0 + l41 * y1) + l42 * y2) + l43 * y3)) / l44;

    let x4 = y4 / l44;
    let x3 = (y3 - l43 * x4) / l33;
    let x2 = (y2 - (l32 * x3 + l42 * x4)) / l22;
    let x1 = (y1 - ((l21 * x2 + l31 * x3) + l41 * x4)) / l11;
    let x0 = (y0 - (((l10 * x1 + l20 * x2) + l30 * x3) + l40 * x4)) / l00;

    var out: Solution;
    out.x = Guide5(vec3<f32>(x0, x1, x2), vec2<f32>(x3, x4));
    out.ok = pivot_ok(p0) && pivot_ok(p1) && pivot_ok(p2) && pivot_ok(p3) && pivot_ok(p4)
        && is_finite(x0) && is_finite(x1) && is_finite(x2) && is_finite(x3) && is_finite(x4);
    return out;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = recon.dims.x;
    let h = recon.dims.y;
    if id.x >= w || id.y >= h {
        return;
    }
    let r = i32(recon.dims.z);
    let taps = u32(2 * r + 1);
    let n = w * h;
    // Window sums: mask moments, p moments, colour moments.
    var m_1 = 0.0;
    var m_x = 0.0;
    var m_y = 0.0;
    var m_xx = 0.0;
    var m_yy = 0.0;
    var m_xy = 0.0;
    var p_1 = 0.0;
    var p_x = 0.0;
    var p_y = 0.0;
    var c_1 = vec3<f32>(0.0);
    var c_x = vec3<f32>(0.0);
    var c_y = vec3<f32>(0.0);
    var c_p = vec3<f32>(0.0);
    var c_c0 = vec2<f32>(0.0);
    var c_c1 = vec4<f32>(0.0);
    for (var d = -r; d <= r; d++) {
        let y = i32(id.y) + d;
        if y < 0 || y >= i32(h) {
            continue;
        }
        let i = u32(y) * w + id.x;
        let kd = kernel[u32(d + r)];
        let kd2 = kernel[taps + u32(d + r)];
        let s0 = rows[i];
        let s1 = rows[n + i];
        let s2 = rows[2u * n + i];
        let s3 = rows[3u * n + i];
        let s4 = rows[4u * n + i];
        m_1 += s0.x;
        m_x += s0.y;
        m_y += kd * s0.x;
        m_xx += s0.z;
        m_yy += kd2 * s0.x;
        m_xy += kd * s0.y;
        p_1 += s0.w;
        p_x += s1.x;
        p_y += kd * s0.w;
        c_1 += s1.yzw;
        c_x += s2.xyz;
        c_y += kd * s1.yzw;
        c_p += vec3<f32>(s2.w, s3.x, s3.y);
        c_c0 += s3.zw;
        c_c1 += s4;
    }
    let i = id.y * w + id.x;
    let n_k = m_1;
    if n_k < 1.0 {
        coefficients[i] = vec4<f32>(n_k, 0.0, 0.0, 0.0);
        coefficients[n + i] = vec4<f32>(0.0);
        return;
    }
    let mu = Guide5(c_1 / n_k, vec2<f32>(m_x, m_y) / n_k);
    let p_mean = p_1 / n_k;
    let mean_gp = Guide5(c_p / n_k, vec2<f32>(p_x, p_y) / n_k);
    // mean g gᵀ − μ μᵀ + E, lower triangle: the colour pairs (0,0) (1,0) (1,1) (2,0) (2,1)
    // (2,2) are c_c0.xy, c_c1.xyzw in the order (0,0) (0,1) (0,2) (1,1) (1,2) (2,2).
    let eps = recon.settings.x;
    let eps_position = recon.settings.y;
    let cx = c_x / n_k;
    let cy = c_y / n_k;
    let system = array<f32, 15>(
        (c_c0.x / n_k - mu.c.x * mu.c.x) + eps,
        c_c0.y / n_k - mu.c.y * mu.c.x,
        (c_c1.y / n_k - mu.c.y * mu.c.y) + eps,
        c_c1.x / n_k - mu.c.z * mu.c.x,
        c_c1.z / n_k - mu.c.z * mu.c.y,
        (c_c1.w / n_k - mu.c.z * mu.c.z) + eps,
        cx.x - mu.o.x * mu.c.x,
        cx.y - mu.o.x * mu.c.y,
        cx.z - mu.o.x * mu.c.z,
        (m_xx / n_k - mu.o.x * mu.o.x) + eps_position,
        cy.x - mu.o.y * mu.c.x,
        cy.y - mu.o.y * mu.c.y,
        cy.z - mu.o.y * mu.c.z,
        m_xy / n_k - mu.o.y * mu.o.x,
        (m_yy / n_k - mu.o.y * mu.o.y) + eps_position,
    );
    let rhs = Guide5(mean_gp.c - mu.c * p_mean, mean_gp.o - mu.o * p_mean);
    let solution = solve_spd(system, rhs);
    var a_k = Guide5(vec3<f32>(0.0), vec2<f32>(0.0));
    if solution.ok {
        a_k = solution.x;
    }
    let a_mu = (((a_k.c.x * mu.c.x + a_k.c.y * mu.c.y) + a_k.c.z * mu.c.z) + a_k.o.x * mu.o.x)
        + a_k.o.y * mu.o.y;
    let b_k = p_mean - a_mu;
    coefficients[i] = vec4<f32>(n_k, n_k * a_k.c);
    coefficients[n + i] = vec4<f32>(n_k * a_k.o, n_k * b_k, 0.0);
}
