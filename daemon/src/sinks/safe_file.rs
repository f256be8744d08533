//! Creating output files (composites, snapshots, recordings) so that what a path names cannot
//! stall or redirect the writer: the last component is not followed if it is a link, the open
//! does not block (a FIFO with no reader fails at once instead of waiting for one), and anything
//! but a regular file is refused before a byte is written. A file a client names is created
//! exclusively unless it asked to replace it ([`Existing`]), and its path is checked first
//! ([`resolve_output`]): relative paths are taken from the output's own directory, never from
//! the daemon's working directory.

use std::fs::File;
use std::io;
use std::path::{Component, Path, PathBuf};

use rustix::fs::{FileType, Mode, OFlags};

/// What to do when the file to create already exists.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Existing {
    /// Fail (`overwrite` not asked for): a recording is never lost to a typo.
    Refuse,
    /// Truncate it, if it is a regular file (periodic outputs, `overwrite: true`).
    Replace,
}

impl Existing {
    pub fn from_overwrite(overwrite: bool) -> Self {
        if overwrite {
            Existing::Replace
        } else {
            Existing::Refuse
        }
    }
}

/// The directories a unit with `PrivateTmp=yes` gives the service to itself.
const PRIVATE_TMP_DIRS: [&str; 2] = ["/tmp", "/var/tmp"];

/// Whether this process runs as a systemd unit (systemd sets `INVOCATION_ID` for every unit).
fn under_systemd() -> bool {
    std::env::var_os("INVOCATION_ID").is_some()
}

fn invalid(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, message)
}

/// Where a requested output path points: relative paths are joined to `base` (the recordings
/// or snapshots directory). Refused: control characters (a newline in a file name breaks every
/// log and listing that shows it), `..` components (a client may not climb out of `base` or
/// anywhere else by indirection), and, under systemd, the unit's private `/tmp`, where a file
/// would be invisible to whoever asked for it.
pub fn resolve_output(path: &Path, base: &Path) -> io::Result<PathBuf> {
    let text = path.to_string_lossy();
    if let Some(c) = text.chars().find(|c| c.is_control()) {
        return Err(invalid(format!(
            "refusing {text:?}: the name holds the control character {c:?}"
        )));
    }
    if path.components().any(|c| c == Component::ParentDir) {
        return Err(invalid(format!(
            "refusing {}: `..` is not allowed in an output path; name a path under {} or an absolute one",
            path.display(),
            base.display()
        )));
    }
    let resolved = if path.is_relative() {
        base.join(path)
    } else {
        path.to_owned()
    };
    if under_systemd()
        && let Some(tmp) = PRIVATE_TMP_DIRS.iter().find(|d| resolved.starts_with(d))
    {
        return Err(invalid(format!(
            "refusing {}: the relightd service has a private {tmp} (PrivateTmp=yes), where you would never see the file; write under {} instead",
            resolved.display(),
            base.display()
        )));
    }
    Ok(resolved)
}

/// Create `path` for writing, as a regular file only; an existing one is refused or truncated
/// as `existing` says.
pub fn create_regular(path: &Path, existing: Existing) -> io::Result<File> {
    let mut flags = OFlags::WRONLY
        | OFlags::CREATE
        | OFlags::NOFOLLOW
        | OFlags::NONBLOCK
        | OFlags::NOCTTY
        | OFlags::CLOEXEC;
    if existing == Existing::Refuse {
        // With CREATE, EXCL also refuses a symbolic link, dangling or not.
        flags |= OFlags::EXCL;
    }
    let fd = rustix::fs::open(path, flags, Mode::from_raw_mode(0o644)).map_err(|errno| {
        let reason = match errno {
            rustix::io::Errno::EXIST => existing_kind_reason(path),
            rustix::io::Errno::LOOP => "it is a symbolic link; output is not written through links",
            rustix::io::Errno::NXIO => "it is a FIFO or socket; output goes to regular files only",
            rustix::io::Errno::ROFS if under_systemd() => {
                "read-only here: the relightd service may write only under its state directory /var/lib/relightd (ReadWritePaths in relightd.service)"
            }
            _ => {
                return io::Error::new(
                    io::Error::from(errno).kind(),
                    format!("cannot create {}: {errno}", path.display()),
                );
            }
        };
        invalid(format!("refusing {}: {reason}", path.display()))
    })?;
    let kind = FileType::from_raw_mode(rustix::fs::fstat(&fd)?.st_mode);
    if kind != FileType::RegularFile {
        return Err(invalid(format!(
            "refusing {}: it is a {kind:?}; output goes to regular files only",
            path.display()
        )));
    }
    rustix::fs::ftruncate(&fd, 0)?;
    rustix::fs::fcntl_setfl(&fd, OFlags::empty())?;
    Ok(File::from(fd))
}

