//! The reflection maps of Kan et al.: the environment convolved with the diffuse and Phong lobes
//! for every output texel, over the *whole* input map (`shaders/ibl_convolve.wgsl`), in
//! octahedral maps (Engelhardt & Dachsbacher 2008: square, the whole sphere, nearly uniform texel
//! solid angles). The f64 brute-force convolution here is the test oracle.

use bytemuck::{Pod, Zeroable};
use glam::{DVec3, Vec2, Vec3};
use relight_core::scene::EnvironmentMap;
use relight_recon::envmap::{texel_direction, texel_solid_angle};

use crate::engine::EngineError;
use crate::gpu::{GpuContext, GpuError};
use crate::roofline::Work;
use crate::shaders;
use crate::timer::GpuTimer;
use crate::timer::timed_pass;

/// Specular levels one pass computes (the shader's `MAX_LEVELS`).
pub const MAX_LEVELS: usize = 8;

/// `levels` Phong exponents spaced evenly in log scale from 1 to 512 (rounded): the fixed set
/// of `ibl`'s `levels` parameter and of the convolution benchmark.
pub fn log_spaced_shininess(levels: u32) -> Vec<f32> {
    let last = (levels.max(1) - 1).max(1) as f32;
    (0..levels)
        .map(|k| 512f32.powf(k as f32 / last).round())
        .collect()
}

/// One input texel: unit direction and solid angle, radiance (`InputTexel` in the shader).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct InputTexel {
    pub direction: [f32; 4],
    pub radiance: [f32; 4],
}

/// `Ibl` in `shaders/common.wgsl`.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct IblUniform {
    pub dims: [u32; 4],
    pub frame: [u32; 4],
    pub params: [f32; 4],
    pub shininess: [f32; MAX_LEVELS],
    pub region: [u32; 4],
    pub bounce: [[f32; 4]; 9],
    pub probe: [[f32; 4]; 9],
    pub object: [[f32; 4]; 3],
    pub object_faces: [[f32; 4]; 6],
}

/// The unit direction at `uv` ∈ [0, 1]² of an octahedral map (`oct_decode` in the shaders).
pub fn oct_decode(uv: Vec2) -> Vec3 {
    let f = uv * 2.0 - 1.0;
    let mut n = Vec3::new(f.x, f.y, 1.0 - f.x.abs() - f.y.abs());
    let t = (-n.z).max(0.0);
    n.x += if n.x >= 0.0 { -t } else { t };
    n.y += if n.y >= 0.0 { -t } else { t };
    n.normalize()
}

/// The direction of texel `index` (row-major) of an octahedral map `size` texels square.
pub fn oct_texel_direction(index: usize, size: u32) -> Vec3 {
    let size = size as usize;
    let uv = Vec2::new((index % size) as f32 + 0.5, (index / size) as f32 + 0.5) / size as f32;
    oct_decode(uv)
}

/// `env` resampled to `width × width/2` texels by solid-angle-weighted averaging, so that the
/// map's energy Σ L ΔΩ is kept (exactly when the sizes divide); maps already that small or
/// smaller are returned as they are.
pub fn resample(env: &EnvironmentMap, width: u32) -> EnvironmentMap {
    let (w, h) = (env.width as usize, env.height as usize);
    let (ow, oh) = (width.max(2) as usize, (width / 2).max(1) as usize);
    if w <= ow || h <= oh || env.radiance.len() != w * h {
        return env.clone();
    }
    let mut sum = vec![DVec3::ZERO; ow * oh];
    let mut omega = vec![0f64; ow * oh];
    for y in 0..h {
        let o = texel_solid_angle(env.width, env.height, y as u32);
        let oy = y * oh / h;
        for x in 0..w {
            let l = env.radiance[y * w + x];
            let l = if l.is_finite() {
                l.max(Vec3::ZERO)
            } else {
                Vec3::ZERO
            };
            let i = oy * ow + x * ow / w;
            sum[i] += l.as_dvec3() * o;
            omega[i] += o;
        }
    }
    EnvironmentMap {
        width: ow as u32,
        height: oh as u32,
        radiance: sum
            .iter()
            .zip(&omega)
            .map(|(s, o)| {
                if *o > 0.0 {
                    (*s / *o).as_vec3()
                } else {
                    Vec3::ZERO
                }
            })
            .collect(),
    }
}

