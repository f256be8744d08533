//! Every WGSL pass, each with `shaders/common.wgsl` in front (WGSL has no includes). The list
//! [`ALL`] is what the naga validation test walks, so a pass that is not listed here is a test
//! failure waiting to happen: add new passes to it.

macro_rules! pass {
    ($file:literal) => {
        concat!(
            include_str!("../../shaders/common.wgsl"),
            "\n",
            include_str!(concat!("../../shaders/", $file))
        )
    };
}

pub const GBUFFER: &str = pass!("gbuffer.wgsl");
pub const RSM: &str = pass!("rsm.wgsl");
pub const SHADE: &str = pass!("shade.wgsl");
pub const DLPV_INJECT: &str = pass!("dlpv_inject.wgsl");
pub const DLPV_RESOLVE: &str = pass!("dlpv_resolve.wgsl");
pub const DLPV_PROPAGATE: &str = pass!("dlpv_propagate.wgsl");
pub const DLPV_LOOKUP: &str = pass!("dlpv_lookup.wgsl");

/// (file name, full source) of every pass.
pub const ALL: &[(&str, &str)] = &[
    ("gbuffer.wgsl", GBUFFER),
    ("rsm.wgsl", RSM),
    ("shade.wgsl", SHADE),
    ("dlpv_inject.wgsl", DLPV_INJECT),
    ("dlpv_resolve.wgsl", DLPV_RESOLVE),
    ("dlpv_propagate.wgsl", DLPV_PROPAGATE),
    ("dlpv_lookup.wgsl", DLPV_LOOKUP),
];

/// Compile a pass into a shader module.
pub fn module(device: &wgpu::Device, name: &str, source: &str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(name),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    })
}
