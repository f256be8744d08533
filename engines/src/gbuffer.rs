//! The camera G-buffer (world position + material, normal + virtual flag, albedo) and the
//! reflective shadow maps, both rasterised from the [`GpuScene`] in a ρ variant (every mesh) and
//! a μ variant (real meshes only).

use relight_core::PixelRect;

use crate::gpu::GpuContext;
use crate::gpu_scene::{GpuScene, GpuVertex};
use crate::roofline::{self, Work};
use crate::shaders;
use crate::timer::GpuTimer;

const POSITION: wgpu::TextureFormat = wgpu::TextureFormat::Rgba32Float;
const NORMAL: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
const ALBEDO: wgpu::TextureFormat = wgpu::TextureFormat::Rgba16Float;
const DEPTH: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// Three colour targets (position, normal, albedo) and a depth buffer, `layers` deep.
#[derive(Debug)]
pub struct Targets {
    pub width: u32,
    pub height: u32,
    pub layers: u32,
    pub position: wgpu::Texture,
    /// The colour targets are 1 × 1 and never drawn in depth-only targets
    /// ([`Targets::depth_only`]).
    pub normal: wgpu::Texture,
    pub albedo: wgpu::Texture,
    depth: wgpu::Texture,
    depth_only: bool,
}

impl Targets {
    pub fn new(ctx: &GpuContext, label: &str, width: u32, height: u32, layers: u32) -> Self {
        Self::with_attachments(ctx, label, width, height, layers, false)
    }

    /// Targets of which only the depth is drawn (shadow maps used for visibility alone).
    pub fn depth_only(ctx: &GpuContext, label: &str, width: u32, height: u32, layers: u32) -> Self {
        Self::with_attachments(ctx, label, width, height, layers, true)
    }

