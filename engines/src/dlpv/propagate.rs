//! Light propagation (Kaplanyan & Dachsbacher 2010, as DLPV uses it): `steps` gathers of every
//! cell from its six neighbours, ping-ponging between two buffers and summing every step into
//! the accumulation (`dlpv_propagate.wgsl`). All steps go into one compute pass; the two bind
//! groups are built once per frame.

use crate::shaders;

#[derive(Debug)]
pub(crate) struct Propagation {
    pipeline: wgpu::ComputePipeline,
}

/// The buffers of a propagation: the injected SH (the first step's source, overwritten by
/// every second step), the other half of the ping-pong, and the accumulation (which must
/// already hold the injected SH: the resolve writes both).
pub(crate) struct PropagationBuffers<'a> {
    pub uniform: &'a wgpu::Buffer,
    pub injected: &'a wgpu::Buffer,
    pub ping: &'a wgpu::Buffer,
    pub accumulated: &'a wgpu::Buffer,
}

impl Propagation {
    pub fn new(device: &wgpu::Device) -> Self {
        Self {
            pipeline: shaders::compute_pipeline(device, "dlpv propagate", shaders::DLPV_PROPAGATE),
        }
    }

    /// Record `steps` steps over `n`³ cells into `pass`: V^Δ's all, V^ρ's the first
    /// `rho_steps`.
    pub fn record(
        &self,
        device: &wgpu::Device,
        pass: &mut wgpu::ComputePass,
        buffers: &PropagationBuffers,
        n: u32,
        steps: u32,
        rho_steps: u32,
    ) {
        let step_group = |from: &wgpu::Buffer, to: &wgpu::Buffer| {
            shaders::pipeline_bind_group(
                device,
                &self.pipeline,
                "dlpv propagate",
                &[
                    buffers.uniform.as_entire_binding(),
                    from.as_entire_binding(),
                    to.as_entire_binding(),
                    buffers.accumulated.as_entire_binding(),
                ],
            )
        };
        let forward = step_group(buffers.injected, buffers.ping);
        let backward = step_group(buffers.ping, buffers.injected);
        pass.set_pipeline(&self.pipeline);
        for step in 0..steps {
            pass.set_bind_group(0, if step % 2 == 0 { &forward } else { &backward }, &[]);
            // 8 × 8 cells of one slice a workgroup (`@workgroup_size(8, 8, 1)`); z runs over
            // the slices of V^Δ, then of V^ρ while it still propagates.
            let volumes = if step < rho_steps { 2 } else { 1 };
            pass.dispatch_workgroups(n.div_ceil(8), n.div_ceil(8), volumes * n);
        }
    }
}

#[cfg(test)]
mod tests {
    //! The shader's per-direction transfer against the general form it was derived from: every
    //! face's flux as a dot product with the SH basis at the face's centre, re-emitted as the
    //! cosine lobe around the face's normal (Kaplanyan & Dachsbacher 2010, Sec. 3.3), in f64.

    use super::*;
    use crate::gpu::GpuContext;
    use crate::volume::VolumeUniform;
    use glam::DVec3;
    use half::f16;

    fn sh_basis(d: DVec3) -> [f64; 4] {
        let c = 0.488602512;
        [0.282094792, c * d.y, c * d.z, c * d.x]
    }

    fn cosine_lobe(d: DVec3) -> [f64; 4] {
        let c = 1.023326708;
        [0.886226925, c * d.y, c * d.z, c * d.x]
    }

