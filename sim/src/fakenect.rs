//! The simulated rig as a fakenect dump, so the freenect backend — and the daemon above it — can
//! be run through the real libfreenect API without a Kinect. The format is written by
//! [`relight_backends::freenect::dump::DumpWriter`].

use std::path::Path;

use relight_backends::freenect::dump::{DumpError, DumpSummary, DumpWriter};

use crate::rig::SimRig;

/// Simulate every frame of `rig` into a fakenect dump in `dir`: its depth and colour, with the
/// simulator's clocks (host time → `<time>`, device time → the 60 MHz `<timestamp>`). Other
/// streams of the rig (probe, markers, lamp) are not part of a Kinect dump.
pub fn write_fakenect_dump(dir: &Path, rig: &SimRig) -> Result<DumpSummary, DumpError> {
    let mut writer = DumpWriter::create(dir)?;
    for frame in rig.frames() {
        for msg in &frame.messages {
            writer.write_message(msg)?;
        }
    }
    writer.finish()
}