/// The map's texels as convolution input: centre direction, exact solid angle, radiance; black,
/// negative and non-finite texels are left out (they add nothing). The texels `specular_only`
/// flags (row-major, the local picture's surfaces, whose diffuse light the shading takes from
/// their patches instead: `LocalPicture::near`) are left out of the diffuse map alone.
pub fn input_texels(env: &EnvironmentMap, specular_only: Option<&[bool]>) -> Vec<InputTexel> {
    let (w, h) = (env.width as usize, env.height as usize);
    if env.radiance.len() != w * h {
        return Vec::new();
    }
    let mut texels = Vec::new();
    for y in 0..env.height {
        let omega = texel_solid_angle(env.width, env.height, y) as f32;
        for x in 0..env.width {
            let index = y as usize * w + x as usize;
            let l = env.radiance[index];
            if !l.is_finite() || l.max_element() <= 0.0 {
                continue;
            }
            let diffuse = specular_only.is_none_or(|flags| flags.get(index) != Some(&true));
            texels.push(InputTexel {
                direction: texel_direction(env.width, env.height, x, y)
                    .extend(omega)
                    .to_array(),
                radiance: l
                    .max(Vec3::ZERO)
                    .extend(if diffuse { 0.0 } else { 1.0 })
                    .to_array(),
            });
        }
    }
    texels
}

/// The oracle, in f64: the diffuse irradiance map's value 1/π Σ L ΔΩ ⟨d, ω⟩₊ (`shininess`
/// `None`) or the specular map's (n + 1)/(2π) Σ L ΔΩ ⟨d, ω⟩₊ⁿ at direction `d`.
pub fn convolve_f64(texels: &[InputTexel], d: Vec3, shininess: Option<f32>) -> DVec3 {
    let d = d.as_dvec3();
    let mut sum = DVec3::ZERO;
    for t in texels {
        let dir = DVec3::new(
            f64::from(t.direction[0]),
            f64::from(t.direction[1]),
            f64::from(t.direction[2]),
        );
        let c = d.dot(dir);
        if c > 0.0 {
            let l = DVec3::new(
                f64::from(t.radiance[0]),
                f64::from(t.radiance[1]),
                f64::from(t.radiance[2]),
            );
            // A texel flagged specular-only (w = 1) is left out of the diffuse map.
            let lobe = shininess.map_or(c * (1.0 - f64::from(t.radiance[3])), |n| {
                c.powf(f64::from(n))
            });
            sum += l * f64::from(t.direction[3]) * lobe;
        }
    }
    match shininess {
        None => sum / std::f64::consts::PI,
        Some(n) => sum * (f64::from(n) + 1.0) / std::f64::consts::TAU,
    }
}

/// The maps on the GPU: layer 0 diffuse, layer 1 + k specular of `shininess[k]`, each
/// `size × size` texels of RGBA32F (a = 1), row-major, layer after layer.
#[derive(Debug)]
pub struct ReflectionMaps {
    pipeline: wgpu::ComputePipeline,
    uniform: wgpu::Buffer,
    input: Option<wgpu::Buffer>,
    maps: Option<wgpu::Buffer>,
    size: u32,
    shininess: Vec<f32>,
}

impl ReflectionMaps {
    pub fn new(ctx: &GpuContext) -> Self {
        Self {
            pipeline: shaders::compute_pipeline(&ctx.device, "ibl convolve", shaders::IBL_CONVOLVE),
            uniform: shaders::params_buffer(&ctx.device, "ibl convolve", size_of::<IblUniform>()),
            input: None,
            maps: None,
            size: 0,
            shininess: Vec::new(),
        }
    }

