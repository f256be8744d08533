//! Any scene directory: the input is `scene.toml`, a 0xFF byte, then `scene.gltf` (glTF JSON or
//! binary). Loading never panics and never reads outside the directory.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relight_core::scene::Scene;

fuzz_target!(|data: &[u8]| {
    let (toml, gltf) = match data.iter().position(|&b| b == 0xff) {
        Some(at) => (&data[..at], &data[at + 1..]),
        None => (data, &[][..]),
    };
    let Ok(dir) = tempfile::tempdir() else {
        return;
    };
    if std::fs::write(dir.path().join("scene.toml"), toml).is_err()
        || std::fs::write(dir.path().join("scene.gltf"), gltf).is_err()
    {
        return;
    }
    let _ = Scene::load(dir.path());
});
