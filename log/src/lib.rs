//! How every relight binary logs, so that `relightd`, `relightctl` and `relight-calibrate` read
//! one filter variable and write the same way:
//!
//! - the filter is `RUST_LOG` (the ecosystem's name), else `RELIGHT_LOG` (relightd's older
//!   name, kept as an alias), else the binary's default;
//! - ANSI colour only when stderr is a terminal, so log files and pipes get plain text;
//! - under systemd, when stderr is the journal (`JOURNAL_STREAM` names it), events go to
//!   journald over its native protocol (tracing-journald), with their fields and levels as
//!   journal fields instead of text, so `journalctl -p warning -u relightd` works.

use std::io::IsTerminal as _;

use tracing_subscriber::EnvFilter;
use tracing_subscriber::layer::SubscriberExt as _;
use tracing_subscriber::util::SubscriberInitExt as _;

/// The filter variables, in the order they are read.
pub const FILTER_VARIABLES: [&str; 2] = ["RUST_LOG", "RELIGHT_LOG"];

/// The filter from the first of [`FILTER_VARIABLES`] that is set, else `default`. A variable
/// that does not parse is reported on stderr and `default` is used.
pub fn filter(default: &str) -> EnvFilter {
    for name in FILTER_VARIABLES {
        let Ok(text) = std::env::var(name) else {
            continue;
        };
        match EnvFilter::try_new(&text) {
            Ok(filter) => return filter,
            Err(error) => {
                eprintln!("ignoring {name}={text:?}: {error}");
                break;
            }
        }
    }
    EnvFilter::new(default)
}

/// Whether systemd connected stderr to the journal: `JOURNAL_STREAM` is `device:inode` of the
/// stream it set up, and it must be stderr itself (a child whose stderr was redirected
/// inherits the variable but not the stream).
pub fn stderr_is_journal() -> bool {
    let Some(value) = std::env::var_os("JOURNAL_STREAM") else {
        return false;
    };
    let Some((device, inode)) = value.to_str().and_then(|v| v.split_once(':')) else {
        return false;
    };
    let Ok(stat) = rustix::fs::fstat(std::io::stderr()) else {
        return false;
    };
    device.parse::<u64>() == Ok(stat.st_dev) && inode.parse::<u64>() == Ok(stat.st_ino)
}

/// Install the global subscriber: the journal under systemd, else formatted text on stderr,
/// coloured on a terminal only.
pub fn init(default_filter: &str) {
    let filter = filter(default_filter);
    if stderr_is_journal() {
        match tracing_journald::layer() {
            Ok(journal) => {
                tracing_subscriber::registry()
                    .with(filter)
                    .with(journal)
                    .init();
                return;
            }
            Err(error) => eprintln!("journald unreachable ({error}); logging to stderr"),
        }
    }
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .init();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pipe_is_not_the_journal() {
        // Under `cargo test` stderr is a pipe or a terminal, never the stream JOURNAL_STREAM
        // names (it is unset, or names the test runner's own journal stream).
        if std::env::var_os("JOURNAL_STREAM").is_none() {
            assert!(!stderr_is_journal());
        }
    }

    #[test]
    fn without_a_variable_the_default_applies() {
        if FILTER_VARIABLES
            .iter()
            .all(|v| std::env::var_os(v).is_none())
        {
            assert_eq!(filter("warn").to_string(), "warn");
        }
    }
}
