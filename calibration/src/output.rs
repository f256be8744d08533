//! Writing a rig's calibration file: one TOML per rig
//! ([`RigCalibration::to_toml`]), merged into the file already there so that a run replaces only
//! what it calibrated, and written atomically — a temporary file in the same directory, flushed
//! to disk, then renamed over the target — so that a reader (or `relightd` reloading it) sees
//! either the old file or the new one, never a partial one, and a failed run leaves the old file
//! as it was.
//!
//! Callers write the file last, after every computation and every report has succeeded.

use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use relight_core::Pose;
use relight_core::camera::CameraModel;
use relight_core::rig::{RigCalibration, RigCalibrationError};

/// Why the calibration file was not written (the target is then untouched).
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{path} exists but is not a rig calibration ({source}); refusing to overwrite it — \
         fix or remove it, or write to another file"
    )]
    Existing {
        path: PathBuf,
        #[source]
        source: RigCalibrationError,
    },
    #[error("serialising the calibration: {0}")]
    Serialize(#[source] RigCalibrationError),
    #[error("the serialised calibration does not load back ({0}); nothing written")]
    RoundTrip(#[source] RigCalibrationError),
    #[error("{path} has no file name")]
    NoFileName { path: PathBuf },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> OutputError + '_ {
    move |source| OutputError::Io {
        path: path.to_owned(),
        source,
    }
}

/// The parts of a [`RigCalibration`] one run determined; `None` leaves the existing value.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CalibratedParts {
    pub name: Option<String>,
    pub depth: Option<CameraModel>,
    pub color: Option<CameraModel>,
    pub probe: Option<CameraModel>,
    pub color_from_depth: Option<Pose>,
    pub world_from_probe: Option<Pose>,
    pub lamp_marker_from_light: Option<Pose>,
    pub probe_response: Option<Vec<f32>>,
    pub probe_radiance_scale: Option<f32>,
    pub probe_vignetting: Option<Vec<f32>>,
}

impl CalibratedParts {
    /// Whether the run determined nothing.
    pub fn is_empty(&self) -> bool {
        self == &Self::default()
    }

    /// `base` with every part this run determined replaced.
    pub fn merged_into(&self, mut base: RigCalibration) -> RigCalibration {
        if let Some(name) = &self.name {
            base.name.clone_from(name);
        }
        if let Some(model) = self.depth {
            base.depth = Some(model);
        }
        if let Some(model) = self.color {
            base.color = Some(model);
        }
        if let Some(model) = self.probe {
            base.probe = Some(model);
        }
        if let Some(pose) = self.color_from_depth {
            base.color_from_depth = pose;
        }
        if let Some(pose) = self.world_from_probe {
            base.world_from_probe = pose;
        }
        if let Some(pose) = self.lamp_marker_from_light {
            base.lamp_marker_from_light = pose;
        }
        if let Some(table) = &self.probe_response {
            base.probe_response.clone_from(table);
        }
        if let Some(scale) = self.probe_radiance_scale {
            base.probe_radiance_scale = scale;
        }
        if let Some(coefficients) = &self.probe_vignetting {
            base.probe_vignetting.clone_from(coefficients);
        }
        base
    }
}

/// The calibration at `path`, if a file is there.
pub fn read_existing(path: &Path) -> Result<Option<RigCalibration>, OutputError> {
    match fs::read_to_string(path) {
        Ok(text) => RigCalibration::from_toml(&text)
            .map(Some)
            .map_err(|source| OutputError::Existing {
                path: path.to_owned(),
                source,
            }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(OutputError::Io {
            path: path.to_owned(),
            source,
        }),
    }
}

/// Merges `parts` into the calibration at `path` (or a default one when there is none) and
/// writes the result atomically; returns what was written. The TOML is checked to load back
/// before anything touches the disk.
pub fn write_calibration(
    path: &Path,
    parts: &CalibratedParts,
) -> Result<RigCalibration, OutputError> {
    let base = read_existing(path)?.unwrap_or_default();
    let merged = parts.merged_into(base);
    let text = merged.to_toml().map_err(OutputError::Serialize)?;
    RigCalibration::from_toml(&text).map_err(OutputError::RoundTrip)?;
    write_atomically(path, text.as_bytes())?;
    tracing::info!(path = %path.display(), "calibration written");
    Ok(merged)
}

/// Writes `contents` to `path` through a temporary file in the same directory (so the rename
/// cannot cross file systems), flushed with `fsync` before the rename and the directory flushed
/// after it. An existing file keeps its permissions. On any error the temporary file is removed
/// and `path` is untouched.
pub fn write_atomically(path: &Path, contents: &[u8]) -> Result<(), OutputError> {
    let file_name = path.file_name().ok_or_else(|| OutputError::NoFileName {
        path: path.to_owned(),
    })?;
    let directory = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.to_owned(),
        _ => PathBuf::from("."),
    };
    let permissions = fs::metadata(path).ok().map(|m| m.permissions());
    let (temp_path, mut file) = create_temp(&directory, file_name)?;
    let written = (|| {
        file.write_all(contents).map_err(io(&temp_path))?;
        if let Some(permissions) = permissions {
            file.set_permissions(permissions).map_err(io(&temp_path))?;
        }
        file.sync_all().map_err(io(&temp_path))?;
        drop(file);
        fs::rename(&temp_path, path).map_err(io(path))
    })();
    if let Err(e) = written {
        // The temporary file is ours alone; a failure to remove it changes nothing for `path`.
        let _ = fs::remove_file(&temp_path);
        return Err(e);
    }
    // Makes the rename itself durable; not every platform can open a directory for this.
    if let Ok(dir) = File::open(&directory) {
        dir.sync_all().map_err(io(&directory))?;
    }
    Ok(())
}

