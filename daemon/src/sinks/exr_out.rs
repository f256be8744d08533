//! OpenEXR output of linear HDR images (Δ may be negative; EXR keeps it).

use std::io::BufWriter;
use std::path::Path;

use exr::prelude::{Image, SpecificChannels, Vec2, WritableImage as _};
use glam::Vec3;

use super::safe_file::{Existing, create_regular};

#[derive(Debug, thiserror::Error)]
pub enum ExrError {
    #[error("{path}: {width}×{height} image needs {expected} pixels, got {actual}")]
    Size {
        path: String,
        width: u32,
        height: u32,
        expected: usize,
        actual: usize,
    },
    #[error("cannot create {path}: {source}")]
    Create {
        path: String,
        source: std::io::Error,
    },
    #[error("cannot write {path}: {source}")]
    Write {
        path: String,
        source: exr::error::Error,
    },
}

/// Write row-major linear RGB pixels as a 32-bit float EXR, replacing a file already there.
pub fn write_exr(path: &Path, width: u32, height: u32, pixels: &[Vec3]) -> Result<(), ExrError> {
    write_exr_as(path, width, height, pixels, Existing::Replace)
}

/// [`write_exr`] into a file created as [`create_regular`] creates it: a regular file only,
/// no final symbolic link followed, an existing one refused unless `existing` says replace.
pub fn write_exr_as(
    path: &Path,
    width: u32,
    height: u32,
    pixels: &[Vec3],
    existing: Existing,
) -> Result<(), ExrError> {
    let name = path.display().to_string();
    let expected = width as usize * height as usize;
    if pixels.len() != expected {
        return Err(ExrError::Size {
            path: name,
            width,
            height,
            expected,
            actual: pixels.len(),
        });
    }
    let file = create_regular(path, existing).map_err(|source| ExrError::Create {
        path: name.clone(),
        source,
    })?;
    let w = width as usize;
    let channels = SpecificChannels::rgb(|position: Vec2<usize>| {
        let p = pixels[position.y() * w + position.x()];
        (p.x, p.y, p.z)
    });
    Image::from_channels((w, height as usize), channels)
        .write()
        .to_buffered(BufWriter::new(file))
        .map_err(|source| ExrError::Write { path: name, source })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn negative_and_huge_values_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("delta.exr");
        let pixels = vec![Vec3::new(-0.25, 1e4, 0.0), Vec3::new(0.5, -1e-3, 3.0)];
        write_exr(&path, 2, 1, &pixels).unwrap();
        let image = exr::prelude::read_first_rgba_layer_from_file(
            &path,
            |resolution, _| vec![Vec3::ZERO; resolution.width() * resolution.height()],
            |buffer: &mut Vec<Vec3>, position, (r, g, b, _a): (f32, f32, f32, f32)| {
                buffer[position.y() * 2 + position.x()] = Vec3::new(r, g, b);
            },
        )
        .unwrap();
        assert_eq!(image.layer_data.channel_data.pixels, pixels);
    }

    #[test]
    fn an_existing_file_is_refused_unless_replacing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("env.exr");
        let pixels = [Vec3::ONE];
        write_exr_as(&path, 1, 1, &pixels, Existing::Refuse).unwrap();
        let err = write_exr_as(&path, 1, 1, &pixels, Existing::Refuse).unwrap_err();
        assert!(matches!(err, ExrError::Create { .. }), "{err}");
        write_exr_as(&path, 1, 1, &pixels, Existing::Replace).unwrap();
    }

    #[test]
    fn wrong_pixel_count_is_an_error() {
        let err = write_exr(Path::new("x.exr"), 2, 2, &[Vec3::ZERO]).unwrap_err();
        assert!(err.to_string().contains("needs 4 pixels, got 1"));
    }
}
