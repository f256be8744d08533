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

const GUIDE: u32 = 5u;

struct Solution {
    x: array<f32, 5>,
    ok: bool,
}

// depth.rs `solve_spd`: m = L Lᵀ with L in the lower triangle, then L y = rhs, Lᵀ x = y. Every
// dot product adds its terms in ascending index order, as the CPU's iterator sums do.
fn solve_spd(system: array<array<f32, 5>, 5>, rhs: array<f32, 5>) -> Solution {
    var m = system;
    var out: Solution;
    out.ok = false;
    for (var j = 0u; j < GUIDE; j++) {
        var dot_jj = 0.0;
        for (var t = 0u; t < j; t++) {
            dot_jj += m[j][t] * m[j][t];
        }
        let pivot_sq = m[j][j] - dot_jj;
        if !(is_finite(pivot_sq) && pivot_sq > 0.0) {
            return out;
        }
        let pivot = sqrt(pivot_sq);
        m[j][j] = pivot;
        for (var i = j + 1u; i < GUIDE; i++) {
            var dot_ij = 0.0;
            for (var t = 0u; t < j; t++) {
                dot_ij += m[i][t] * m[j][t];
            }
            m[i][j] = (m[i][j] - dot_ij) / pivot;
        }
    }
    var y: array<f32, 5>;
    for (var i = 0u; i < GUIDE; i++) {
        var lower = 0.0;
        for (var t = 0u; t < i; t++) {
            lower += m[i][t] * y[t];
        }
        y[i] = (rhs[i] - lower) / m[i][i];
    }
    for (var step = 0u; step < GUIDE; step++) {
        let i = GUIDE - 1u - step;
        var upper = 0.0;
        for (var k = i + 1u; k < GUIDE; k++) {
            upper += m[k][i] * out.x[k];
        }
        out.x[i] = (y[i] - upper) / m[i][i];
    }
    for (var i = 0u; i < GUIDE; i++) {
        if !is_finite(out.x[i]) {
            return out;
        }
    }
    out.ok = true;
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
    let mu = array<f32, 5>(c_1.x / n_k, c_1.y / n_k, c_1.z / n_k, m_x / n_k, m_y / n_k);
    let p_mean = p_1 / n_k;
    let mean_gp = array<f32, 5>(c_p.x / n_k, c_p.y / n_k, c_p.z / n_k, p_x / n_k, p_y / n_k);
    // Pairs (0,0) (0,1) (0,2) (1,1) (1,2) (2,2) of the colour products.
    let cc = array<f32, 6>(c_c0.x, c_c0.y, c_c1.x, c_c1.y, c_c1.z, c_c1.w);
    var mean_gg: array<array<f32, 5>, 5>;
    mean_gg[0][0] = cc[0] / n_k;
    mean_gg[0][1] = cc[1] / n_k;
    mean_gg[1][0] = mean_gg[0][1];
    mean_gg[0][2] = cc[2] / n_k;
    mean_gg[2][0] = mean_gg[0][2];
    mean_gg[1][1] = cc[3] / n_k;
    mean_gg[1][2] = cc[4] / n_k;
    mean_gg[2][1] = mean_gg[1][2];
    mean_gg[2][2] = cc[5] / n_k;
    for (var c = 0u; c < 3u; c++) {
        mean_gg[c][3] = c_x[c] / n_k;
        mean_gg[3][c] = mean_gg[c][3];
        mean_gg[c][4] = c_y[c] / n_k;
        mean_gg[4][c] = mean_gg[c][4];
    }
    mean_gg[3][3] = m_xx / n_k;
    mean_gg[4][4] = m_yy / n_k;
    mean_gg[3][4] = m_xy / n_k;
    mean_gg[4][3] = mean_gg[3][4];
    let regularisation = array<f32, 5>(
        recon.settings.x,
        recon.settings.x,
        recon.settings.x,
        recon.settings.y,
        recon.settings.y,
    );
    var system: array<array<f32, 5>, 5>;
    var rhs: array<f32, 5>;
    for (var a = 0u; a < GUIDE; a++) {
        for (var b = 0u; b < GUIDE; b++) {
            system[a][b] = mean_gg[a][b] - mu[a] * mu[b];
        }
        system[a][a] += regularisation[a];
        rhs[a] = mean_gp[a] - mu[a] * p_mean;
    }
    let solution = solve_spd(system, rhs);
    var a_k: array<f32, 5>;
    if solution.ok {
        a_k = solution.x;
    }
    var a_mu = 0.0;
    for (var j = 0u; j < GUIDE; j++) {
        a_mu += a_k[j] * mu[j];
    }
    let b_k = p_mean - a_mu;
    coefficients[i] = vec4<f32>(n_k, n_k * a_k[0], n_k * a_k[1], n_k * a_k[2]);
    coefficients[n + i] = vec4<f32>(n_k * a_k[3], n_k * a_k[4], n_k * b_k, 0.0);
}