/// A new file `.<name>.<pid>.<n>.tmp` beside the target, created exclusively.
fn create_temp(
    directory: &Path,
    file_name: &std::ffi::OsStr,
) -> Result<(PathBuf, File), OutputError> {
    let pid = std::process::id();
    let mut last_error = None;
    for attempt in 0..100u32 {
        let mut name = std::ffi::OsString::from(".");
        name.push(file_name);
        name.push(format!(".{pid}.{attempt}.tmp"));
        let candidate = directory.join(name);
        match OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&candidate)
        {
            Ok(file) => return Ok((candidate, file)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last_error = Some(e),
            Err(source) => {
                return Err(OutputError::Io {
                    path: candidate,
                    source,
                });
            }
        }
    }
    Err(OutputError::Io {
        path: directory.to_owned(),
        source: last_error.unwrap_or_else(|| std::io::Error::other("no temporary name free")),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use relight_core::camera::Pinhole;

    fn pinhole(fx: f64) -> CameraModel {
        CameraModel::Pinhole(Pinhole {
            width: 64,
            height: 48,
            fx,
            fy: fx,
            cx: 31.5,
            cy: 23.5,
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        })
    }

    fn entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn a_new_file_holds_exactly_the_calibrated_parts() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rig.toml");
        let parts = CalibratedParts {
            color: Some(pinhole(50.0)),
            ..Default::default()
        };
        let written = write_calibration(&path, &parts).unwrap();
        let loaded = RigCalibration::from_toml(&fs::read_to_string(&path).unwrap()).unwrap();
        assert_eq!(loaded, written);
        assert_eq!(loaded.color, Some(pinhole(50.0)));
        assert_eq!(loaded.depth, None);
        assert_eq!(
            entries(dir.path()),
            vec!["rig.toml"],
            "no temporary file left"
        );
    }

    #[test]
    fn merging_replaces_only_what_was_calibrated() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rig.toml");
        let existing = RigCalibration {
            name: "desk".into(),
            depth: Some(pinhole(40.0)),
            color: Some(pinhole(50.0)),
            probe_response: vec![0.5; 256],
            probe_radiance_scale: 3.0,
            ..Default::default()
        };
        fs::write(&path, existing.to_toml().unwrap()).unwrap();
        let parts = CalibratedParts {
            color: Some(pinhole(55.0)),
            probe_response: Some((0..256).map(|m| m as f32 / 128.0).collect()),
            ..Default::default()
        };
        let written = write_calibration(&path, &parts).unwrap();
        assert_eq!(written.name, "desk");
        assert_eq!(written.depth, Some(pinhole(40.0)));
        assert_eq!(written.color, Some(pinhole(55.0)));
        assert_eq!(written.probe_response[128], 1.0);
        assert_eq!(written.probe_radiance_scale, 3.0);
        let loaded = RigCalibration::from_toml(&fs::read_to_string(&path).unwrap()).unwrap();
        assert_eq!(loaded, written);
    }

    #[test]
    fn an_unreadable_existing_file_is_left_untouched() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rig.toml");
        let garbage = "this is = = not a calibration\n";
        fs::write(&path, garbage).unwrap();
        let parts = CalibratedParts {
            color: Some(pinhole(55.0)),
            ..Default::default()
        };
        let error = write_calibration(&path, &parts).unwrap_err();
        assert!(matches!(error, OutputError::Existing { .. }), "{error}");
        assert_eq!(fs::read_to_string(&path).unwrap(), garbage);
        assert_eq!(entries(dir.path()), vec!["rig.toml"]);
    }

    #[test]
    fn a_failed_write_leaves_no_file_and_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        // The target is a directory: the rename fails after the temporary file was written.
        let path = dir.path().join("rig.toml");
        fs::create_dir(&path).unwrap();
        fs::write(path.join("inside"), "x").unwrap();
        let error = write_atomically(&path, b"name = \"x\"\n").unwrap_err();
        assert!(matches!(error, OutputError::Io { .. }), "{error}");
        assert!(path.is_dir());
        assert_eq!(entries(dir.path()), vec!["rig.toml"]);
        // A directory that does not exist: nothing is created anywhere.
        let missing = dir.path().join("absent").join("rig.toml");
        assert!(write_atomically(&missing, b"x").is_err());
        assert!(!dir.path().join("absent").exists());
    }

    #[test]
    fn replacing_keeps_the_permissions_of_the_old_file() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rig.toml");
        fs::write(&path, "name = \"old\"\n").unwrap();
        fs::set_permissions(&path, fs::Permissions::from_mode(0o640)).unwrap();
        write_atomically(&path, b"name = \"new\"\n").unwrap();
        assert_eq!(fs::read_to_string(&path).unwrap(), "name = \"new\"\n");
        assert_eq!(
            fs::metadata(&path).unwrap().permissions().mode() & 0o777,
            0o640
        );
    }
}
