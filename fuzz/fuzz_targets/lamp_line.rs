//! Any line from the lamp's serial port: never a panic, and a report that parses writes back a
//! line that parses.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relight_backends::lamp_protocol::parse_line;

fuzz_target!(|data: &[u8]| {
    let Ok(line) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(report) = parse_line(line) {
        let written = report.to_line();
        let again = parse_line(written.trim_end()).unwrap_or_else(|e| panic!("{written:?}: {e}"));
        assert_eq!(
            (again.seq, again.on, again.cct_k),
            (report.seq, report.on, report.cct_k)
        );
    }
});
