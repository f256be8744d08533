//! Creating output files (composites, snapshots, recordings) so that what a path names cannot
//! stall or redirect the writer: the last component is not followed if it is a link, the open
//! does not block (a FIFO with no reader fails at once instead of waiting for one), and anything
//! but a regular file is refused before a byte is written.

use std::fs::File;
use std::io;
use std::path::Path;

use rustix::fs::{FileType, Mode, OFlags};

/// Create (or truncate) `path` for writing, as a regular file only.
pub fn create_regular(path: &Path) -> io::Result<File> {
    let flags = OFlags::WRONLY
        | OFlags::CREATE
        | OFlags::NOFOLLOW
        | OFlags::NONBLOCK
        | OFlags::NOCTTY
        | OFlags::CLOEXEC;
    let fd = rustix::fs::open(path, flags, Mode::from_raw_mode(0o644)).map_err(|errno| {
        let reason = match errno {
            rustix::io::Errno::LOOP => "it is a symbolic link; output is not written through links",
            rustix::io::Errno::NXIO => "it is a FIFO or socket; output goes to regular files only",
            _ => return io::Error::from(errno),
        };
        io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("refusing {}: {reason}", path.display()),
        )
    })?;
    let kind = FileType::from_raw_mode(rustix::fs::fstat(&fd)?.st_mode);
    if kind != FileType::RegularFile {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "refusing {}: it is a {kind:?}; output goes to regular files only",
                path.display()
            ),
        ));
    }
    rustix::fs::ftruncate(&fd, 0)?;
    rustix::fs::fcntl_setfl(&fd, OFlags::empty())?;
    Ok(File::from(fd))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write as _;

    #[test]
    fn writes_regular_files_and_refuses_links_fifos_and_devices() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("out.png");
        std::fs::write(&file, b"old and longer").unwrap();
        create_regular(&file).unwrap().write_all(b"new").unwrap();
        assert_eq!(std::fs::read(&file).unwrap(), b"new");

        let link = dir.path().join("link.png");
        std::os::unix::fs::symlink(&file, &link).unwrap();
        let error = create_regular(&link).unwrap_err().to_string();
        assert!(error.contains("symbolic link"), "{error}");
        assert_eq!(
            std::fs::read(&file).unwrap(),
            b"new",
            "the link's target is untouched"
        );

        let fifo = dir.path().join("fifo.png");
        rustix::fs::mknodat(
            rustix::fs::CWD,
            &fifo,
            FileType::Fifo,
            Mode::from_raw_mode(0o644),
            0,
        )
        .unwrap();
        let error = create_regular(&fifo).unwrap_err().to_string();
        assert!(error.contains("FIFO"), "{error}");

        let error = create_regular(Path::new("/dev/null"))
            .unwrap_err()
            .to_string();
        assert!(error.contains("regular files only"), "{error}");
    }
}