/// Why an exclusive create found `path` taken, naming what is there: replacing a link or a
/// FIFO is refused even with overwrite, so "ask for overwrite" would mislead for those.
fn existing_kind_reason(path: &Path) -> &'static str {
    match rustix::fs::lstat(path).map(|stat| FileType::from_raw_mode(stat.st_mode)) {
        Ok(FileType::Symlink) => "it is a symbolic link; output is not written through links",
        Ok(FileType::Fifo | FileType::Socket) => {
            "it is a FIFO or socket; output goes to regular files only"
        }
        Ok(FileType::Directory) => "it is a directory",
        Ok(FileType::RegularFile) | Err(_) => {
            "it exists; ask for overwrite (`overwrite: true`, `--overwrite`) to replace it"
        }
        Ok(_) => "it is a device or other special file; output goes to regular files only",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write as _;

    fn mkfifo(path: &Path) -> PathBuf {
        rustix::fs::mknodat(
            rustix::fs::CWD,
            path,
            FileType::Fifo,
            Mode::from_raw_mode(0o644),
            0,
        )
        .unwrap();
        path.to_owned()
    }

    #[test]
    fn writes_regular_files_and_refuses_links_fifos_and_devices() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("out.png");
        std::fs::write(&file, b"old and longer").unwrap();
        create_regular(&file, Existing::Replace)
            .unwrap()
            .write_all(b"new")
            .unwrap();
        assert_eq!(std::fs::read(&file).unwrap(), b"new");

        let link = dir.path().join("link.png");
        std::os::unix::fs::symlink(&file, &link).unwrap();
        let error = create_regular(&link, Existing::Replace)
            .unwrap_err()
            .to_string();
        assert!(error.contains("symbolic link"), "{error}");
        assert_eq!(
            std::fs::read(&file).unwrap(),
            b"new",
            "the link's target is untouched"
        );

        let fifo = mkfifo(&dir.path().join("fifo.png"));
        let error = create_regular(&fifo, Existing::Replace)
            .unwrap_err()
            .to_string();
        assert!(error.contains("FIFO"), "{error}");

        let error = create_regular(Path::new("/dev/null"), Existing::Replace)
            .unwrap_err()
            .to_string();
        assert!(error.contains("regular files only"), "{error}");
    }

    #[test]
    fn an_existing_file_or_link_is_refused_unless_replacing() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("run.mcap");
        create_regular(&file, Existing::Refuse)
            .unwrap()
            .write_all(b"first")
            .unwrap();
        let error = create_regular(&file, Existing::Refuse).unwrap_err();
        assert!(error.to_string().contains("it exists"), "{error}");
        assert_eq!(std::fs::read(&file).unwrap(), b"first");

        let dangling = dir.path().join("dangling.mcap");
        let target = dir.path().join("target.mcap");
        std::os::unix::fs::symlink(&target, &dangling).unwrap();
        let error = create_regular(&dangling, Existing::Refuse).unwrap_err();
        assert!(error.to_string().contains("symbolic link"), "{error}");
        assert!(!target.exists(), "a dangling link's target is not created");

        let fifo = mkfifo(&dir.path().join("fifo.mcap"));
        let error = create_regular(&fifo, Existing::Refuse).unwrap_err();
        assert!(error.to_string().contains("FIFO"), "{error}");
    }

    #[test]
    fn output_paths_are_resolved_under_their_directory() {
        let base = Path::new("/var/lib/relightd/recordings");
        assert_eq!(
            resolve_output(Path::new("run1.mcap"), base).unwrap(),
            base.join("run1.mcap")
        );
        assert_eq!(
            resolve_output(Path::new("/data/run1.mcap"), base).unwrap(),
            Path::new("/data/run1.mcap")
        );
        for bad in [
            "../x.mcap",
            "a/../../x.mcap",
            "/data/../etc/x",
            "run\n1.mcap",
            "a\u{7}.mcap",
        ] {
            let error = resolve_output(Path::new(bad), base).unwrap_err();
            assert_eq!(error.kind(), io::ErrorKind::InvalidInput, "{bad}");
        }
        let error = resolve_output(Path::new("x\ny.mcap"), base).unwrap_err();
        assert!(error.to_string().contains("control character"), "{error}");
    }
}
