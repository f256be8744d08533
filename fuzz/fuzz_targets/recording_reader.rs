//! Any bytes as a recording: opening never panics, and reading every message and counting what
//! is lost (`relightd recording check`) never panics either.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relight_core::recording::RecordingReader;
use relight_core::recording::salvage::inspect;

fuzz_target!(|data: &[u8]| {
    if let Ok(reader) = RecordingReader::from_bytes(data.to_vec()) {
        let _ = reader.chunks();
        let found = inspect(&reader);
        assert!(found.total_messages() <= data.len() as u64);
    }
});