    fn with_attachments(
        ctx: &GpuContext,
        label: &str,
        width: u32,
        height: u32,
        layers: u32,
        depth_only: bool,
    ) -> Self {
        let texture = |format, suffix: &str, layers: u32| {
            let (width, height, layers) = if depth_only && suffix != "depth" {
                (1, 1, 1)
            } else {
                (width, height, layers)
            };
            ctx.device.create_texture(&wgpu::TextureDescriptor {
                label: Some(&format!("{label} {suffix}")),
                size: wgpu::Extent3d {
                    width,
                    height,
                    depth_or_array_layers: layers,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                    | wgpu::TextureUsages::TEXTURE_BINDING
                    | wgpu::TextureUsages::COPY_SRC
                    | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            })
        };
        Self {
            width,
            height,
            layers,
            position: texture(POSITION, "position", layers),
            normal: texture(NORMAL, "normal", layers),
            albedo: texture(ALBEDO, "albedo", layers),
            // One depth layer per target layer, so that a layer's depth can be kept and copied.
            depth: texture(DEPTH, "depth", layers),
            depth_only,
        }
    }

    /// View of all layers as an array (for sampling in compute passes).
    pub fn array_view(texture: &wgpu::Texture) -> wgpu::TextureView {
        texture.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..Default::default()
        })
    }

    /// Array views of R^ρ's and R^μ's position, normal and albedo, in that order (how every
    /// pass that reads VPLs binds them).
    pub fn rsm_views(rho: &Targets, mu: &Targets) -> [wgpu::TextureView; 6] {
        [rho, mu]
            .map(|t| [&t.position, &t.normal, &t.albedo].map(Self::array_view))
            .concat()
            .try_into()
            .unwrap_or_else(|_| unreachable!("two maps of three views"))
    }

    /// Array view of the depth: what a shadow-map test reads (`lit` in `common.wgsl`).
    pub fn depth_array_view(&self) -> wgpu::TextureView {
        Self::array_view(&self.depth)
    }

    /// Bytes of one texel over every drawn target and the depth.
    pub fn texel_bytes(&self) -> u64 {
        let colour = if self.depth_only {
            0
        } else {
            POSITION.block_copy_size(None).unwrap_or(16)
                + NORMAL.block_copy_size(None).unwrap_or(8)
                + ALBEDO.block_copy_size(None).unwrap_or(8)
        };
        u64::from(colour) + 4
    }

    /// Texels of one layer.
    pub fn layer_texels(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    pub fn view(texture: &wgpu::Texture) -> wgpu::TextureView {
        texture.create_view(&wgpu::TextureViewDescriptor::default())
    }

    fn layer_view(texture: &wgpu::Texture, layer: u32) -> wgpu::TextureView {
        texture.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2),
            base_array_layer: layer,
            array_layer_count: Some(1),
            ..Default::default()
        })
    }

    /// Draw the triangles of `scene` whose indices are `corners` into layer `layer`, with the
    /// layer as the draw's instance index: cleared first (to zero, depth to the far plane)
    /// unless `start` says to draw over what the layer holds, depth test included.
    #[allow(clippy::too_many_arguments)]
    fn draw(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::RenderPipeline,
        bind_group: &wgpu::BindGroup,
        scene: &GpuScene,
        (indices, corners): (&wgpu::Buffer, std::ops::Range<u32>),
        layer: u32,
        start: LayerStart,
        scissor: Option<PixelRect>,
        timestamps: Option<wgpu::RenderPassTimestampWrites>,
    ) {
        let views: Vec<wgpu::TextureView> = self
            .drawn_colour()
            .map(|t| Self::layer_view(t, layer))
            .collect();
        let load = match start {
            LayerStart::Clear(_) => wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT),
            LayerStart::Over => wgpu::LoadOp::Load,
        };
        let attachments: Vec<Option<wgpu::RenderPassColorAttachment>> = views
            .iter()
            .map(|view| {
                Some(wgpu::RenderPassColorAttachment {
                    view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load,
                        store: wgpu::StoreOp::Store,
                    },
                })
            })
            .collect();
        let depth_view = Self::layer_view(&self.depth, layer);
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("g-buffer"),
            color_attachments: &attachments,
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &depth_view,
                depth_ops: Some(wgpu::Operations {
                    load: match start {
                        LayerStart::Clear(order) => wgpu::LoadOp::Clear(order.far()),
                        LayerStart::Over => wgpu::LoadOp::Load,
                    },
                    // Kept: a layer's depth is copied (`copy_from`) and drawn over.
                    store: wgpu::StoreOp::Store,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: timestamps,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        if let Some(rect) = scissor {
            if rect.is_empty() {
                return;
            }
            pass.set_scissor_rect(rect.x, rect.y, rect.width, rect.height);
        }
        if !corners.is_empty() {
            pass.set_pipeline(pipeline);
            pass.set_bind_group(0, bind_group, &[]);
            pass.set_vertex_buffer(0, scene.vertices.slice(..));
            pass.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
            pass.draw_indexed(corners, 0, layer..layer + 1);
        }
    }

    /// The colour targets a pass draws, in attachment order: none in depth-only targets.
    fn drawn_colour(&self) -> impl Iterator<Item = &wgpu::Texture> {
        let drawn = if self.depth_only { 0 } else { 3 };
        [&self.position, &self.normal, &self.albedo]
            .into_iter()
            .take(drawn)
    }

    /// Copy every layer of every drawn target, depth included, from `source` (same size and
    /// kind).
    fn copy_from(&self, encoder: &mut wgpu::CommandEncoder, source: &Targets) {
        for (from, to) in source
            .drawn_colour()
            .chain([&source.depth])
            .zip(self.drawn_colour().chain([&self.depth]))
        {
            encoder.copy_texture_to_texture(from.as_image_copy(), to.as_image_copy(), from.size());
        }
    }

    /// [`copy_from`](Self::copy_from) of one layer.
    fn copy_layer_from(&self, encoder: &mut wgpu::CommandEncoder, source: &Targets, layer: u32) {
        for (from, to) in source
            .drawn_colour()
            .chain([&source.depth])
            .zip(self.drawn_colour().chain([&self.depth]))
        {
            let at = |texture| wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: 0,
                origin: wgpu::Origin3d {
                    x: 0,
                    y: 0,
                    z: layer,
                },
                aspect: wgpu::TextureAspect::All,
            };
            let size = wgpu::Extent3d {
                depth_or_array_layers: 1,
                ..from.size()
            };
            encoder.copy_texture_to_texture(at(from), at(to), size);
        }
    }
}

