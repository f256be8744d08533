//! Offline references kept on disk, so the bench renders each scene's reference once rather than
//! on every run (a refined one takes minutes on a CPU). An entry is keyed by everything its
//! pixels depend on: every file of the scene directory (names and bytes), the render size, the
//! offline reference settings and [`relight_reference::REVISION`]; the key is FNV-1a over
//! those bytes, written out here because it must stay the same across toolchains (std's
//! `DefaultHasher` may change) and a hash crate would add a dependency for eight lines.
//!
//! An entry is one file, `<key>.ref`: a header (magic, width, height, spp) and the five images
//! and the virtual mask as little-endian f32 and bytes. A file that does not read back whole
//! is ignored (and rendered again), never trusted.

use std::io;
use std::path::{Path, PathBuf};

use glam::Vec3;

use crate::offline::{Sampling, Transport};
use crate::reference::{REVISION, ReferenceImages};

const MAGIC: &[u8; 8] = b"RLREF\x00\x00\x01";

/// FNV-1a, 64 bit.
struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
}

/// A directory of cached references.
#[derive(Debug, Clone)]
pub struct ReferenceCache {
    dir: PathBuf,
}

impl ReferenceCache {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }

    /// The key of the offline reference ([`crate::offline::reference_renderer`]) of the scene
    /// in `scene_dir` at `width × height`, sampling pixels as `sampling` says and carrying
    /// `transport`.
    pub fn key(
        scene_dir: &Path,
        width: u32,
        height: u32,
        sampling: Sampling,
        transport: Transport,
    ) -> io::Result<u64> {
        Self::key_of_view(scene_dir, width, height, sampling, transport, "")
    }

    /// [`Self::key`] of the scene seen otherwise than its file says: `view` names what differs
    /// (`relightd score`'s truth frames: the true camera pose, lights and samples). An empty
    /// `view` is the scene file's own key.
    pub fn key_of_view(
        scene_dir: &Path,
        width: u32,
        height: u32,
        sampling: Sampling,
        transport: Transport,
        view: &str,
    ) -> io::Result<u64> {
        let mut files: Vec<PathBuf> = std::fs::read_dir(scene_dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        let mut hash = Fnv::new();
        hash.write(MAGIC);
        hash.write(&REVISION.to_le_bytes());
        hash.write(
            format!(
                "{:?}",
                crate::offline::reference_settings(width, height, 0, sampling, transport)
            )
            .as_bytes(),
        );
        hash.write(view.as_bytes());
        for file in files {
            let name = file.file_name().unwrap_or_default().to_string_lossy();
            hash.write(name.as_bytes());
            let bytes = std::fs::read(&file)?;
            hash.write(&(bytes.len() as u64).to_le_bytes());
            hash.write(&bytes);
        }
        Ok(hash.0)
    }

    fn path(&self, key: u64) -> PathBuf {
        self.dir.join(format!("{key:016x}.ref"))
    }

    /// The cached reference of `key`, if one reads back whole.
    pub fn load(&self, key: u64) -> Option<ReferenceImages> {
        decode(&std::fs::read(self.path(key)).ok()?)
    }

    /// Keep `images` as the reference of `key` (written to a temporary name, then renamed, so
    /// a reader never sees half a file).
    pub fn store(&self, key: u64, images: &ReferenceImages) -> io::Result<()> {
        std::fs::create_dir_all(&self.dir)?;
        let path = self.path(key);
        let partial = path.with_extension("ref.partial");
        std::fs::write(&partial, encode(images))?;
        std::fs::rename(partial, path)
    }
}

fn images(r: &ReferenceImages) -> [&Vec<Vec3>; 5] {
    [
        &r.l_rho,
        &r.l_mu,
        &r.delta,
        &r.delta_std_error,
        &r.l_rho_std_error,
    ]
}

