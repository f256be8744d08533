//! `relightd gpu`: the adapters wgpu sees, numbered as `RELIGHT_ADAPTER=#N` takes them, which
//! one relightd would choose, and the GPU device nodes present (a GPU node without a GPU adapter
//! is a missing Vulkan driver, or a device policy that hides it).

use anyhow::Result;
use relight_engines::gpu::{ADAPTER_ENV, adapters, gpu_device_nodes};

pub fn run() -> Result<()> {
    let (adapters, preferred) = adapters();
    if adapters.is_empty() {
        println!("no adapters (neither Vulkan nor OpenGL)");
    }
    let forced = std::env::var(ADAPTER_ENV)
        .ok()
        .filter(|s| !s.trim().is_empty());
    for adapter in &adapters {
        let mark = if preferred == Some(adapter.index) && forced.is_none() {
            "  <- chosen"
        } else {
            ""
        };
        println!("{adapter}{mark}");
    }
    if let Some(forced) = forced {
        println!("{ADAPTER_ENV}={forced} chooses the adapter");
    }
    let nodes = gpu_device_nodes();
    if nodes.is_empty() {
        println!("GPU device nodes: none");
    } else {
        let nodes: Vec<String> = nodes.iter().map(|n| n.display().to_string()).collect();
        println!("GPU device nodes: {}", nodes.join(" "));
    }
    Ok(())
}
