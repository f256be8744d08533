// DLPV propagation, one step (Kaplanyan & Dachsbacher 2010, as DLPV uses it): every cell
// gathers from its six neighbours. The neighbour's intensity towards each of the five faces of
// this cell it can see (the face opposite it, solid angle 0.4006696846 sr, and the four side
// faces, 0.4234413544 sr each, seen at (d + s/2)/|d + s/2|) becomes flux through that face,
// re-emitted into this cell as a cosine lobe around the face's normal.
//
// The transfer is written out per direction rather than as dot products with the faces' SH
// bases and lobes: the directions are axes, so each face's flux needs two or three of the
// neighbour's coefficients and each lobe adds to two of this cell's. Work runs across the
// three colour channels at once (one vec3 per SH coefficient), about a third of the arithmetic
// of the general form (engines/src/dlpv/propagate.rs tests the two agree). Values are float
// here: each cell is written by exactly one thread. `accumulated` sums every step (and the
// injection). Negative light (antiradiance) is scaled by 1 − dampening per step (Sec. 4.4: it
// keeps shadows from bleeding far beyond the occluder; see the closing notes for how this
// differs from the paper's derivative-based rule).

@group(0) @binding(0) var<storage, read> volume_buffer: Volume;
var<private> volume: Volume;
// n³ cells × 3 channels of L1 SH (four f16 per channel), for V^Δ then V^ρ.
@group(0) @binding(1) var<storage, read> source: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read_write> next: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read_write> accumulated: array<vec2<u32>>;

// Flux through the face opposite the neighbour and through a side face, per unit of
// intensity: solid angle / π.
const DIRECT_FACE: f32 = 0.4006696846 / PI;
const SIDE_FACE: f32 = 0.4234413544 / PI;
// sh_basis and cosine_lobe's coefficients (common.wgsl), and the side-face direction's
// components along and across the propagation axis, (d + s/2)/|d + s/2| = 0.894 d + 0.447 s.
const SH0: f32 = 0.282094792;
const SH1: f32 = 0.488602512;
const LOBE0: f32 = 0.886226925;
const LOBE1: f32 = 1.023326708;
const ALONG: f32 = 0.894427191;
const ACROSS: f32 = 0.447213595;

// A cell's L1 SH, each coefficient as a vec3 over the colour channels.
struct Sh {
    c0: vec3<f32>,
    cx: vec3<f32>,
    cy: vec3<f32>,
    cz: vec3<f32>,
}

// Light passes unchanged; antiradiance (negative) is dampened.
fn dampen(f: vec3<f32>) -> vec3<f32> {
    return select(f * (1.0 - volume.scale.z), f, f >= vec3<f32>(0.0));
}

// A neighbour's light into this cell, in the neighbour's coefficients along the propagation
// axis (`along`, travelling towards `sign`) and the two axes across it (`u`, `v`), zero when
// `w` is 0 (no neighbour: the volume's edge); returns what it adds to this cell's
// coefficients in the same roles.
struct Transfer {
    c0: vec3<f32>,
    along: vec3<f32>,
    u: vec3<f32>,
    v: vec3<f32>,
}

fn transfer(c0: vec3<f32>, along: vec3<f32>, u: vec3<f32>, v: vec3<f32>, sign: f32, w: f32) -> Transfer {
    let a = SH0 * w * c0;
    let main = dampen(DIRECT_FACE * (a + (sign * SH1 * w) * along));
    let b = a + (sign * SH1 * ALONG * w) * along;
    let du = (SH1 * ACROSS * w) * u;
    let dv = (SH1 * ACROSS * w) * v;
    let up = dampen(SIDE_FACE * (b + du));
    let um = dampen(SIDE_FACE * (b - du));
    let vp = dampen(SIDE_FACE * (b + dv));
    let vm = dampen(SIDE_FACE * (b - dv));
    return Transfer(
        LOBE0 * (main + up + um + vp + vm),
        (sign * LOBE1) * main,
        LOBE1 * (up - um),
        LOBE1 * (vp - vm),
    );
}

fn load(base: u32, c: vec3<i32>, d: vec3<i32>, w: ptr<function, f32>) -> Sh {
    let ni = i32(volume.dims.x);
    let s = c - d;
    *w = select(0.0, 1.0, all(s >= vec3<i32>(0)) && all(s < vec3<i32>(ni)));
    let sc = clamp(s, vec3<i32>(0), vec3<i32>(ni - 1));
    let src = (base + u32((sc.z * ni + sc.y) * ni + sc.x)) * 3u;
    let r = unpack_sh(source[src]);
    let g = unpack_sh(source[src + 1u]);
    let b = unpack_sh(source[src + 2u]);
    // sh_basis order: (1, y, z, x).
    return Sh(vec3<f32>(r.x, g.x, b.x), vec3<f32>(r.w, g.w, b.w), vec3<f32>(r.y, g.y, b.y), vec3<f32>(r.z, g.z, b.z));
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    volume = volume_buffer;
    let n = volume.dims.x;
    let which = id.z / n;
    let z = id.z % n;
    if id.x >= n || id.y >= n || which >= 2u {
        return;
    }
    let c = vec3<i32>(i32(id.x), i32(id.y), i32(z));
    let base = which * n * n * n;
    let index = base + u32((c.z * i32(n) + c.y) * i32(n) + c.x);
    var acc = Sh(vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0), vec3<f32>(0.0));
    var w: f32;
    // Light travelling along ±x, ±y, ±z arrives from the neighbour at c − d.
    for (var k = 0; k < 2; k++) {
        let sign = f32(1 - 2 * k);
        let step = 1 - 2 * k;
        var s = load(base, c, vec3<i32>(step, 0, 0), &w);
        var t = transfer(s.c0, s.cx, s.cy, s.cz, sign, w);
        acc = Sh(acc.c0 + t.c0, acc.cx + t.along, acc.cy + t.u, acc.cz + t.v);
        s = load(base, c, vec3<i32>(0, step, 0), &w);
        t = transfer(s.c0, s.cy, s.cx, s.cz, sign, w);
        acc = Sh(acc.c0 + t.c0, acc.cx + t.u, acc.cy + t.along, acc.cz + t.v);
        s = load(base, c, vec3<i32>(0, 0, step), &w);
        t = transfer(s.c0, s.cz, s.cx, s.cy, sign, w);
        acc = Sh(acc.c0 + t.c0, acc.cx + t.u, acc.cy + t.v, acc.cz + t.along);
    }
    let sum = array<vec4<f32>, 3>(
        vec4<f32>(acc.c0.x, acc.cy.x, acc.cz.x, acc.cx.x),
        vec4<f32>(acc.c0.y, acc.cy.y, acc.cz.y, acc.cx.y),
        vec4<f32>(acc.c0.z, acc.cy.z, acc.cz.z, acc.cx.z),
    );
    for (var ch = 0u; ch < 3u; ch++) {
        next[index * 3u + ch] = pack_sh(sum[ch]);
        accumulated[index * 3u + ch] = pack_sh(unpack_sh(accumulated[index * 3u + ch]) + sum[ch]);
    }
}