/// One light face (layer) of the maps [`RsmPass::render`] redraws: R^ρ over a copy of R^μ, and
/// R^μ first when `mu` (else R^μ still holds this frame's real scene and lights).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LayerRedraw {
    pub layer: u32,
    pub mu: bool,
}

/// How [`Targets::draw`] begins a layer.
#[derive(Debug, Clone, Copy)]
enum LayerStart {
    /// Cleared: colour to zero (a G-buffer's position w, its material index + 1, to nothing; an
    /// RSM's albedo w to "nothing drawn"), depth to the far plane of its [`DepthOrder`].
    Clear(DepthOrder),
    /// Drawn over, colour and depth as the layer holds them.
    Over,
}

/// Which way a target's depth runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DepthOrder {
    /// 0 at the near plane, 1 at the far one: the shadow maps, whose depths `lit`
    /// (`shaders/common.wgsl`) compares with a point's.
    Forward,
    /// 1 at the near plane, 0 at infinity (`gpu_scene::camera_uniform`): the camera's
    /// G-buffers. An f32 depth then steps by about 1e-7 of the distance everywhere; forward,
    /// with the near plane at 1e-4 of the far one, it stepped by 0.5 mm at 2 m, and a box sunk
    /// 2 mm into the floor showed through it along its foot (desk_box, `differential`'s Δ
    /// 0.26 → 0.88 at 160 × 120).
    Reversed,
}

impl DepthOrder {
    fn compare(self) -> wgpu::CompareFunction {
        match self {
            Self::Forward => wgpu::CompareFunction::Less,
            Self::Reversed => wgpu::CompareFunction::Greater,
        }
    }

    fn far(self) -> f32 {
        match self {
            Self::Forward => 1.0,
            Self::Reversed => 0.0,
        }
    }
}

/// A raster pipeline whose vertex entry is `vertex` and whose fragment entry `fragment` writes
/// `targets` (in attachment order); without a fragment entry it writes depth alone.
fn raster_pipeline(
    ctx: &GpuContext,
    label: &str,
    source: &str,
    (vertex, fragment): (&str, Option<&str>),
    targets: &[wgpu::TextureFormat],
    order: DepthOrder,
) -> wgpu::RenderPipeline {
    let module = shaders::module(&ctx.device, label, source);
    let targets: Vec<Option<wgpu::ColorTargetState>> = targets
        .iter()
        .map(|&format| {
            Some(wgpu::ColorTargetState {
                format,
                blend: None,
                write_mask: wgpu::ColorWrites::ALL,
            })
        })
        .collect();
    ctx.device
        .create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some(label),
            layout: None,
            vertex: wgpu::VertexState {
                module: &module,
                entry_point: Some(vertex),
                compilation_options: Default::default(),
                buffers: &[Some(GpuVertex::LAYOUT)],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::TriangleList,
                cull_mode: None,
                ..Default::default()
            },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: DEPTH,
                depth_write_enabled: Some(true),
                depth_compare: Some(order.compare()),
                stencil: Default::default(),
                bias: Default::default(),
            }),
            multisample: Default::default(),
            fragment: fragment.map(|entry| wgpu::FragmentState {
                module: &module,
                entry_point: Some(entry),
                compilation_options: Default::default(),
                targets: &targets,
            }),
            multiview_mask: None,
            cache: None,
        })
}

/// The camera G-buffer pass.
#[derive(Debug)]
pub struct GBufferPass {
    pipeline: wgpu::RenderPipeline,
}