    /// One step of the general form over `n`³ cells × 3 channels × 4 coefficients.
    fn step_cpu(n: usize, dampening: f64, source: &[[f64; 4]]) -> Vec<[f64; 4]> {
        let axes = [
            DVec3::X,
            -DVec3::X,
            DVec3::Y,
            -DVec3::Y,
            DVec3::Z,
            -DVec3::Z,
        ];
        let mut next = vec![[0.0; 4]; source.len()];
        let index = |x: usize, y: usize, z: usize| (z * n + y) * n + x;
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let c = DVec3::new(x as f64, y as f64, z as f64);
                    for d in axes {
                        let s = c - d;
                        if s.min_element() < 0.0 || s.max_element() >= n as f64 {
                            continue;
                        }
                        let src = index(s.x as usize, s.y as usize, s.z as usize);
                        let mut faces = vec![(d, d, 0.4006696846)];
                        for side in axes.iter().filter(|a| a.dot(d) == 0.0) {
                            faces.push((0.894427191 * d + 0.447213595 * side, *side, 0.4234413544));
                        }
                        for ch in 0..3 {
                            let sh = source[src * 3 + ch];
                            for &(towards, normal, solid_angle) in &faces {
                                let basis = sh_basis(towards);
                                let intensity: f64 = (0..4).map(|k| sh[k] * basis[k]).sum();
                                let mut flux = solid_angle / std::f64::consts::PI * intensity;
                                if flux < 0.0 {
                                    flux *= 1.0 - dampening;
                                }
                                let lobe = cosine_lobe(normal);
                                let out = &mut next[index(x, y, z) * 3 + ch];
                                for k in 0..4 {
                                    out[k] += flux * lobe[k];
                                }
                            }
                        }
                    }
                }
            }
        }
        next
    }

    /// `pack_sh` then `unpack_sh` (common.wgsl, written by hand) round every value as the
    /// `half` crate does (to nearest, ties to even), subnormals included, and clamp what lies
    /// beyond f16's range to its largest value rather than to ∞.
    #[test]
    fn the_f16_volume_storage_rounds_to_nearest_and_clamps() {
        let ctx = GpuContext::new().expect("a GPU adapter (lavapipe in CI)");
        let device = &ctx.device;
        let source = format!(
            "{}\n{}",
            include_str!("../../../shaders/common.wgsl"),
            "@group(0) @binding(0) var<storage, read_write> values: array<vec4<f32>>;
             @compute @workgroup_size(1)
             fn main(@builtin(global_invocation_id) id: vec3<u32>) {
                 values[id.x] = unpack_sh(pack_sh(values[id.x]));
             }"
        );
        let pipeline = shaders::compute_pipeline(device, "f16 round trip", &source);
        let ties = 1.0 + 2f32.powi(-11);
        let inputs: Vec<f32> = vec![
            0.0,
            -0.0,
            1.0,
            -1.0,
            ties,
            1.0 + 3.0 * 2f32.powi(-11),
            0.1,
            -123.456,
            65504.0,
            65519.0,
            1e6,
            -1e9,
            3e-5,
            -1e-6,
            6e-8,
            2e-8,
            1e-9,
            std::f32::consts::PI * 1e3,
            6.1e-5,
            -65504.0,
        ];
        use wgpu::util::DeviceExt;
        let buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("values"),
            contents: bytemuck::cast_slice(&inputs),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        });
        let group = shaders::pipeline_bind_group(
            device,
            &pipeline,
            "values",
            &[buffer.as_entire_binding()],
        );
        let mut encoder = device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(inputs.len() as u32 / 4, 1, 1);
        }
        ctx.queue.submit([encoder.finish()]);
        let size = (inputs.len() * 4) as u64;
        let staging = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("staging"),
            size,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let gpu: Vec<f32> = ctx
            .read_back(&buffer, &staging, size, |bytes| {
                bytemuck::cast_slice(bytes).to_vec()
            })
            .unwrap();
        for (x, g) in inputs.iter().zip(&gpu) {
            let expected = f16::from_f32(x.clamp(-65504.0, 65504.0)).to_f32();
            assert_eq!(
                g.to_bits(),
                expected.to_bits(),
                "{x:e} came back as {g:e}, not {expected:e}"
            );
        }
        assert_eq!(gpu[4], 1.0, "a tie rounds to the even mantissa");
        assert_eq!(gpu[10], 65504.0, "beyond f16's range clamps, not ∞");
    }

    #[test]
    fn the_per_direction_transfer_matches_the_general_face_form() {
        let ctx = GpuContext::new().expect("a GPU adapter (lavapipe in CI)");
        // V^ρ stops a step before V^Δ.
        let (n, steps, rho_steps, dampening) = (5usize, 3u32, 2u32, 0.5);
        let values = 2 * n.pow(3) * 3;
        // Both signs (antiradiance and L1 ringing are negative), no two values alike.
        let injected: Vec<[f32; 4]> = (0..values)
            .map(|i| {
                std::array::from_fn(|k| {
                    let v = (((i * 4 + k) * 7919 % 1013) as f32 / 1013.0) - 0.4;
                    f16::from_f32(v).to_f32()
                })
            })
            .collect();
        // The volumes' storage (`pack_sh`): four f16 per channel, two to a word, x low.
        let packed: Vec<[u32; 2]> = injected
            .iter()
            .map(|v| {
                let word = |a: f32, b: f32| {
                    u32::from(f16::from_f32(a).to_bits())
                        | (u32::from(f16::from_f32(b).to_bits()) << 16)
                };
                [word(v[0], v[1]), word(v[2], v[3])]
            })
            .collect();
        let device = &ctx.device;
        let storage = |label, usage| {
            use wgpu::util::DeviceExt;
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(&packed),
                usage,
            })
        };
        use wgpu::BufferUsages as U;
        let buffers = PropagationBuffers {
            uniform: &shaders::params_buffer(device, "volume", size_of::<VolumeUniform>()),
            injected: &storage("injected", U::STORAGE),
            ping: &storage("ping", U::STORAGE),
            accumulated: &storage("accumulated", U::STORAGE | U::COPY_SRC),
        };
        let volume = VolumeUniform {
            origin: [0.0; 4],
            dims: [n as u32, 0, 0, 0],
            scale: [1.0, 0.0, dampening as f32, 0.0],
            options: [0; 4],
            object: [[0.0; 4]; 3],
        };
        ctx.queue
            .write_buffer(buffers.uniform, 0, bytemuck::bytes_of(&volume));
        let propagation = Propagation::new(device);
        let mut encoder = device.create_command_encoder(&Default::default());
        {
            let mut pass = encoder.begin_compute_pass(&Default::default());
            propagation.record(device, &mut pass, &buffers, n as u32, steps, rho_steps);
        }
        ctx.queue.submit([encoder.finish()]);
        let size = (values * 8) as u64;
        let staging = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("staging"),
            size,
            usage: U::MAP_READ | U::COPY_DST,
            mapped_at_creation: false,
        });
        let gpu: Vec<[f32; 4]> = ctx
            .read_back(buffers.accumulated, &staging, size, |bytes| {
                bytemuck::cast_slice::<u8, u16>(bytes)
                    .chunks_exact(4)
                    .map(|h| std::array::from_fn(|k| f16::from_bits(h[k]).to_f32()))
                    .collect()
            })
            .unwrap();

        let cells = n.pow(3) * 3;
        for volume in 0..2 {
            let range = volume * cells..(volume + 1) * cells;
            let mut current: Vec<[f64; 4]> = injected[range.clone()]
                .iter()
                .map(|v| v.map(f64::from))
                .collect();
            let mut expected = current.clone();
            let volume_steps = if volume == 0 { steps } else { rho_steps };
            for _ in 0..volume_steps {
                current = step_cpu(n, dampening, &current);
                for (e, c) in expected.iter_mut().zip(&current) {
                    for k in 0..4 {
                        e[k] += c[k];
                    }
                }
            }
            let worst = gpu[range]
                .iter()
                .zip(&expected)
                .flat_map(|(g, e)| (0..4).map(move |k| (f64::from(g[k]) - e[k]).abs()))
                .fold(0.0, f64::max);
            let scale = expected
                .iter()
                .flatten()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            // Each step rounds its values and the accumulation to f16 once, each by at most
            // 2^-11 of a value no larger than `scale`; later steps pass a rounding on without
            // amplifying it (a step passes a uniform field's light on unchanged). An error in
            // the transfer itself is of the order of `scale`. (Measured: 7.6e-4 of it.)
            let bound = 2.0 * f64::from(volume_steps) * 2f64.powi(-11) * scale;
            assert!(
                worst <= bound,
                "volume {volume}: worst |GPU − CPU| {worst:e} of {scale}"
            );
        }
    }
}
