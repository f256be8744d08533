//! Every WGSL pass parses and validates with naga (no GPU needed), and every file in `shaders/`
//! is one of the listed passes (or the common prelude).

use relight_engines::shaders::ALL;

#[test]
fn every_pass_validates_with_naga() {
    for (name, source) in ALL {
        let module = naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(source)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("{name}: {}", e.emit_to_string(source)));
    }
}

#[test]
fn every_shader_file_is_a_listed_pass() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shaders");
    for entry in std::fs::read_dir(&dir).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        if name == "common.wgsl" {
            continue;
        }
        assert!(
            ALL.iter().any(|(pass, _)| *pass == name),
            "shaders/{name} is not in relight_engines::shaders::ALL"
        );
    }
}

/// Every pass reads its parameters from storage buffers (`shaders::PARAMS_USAGE` says why: on
/// lavapipe a uniform buffer's values that steer branches compile a shader variant per frame).
#[test]
fn no_pass_reads_a_uniform_buffer() {
    for (name, source) in ALL {
        let module = naga::front::wgsl::parse_str(source).unwrap();
        for (_, global) in module.global_variables.iter() {
            assert_ne!(
                global.space,
                naga::AddressSpace::Uniform,
                "{name}: `{}` is a uniform buffer; declare it `var<storage, read>`",
                global.name.as_deref().unwrap_or("?")
            );
        }
    }
}