impl GBufferPass {
    pub fn new(ctx: &GpuContext) -> Self {
        Self {
            pipeline: raster_pipeline(
                ctx,
                "gbuffer",
                shaders::GBUFFER,
                ("vs_main", Some("fs_main")),
                &ALL_TARGETS,
                DepthOrder::Reversed,
            ),
        }
    }

    pub fn bind_group(
        &self,
        ctx: &GpuContext,
        camera: &wgpu::Buffer,
        scene: &GpuScene,
    ) -> wgpu::BindGroup {
        shaders::bind_group(
            &ctx.device,
            "gbuffer",
            &self.pipeline.get_bind_group_layout(0),
            &[
                camera.as_entire_binding(),
                scene.materials.as_entire_binding(),
            ],
        )
    }

    /// Render the μ G-buffer (the real meshes) and the ρ one (every mesh). As with the shadow
    /// maps ([`RsmPass::render`]), μ is drawn with its depth kept and copied into ρ, and only
    /// the virtual object is drawn over the copy: the real meshes (the live depth mesh) are
    /// rasterised once. With `real_within`, the real meshes are drawn inside its rectangle
    /// alone ([`shadow_reach`](crate::shadow_reach)), and every pixel outside it holds no real
    /// surface.
    pub fn render(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        scene: &GpuScene,
        (rho, mu): (&Targets, &Targets),
        real_within: Option<RealWithin>,
        mut timer: Option<&mut GpuTimer>,
    ) -> Work {
        let (real, scissor) = match real_within {
            Some(within) => ((within.indices, 0..within.count), Some(within.rect)),
            None => ((&scene.indices, 0..scene.real_indices), None),
        };
        let timestamp_writes = timer
            .as_deref_mut()
            .and_then(|t| t.render(encoder, "gpu.gbuffer"));
        mu.draw(
            encoder,
            &self.pipeline,
            bind_group,
            scene,
            real,
            0,
            LayerStart::Clear(DepthOrder::Reversed),
            scissor,
            timestamp_writes,
        );
        rho.copy_from(encoder, mu);
        let timestamp_writes = timer.and_then(|t| t.render(encoder, "gpu.gbuffer"));
        rho.draw(
            encoder,
            &self.pipeline,
            bind_group,
            scene,
            (&scene.indices, scene.real_indices..scene.all_indices),
            0,
            LayerStart::Over,
            None,
            timestamp_writes,
        );
        let (texels, texel_bytes) = (mu.layer_texels(), mu.texel_bytes());
        // Within a rectangle, the real triangles that can cover it and its texels are the work.
        let (real_corners, real_texels) =
            real_within.map_or((scene.real_indices, texels), |w| (w.count, w.rect.area()));
        roofline::raster(real_corners, real_texels, texel_bytes)
            + roofline::copy(texels * texel_bytes)
            + roofline::raster(scene.all_indices - scene.real_indices, 0, 0)
    }
}

/// The real meshes' part of the camera's G-buffer when only a rectangle of it is needed: the
/// scissor, and the triangles that can cover it (`count` indices of `indices`, into
/// [`GpuScene::vertices`]).
#[derive(Debug, Clone, Copy)]
pub struct RealWithin<'a> {
    pub rect: PixelRect,
    pub indices: &'a wgpu::Buffer,
    pub count: u32,
}

/// The reflective-shadow-map pass: one layer per light face.
#[derive(Debug)]
pub struct RsmPass {
    pipeline: wgpu::RenderPipeline,
    depth_only: bool,
}

/// The formats of a full G-buffer or RSM, in attachment order.
const ALL_TARGETS: [wgpu::TextureFormat; 3] = [POSITION, NORMAL, ALBEDO];

impl RsmPass {
    pub fn new(ctx: &GpuContext) -> Self {
        Self {
            pipeline: raster_pipeline(
                ctx,
                "rsm",
                shaders::RSM,
                ("vs_main", Some("fs_main")),
                &ALL_TARGETS,
                DepthOrder::Forward,
            ),
            depth_only: false,
        }
    }