fn encode(r: &ReferenceImages) -> Vec<u8> {
    let mut out = MAGIC.to_vec();
    for n in [r.width, r.height, r.spp] {
        out.extend(n.to_le_bytes());
    }
    for image in images(r) {
        for v in image {
            for c in v.to_array() {
                out.extend(c.to_le_bytes());
            }
        }
    }
    out.extend(r.virtual_mask.iter().map(|&m| u8::from(m)));
    out
}

fn decode(bytes: &[u8]) -> Option<ReferenceImages> {
    let rest = bytes.strip_prefix(MAGIC)?;
    let u32_at = |i: usize| {
        Some(u32::from_le_bytes(
            rest.get(4 * i..4 * i + 4)?.try_into().ok()?,
        ))
    };
    let (width, height, spp) = (u32_at(0)?, u32_at(1)?, u32_at(2)?);
    let n = usize::try_from(u64::from(width) * u64::from(height)).ok()?;
    let body = rest.get(12..)?;
    if body.len() != n.checked_mul(5 * 12 + 1)? {
        return None;
    }
    let image = |k: usize| -> Vec<Vec3> {
        body[k * n * 12..(k + 1) * n * 12]
            .chunks_exact(12)
            .map(|px| {
                let c = |i: usize| f32::from_le_bytes(px[4 * i..4 * i + 4].try_into().expect("4"));
                Vec3::new(c(0), c(1), c(2))
            })
            .collect()
    };
    Some(ReferenceImages {
        width,
        height,
        spp,
        l_rho: image(0),
        l_mu: image(1),
        delta: image(2),
        delta_std_error: image(3),
        l_rho_std_error: image(4),
        virtual_mask: body[5 * n * 12..].iter().map(|&b| b != 0).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> ReferenceImages {
        let v = |k: f32| (0..6).map(|i| Vec3::new(i as f32, k, -k * 0.5)).collect();
        ReferenceImages {
            width: 3,
            height: 2,
            spp: 64,
            l_rho: v(1.0),
            l_mu: v(2.0),
            delta: v(-1.0),
            delta_std_error: v(0.01),
            l_rho_std_error: v(0.02),
            virtual_mask: vec![true, false, false, true, false, false],
        }
    }

    #[test]
    fn a_stored_reference_reads_back_and_a_damaged_one_is_ignored() {
        let dir = tempfile::tempdir().unwrap();
        let cache = ReferenceCache::new(dir.path().join("refs"));
        assert!(cache.load(7).is_none());
        cache.store(7, &sample()).unwrap();
        assert_eq!(cache.load(7), Some(sample()));
        let path = cache.path(7);
        let mut bytes = std::fs::read(&path).unwrap();
        bytes.pop();
        std::fs::write(&path, &bytes).unwrap();
        assert!(cache.load(7).is_none(), "a cut file is not trusted");
    }

    #[test]
    fn the_key_follows_the_scene_files_the_size_the_sampling_the_transport_and_the_view() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("scene.toml"), "gltf = \"a.gltf\"\n").unwrap();
        let key_of = |w, h, sampling| {
            ReferenceCache::key(dir.path(), w, h, sampling, Transport::Full).unwrap()
        };
        let key = key_of(16, 12, Sampling::Centre);
        assert_eq!(key, key_of(16, 12, Sampling::Centre));
        assert_ne!(key, key_of(16, 13, Sampling::Centre));
        assert_ne!(key, key_of(16, 12, Sampling::Area));
        assert_ne!(
            key,
            ReferenceCache::key(dir.path(), 16, 12, Sampling::Centre, Transport::Direct).unwrap()
        );
        let view = |view| {
            ReferenceCache::key_of_view(dir.path(), 16, 12, Sampling::Centre, Transport::Full, view)
                .unwrap()
        };
        assert_eq!(key, view(""));
        assert_ne!(key, view("pose a"));
        assert_ne!(view("pose a"), view("pose b"));
        std::fs::write(dir.path().join("scene.toml"), "gltf = \"b.gltf\"\n").unwrap();
        assert_ne!(key, key_of(16, 12, Sampling::Centre));
    }
}
