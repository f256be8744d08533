//! Any text as relightd.toml, through the whole validation `run` and `check-config` use: never a
//! panic, and every error is located inside the text.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relight_daemon::config::Config;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Err(error) = Config::validate(text, "/nonexistent/relightd.toml") {
        let lines = text.lines().count().max(1) + 1;
        for d in error.diagnostics() {
            assert!(
                d.line >= 1 && d.line <= lines,
                "{d} (text has {lines} lines)"
            );
            assert!(d.column >= 1, "{d}");
        }
    }
});