    /// Shadow maps for visibility alone: the depth only (no fragment stage), into
    /// [`Targets::depth_only`].
    pub fn depth_only(ctx: &GpuContext) -> Self {
        Self {
            pipeline: raster_pipeline(
                ctx,
                "rsm depth",
                shaders::RSM,
                ("vs_depth", None),
                &[],
                DepthOrder::Forward,
            ),
            depth_only: true,
        }
    }

    /// The pass's name in the frame's work and timings: `shadow` for depth alone, `rsm` for
    /// the full maps.
    pub fn name(&self) -> &'static str {
        if self.depth_only { "shadow" } else { "rsm" }
    }

    pub fn bind_group(
        &self,
        ctx: &GpuContext,
        lights: &wgpu::Buffer,
        faces: &wgpu::Buffer,
        scene: &GpuScene,
    ) -> wgpu::BindGroup {
        let layout = self.pipeline.get_bind_group_layout(0);
        if self.depth_only {
            // The depth alone reads the faces (binding 1) and nothing else, so its layout has
            // that binding alone.
            return ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("rsm depth"),
                layout: &layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 1,
                    resource: faces.as_entire_binding(),
                }],
            });
        }
        shaders::bind_group(
            &ctx.device,
            "rsm",
            &layout,
            &[
                lights.as_entire_binding(),
                faces.as_entire_binding(),
                scene.materials.as_entire_binding(),
            ],
        )
    }

    /// Render R^μ (the real meshes) and R^ρ (every mesh) into every face (layer) of their
    /// targets, one layer per light face. R^ρ differs from R^μ only where the virtual object is
    /// in front, so R^μ is drawn with its depth kept, copied into R^ρ, and only the object's
    /// triangles are drawn over the copy: the real meshes (a live depth mesh of tens of
    /// thousands of triangles) are rasterised once per face, not twice. The real meshes are
    /// [`GpuScene::shadow_real`] (a scene's shadow proxy, where it has one).
    ///
    /// `redraw` says which faces to draw, and in which of them R^μ too: a light that did not
    /// change keeps its faces, one that moved redraws its own alone.
    pub fn render(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        bind_group: &wgpu::BindGroup,
        scene: &GpuScene,
        (rho, mu): (&Targets, &Targets),
        redraw: &[LayerRedraw],
        mut timer: Option<&mut GpuTimer>,
    ) -> Work {
        let timing = if self.depth_only {
            "gpu.shadow"
        } else {
            "gpu.rsm"
        };
        let (texels, texel_bytes) = (mu.layer_texels(), mu.texel_bytes());
        let real = scene.shadow_real.end - scene.shadow_real.start;
        let mut work = roofline::copy(texels * texel_bytes).times(redraw.len() as f64);
        for face in redraw.iter().filter(|r| r.mu) {
            work = work + roofline::raster(real, texels, texel_bytes);
            let timestamp_writes = timer.as_deref_mut().and_then(|t| t.render(encoder, timing));
            mu.draw(
                encoder,
                &self.pipeline,
                bind_group,
                scene,
                (&scene.indices, scene.shadow_real.clone()),
                face.layer,
                LayerStart::Clear(DepthOrder::Forward),
                None,
                timestamp_writes,
            );
        }
        for face in redraw {
            rho.copy_layer_from(encoder, mu, face.layer);
        }
        let virtual_indices = scene.real_indices..scene.all_indices;
        if !virtual_indices.is_empty() {
            for face in redraw {
                let timestamp_writes = timer.as_deref_mut().and_then(|t| t.render(encoder, timing));
                rho.draw(
                    encoder,
                    &self.pipeline,
                    bind_group,
                    scene,
                    (&scene.indices, virtual_indices.clone()),
                    face.layer,
                    LayerStart::Over,
                    None,
                    timestamp_writes,
                );
            }
        }
        work + roofline::raster(scene.all_indices - scene.real_indices, 0, 0)
            .times(redraw.len() as f64)
    }
}
