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
    use crate::volume::{VolumeUniform, uniform_buffer};
    use glam::DVec3;

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

    #[test]
    fn the_per_direction_transfer_matches_the_general_face_form() {
        let ctx = GpuContext::new().expect("a GPU adapter (lavapipe in CI)");
        // V^ρ stops a step before V^Δ.
        let (n, steps, rho_steps, dampening) = (5usize, 3u32, 2u32, 0.5);
        let values = 2 * n.pow(3) * 3;
        // Both signs (antiradiance and L1 ringing are negative), no two values alike.
        let injected: Vec<[f32; 4]> = (0..values)
            .map(|i| std::array::from_fn(|k| (((i * 4 + k) * 7919 % 1013) as f32 / 1013.0) - 0.4))
            .collect();
        let device = &ctx.device;
        let storage = |label, usage| {
            use wgpu::util::DeviceExt;
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(&injected),
                usage,
            })
        };
        use wgpu::BufferUsages as U;
        let buffers = PropagationBuffers {
            uniform: &uniform_buffer(device, "volume", size_of::<VolumeUniform>()),
            injected: &storage("injected", U::STORAGE),
            ping: &storage("ping", U::STORAGE),
            accumulated: &storage("accumulated", U::STORAGE | U::COPY_SRC),
        };
        let volume = VolumeUniform {
            origin: [0.0; 4],
            dims: [n as u32, 0, 0, 0],
            scale: [1.0, 0.0, dampening as f32, 0.0],
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
        let size = (values * 16) as u64;
        let staging = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("staging"),
            size,
            usage: U::MAP_READ | U::COPY_DST,
            mapped_at_creation: false,
        });
        let gpu: Vec<[f32; 4]> = ctx
            .read_back(buffers.accumulated, &staging, size, |bytes| {
                bytemuck::cast_slice(bytes).to_vec()
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
            for _ in 0..if volume == 0 { steps } else { rho_steps } {
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
            // f32 sums of a few dozen terms per step: far under 1e-5 of the largest value.
            assert!(
                worst <= 1e-5 * scale,
                "volume {volume}: worst |GPU − CPU| {worst:e} of {scale}"
            );
        }
    }
}