    /// Convolve `texels` into maps `size` texels square with the specular exponents `shininess`
    /// (at most [`MAX_LEVELS`], each > 0). Returns the work the convolution must do: every
    /// output texel of every map sums every input texel (about 12 operations: the cosine or
    /// the Phong lobe, weighted by the texel's solid angle), the input read once and the maps
    /// written once.
    pub fn convolve(
        &mut self,
        ctx: &GpuContext,
        texels: &[InputTexel],
        size: u32,
        shininess: &[f32],
        timer: &mut Option<GpuTimer>,
    ) -> Result<Work, EngineError> {
        let levels = shininess.len().min(MAX_LEVELS);
        let bytes = u64::from(size).pow(2) * (levels as u64 + 1) * 16;
        ctx.require("max_storage_buffer_binding_size", bytes, "map_size")?;
        let mut uniform = IblUniform::zeroed();
        uniform.dims = [size, levels as u32, texels.len() as u32, 0];
        uniform.shininess[..levels].copy_from_slice(&shininess[..levels]);
        ctx.queue
            .write_buffer(&self.uniform, 0, bytemuck::bytes_of(&uniform));
        let input_bytes = (size_of_val(texels) as u64).max(32);
        if self.input.as_ref().is_none_or(|b| b.size() < input_bytes) {
            self.input = Some(storage(
                ctx,
                "ibl input",
                input_bytes,
                wgpu::BufferUsages::empty(),
            ));
        }
        if self.maps.as_ref().is_none_or(|b| b.size() != bytes) {
            self.maps = Some(storage(
                ctx,
                "ibl maps",
                bytes,
                wgpu::BufferUsages::COPY_SRC,
            ));
        }
        let (Some(input), Some(maps)) = (&self.input, &self.maps) else {
            return Err(EngineError::NotPrepared);
        };
        if !texels.is_empty() {
            ctx.queue
                .write_buffer(input, 0, bytemuck::cast_slice(texels));
        }
        let group = shaders::pipeline_bind_group(
            &ctx.device,
            &self.pipeline,
            "ibl convolve",
            &[
                self.uniform.as_entire_binding(),
                input.as_entire_binding(),
                maps.as_entire_binding(),
            ],
        );
        let mut encoder = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("ibl convolve"),
            });
        {
            let mut pass = timed_pass(&mut encoder, timer, "gpu.convolve");
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups((size * size).div_ceil(64), 1, 1);
        }
        ctx.queue.submit([encoder.finish()]);
        ctx.check()?;
        self.size = size;
        self.shininess = shininess[..levels].to_vec();
        let outputs = f64::from(size).powi(2) * (levels as f64 + 1.0);
        Ok(Work::new(input_bytes as f64 + bytes as f64, 0.0)
            + Work::new(0.0, 12.0).times(outputs * texels.len() as f64))
    }

    /// The maps buffer (after [`convolve`](Self::convolve)).
    pub fn buffer(&self) -> Option<&wgpu::Buffer> {
        self.maps.as_ref()
    }

    pub fn size(&self) -> u32 {
        self.size
    }

    pub fn shininess(&self) -> &[f32] {
        &self.shininess
    }

    /// Read every map back: `(1 + levels) × size²` RGB texels (for tests and tools).
    pub fn read(&self, ctx: &GpuContext) -> Result<Vec<Vec3>, GpuError> {
        let Some(maps) = &self.maps else {
            return Ok(Vec::new());
        };
        let staging = storage_like(ctx, maps.size());
        ctx.read_back(maps, &staging, maps.size(), |bytes| {
            bytemuck::cast_slice::<u8, [f32; 4]>(bytes)
                .iter()
                .map(|t| Vec3::new(t[0], t[1], t[2]))
                .collect()
        })
    }
}

fn storage(ctx: &GpuContext, label: &str, size: u64, extra: wgpu::BufferUsages) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size,
        usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | extra,
        mapped_at_creation: false,
    })
}

fn storage_like(ctx: &GpuContext, size: u64) -> wgpu::Buffer {
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("ibl maps staging"),
        size,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn octahedral_texels_cover_the_sphere() {
        let size = 32;
        let mut mean = Vec3::ZERO;
        for i in 0..(size * size) as usize {
            let d = oct_texel_direction(i, size);
            assert!((d.length() - 1.0).abs() < 1e-5);
            mean += d;
        }
        assert!((mean / (size * size) as f32).length() < 0.02, "{mean}");
    }

    #[test]
    fn resampling_keeps_the_energy() {
        let (w, h) = (64u32, 32u32);
        let radiance = (0..w * h)
            .map(|i| Vec3::new((i % 7) as f32, (i % 3) as f32 * 10.0, 0.5))
            .collect();
        let env = EnvironmentMap {
            width: w,
            height: h,
            radiance,
        };
        let energy = |e: &EnvironmentMap| -> DVec3 {
            input_texels(e, None)
                .iter()
                .map(|t| {
                    DVec3::new(
                        f64::from(t.radiance[0]),
                        f64::from(t.radiance[1]),
                        f64::from(t.radiance[2]),
                    ) * f64::from(t.direction[3])
                })
                .sum()
        };
        let small = resample(&env, 16);
        assert_eq!((small.width, small.height), (16, 8));
        let (a, b) = (energy(&env), energy(&small));
        assert!(((a - b).abs() / a).max_element() < 1e-5, "{a} vs {b}");
    }

    #[test]
    fn uniform_environment_convolves_to_its_radiance() {
        // A uniform sphere of radiance L: E_d = 1/π ∫ L cos = L, E_s = (n+1)/(2π) ∫ L cosⁿ = L,
        // up to the midpoint rule on 5.6° texels, whose error concentrates where the clamped
        // cosine's kink cuts texels (≈ 0.1% here).
        let env = EnvironmentMap {
            width: 64,
            height: 32,
            radiance: vec![Vec3::splat(2.0); 64 * 32],
        };
        let texels = input_texels(&env, None);
        for d in [Vec3::Y, Vec3::X, Vec3::new(0.3, -0.8, 0.5).normalize()] {
            let e = convolve_f64(&texels, d, None);
            assert!((e.x - 2.0).abs() < 1e-2, "diffuse {e}");
            let s = convolve_f64(&texels, d, Some(16.0));
            assert!((s.x - 2.0).abs() < 2e-2, "specular {s}");
        }
    }
}
