//! One repair to `.oni` files written by OpenNI's recorder, so that OpenNI's own player can
//! play them.
//!
//! The recorder writes an `xnCropping` property for a stream only when the stream has
//! `ONI_STREAM_PROPERTY_CROPPING` (OniRecorder.cpp, `Recorder::onAttach`), but the player drops
//! every frame of a stream without one: `PlayerStream::OnNewDataCallback` returns early when
//! the source has no cropping property (PlayerStream.cpp). A recording of a device without
//! cropping — OpenNI's DummyDevice, for one — therefore opens, reports its frame count and then
//! delivers nothing. The repair gives such a stream "cropping disabled" by rewriting, in
//! place, its `xnIsGenerating` record (read only by OpenNI 1.x, ignored by OpenNI2's player),
//! which happens to be exactly as long as an `xnCropping` record: no offset in the file moves.
//!
//! Record layout (DataRecords.h, file format 1.0.1.0): a 24-byte file header, then records of
//! a 28-byte header {magic "NIR\0", type u32, node u32, fields size u32 (header included),
//! payload size u32, undo position u64}, fields, payload; all little-endian. A property's
//! fields are its name (u32 length including the NUL, bytes) and its value (u32 size, bytes).

use std::path::Path;

const FILE_HEADER: usize = 24;
const RECORD_HEADER: usize = 28;
const RECORD_MAGIC: &[u8; 4] = b"NIR\0";
const RECORD_INT_PROPERTY: u32 = 0x03;
const RECORD_NODE_DATA_BEGIN: u32 = 0x08;
const RECORD_GENERAL_PROPERTY: u32 = 0x06;
const RECORD_NEW_DATA: u32 = 0x0A;
const RECORD_END: u32 = 0x0B;

/// `xnCropping`, disabled: XnCropping {XnBool bEnabled; XnUInt16 x, y, width, height}.
fn cropping_record(node: u32, undo_position: u64) -> Vec<u8> {
    let name = b"xnCropping\0";
    let value = [0u8; 12];
    let fields = RECORD_HEADER + 4 + name.len() + 4 + value.len();
    let mut record = Vec::with_capacity(fields);
    record.extend_from_slice(RECORD_MAGIC);
    record.extend_from_slice(&RECORD_GENERAL_PROPERTY.to_le_bytes());
    record.extend_from_slice(&node.to_le_bytes());
    record.extend_from_slice(&(fields as u32).to_le_bytes());
    record.extend_from_slice(&0u32.to_le_bytes());
    record.extend_from_slice(&undo_position.to_le_bytes());
    record.extend_from_slice(&(name.len() as u32).to_le_bytes());
    record.extend_from_slice(name);
    record.extend_from_slice(&(value.len() as u32).to_le_bytes());
    record.extend_from_slice(&value);
    record
}

fn u32_at(bytes: &[u8], at: usize) -> Option<u32> {
    let raw = bytes.get(at..at + 4)?;
    Some(u32::from_le_bytes([raw[0], raw[1], raw[2], raw[3]]))
}

/// Per node: whether it has an `xnCropping` record, and where its `xnIsGenerating` record is.
#[derive(Debug, Default, Clone, Copy)]
struct NodeRecords {
    has_cropping: bool,
    is_generating_at: Option<usize>,
    repaired: bool,
}

/// Gives every stream of the recording in `bytes` without an `xnCropping` record one; returns
/// how many it repaired.
pub(super) fn add_missing_cropping(bytes: &mut [u8]) -> Result<usize, String> {
    if bytes.get(..4) != Some(b"NI10") {
        return Err("not an OpenNI recording (no NI10 header)".into());
    }
    // Version {major u8, minor u8, maintenance u16, build u32}; 1.0.1.0 and later have 64-bit
    // record headers.
    let version = match bytes.get(4..8) {
        Some(&[major, minor, lo, hi]) => (major, minor, u16::from_le_bytes([lo, hi])),
        _ => return Err("truncated file header".into()),
    };
    if version < (1, 0, 1) {
        return Err(format!(
            "recording format {}.{}.{} is older than 1.0.1",
            version.0, version.1, version.2
        ));
    }
    let mut nodes: Vec<(u32, NodeRecords)> = Vec::new();
    let mut at = FILE_HEADER;
    while at + RECORD_HEADER <= bytes.len() {
        if bytes.get(at..at + 4) != Some(&RECORD_MAGIC[..]) {
            return Err(format!("no record header at byte {at}"));
        }
        let (Some(kind), Some(node), Some(fields), Some(payload)) = (
            u32_at(bytes, at + 4),
            u32_at(bytes, at + 8),
            u32_at(bytes, at + 12),
            u32_at(bytes, at + 16),
        ) else {
            return Err(format!("truncated record at byte {at}"));
        };
        let index = match nodes.iter().position(|(n, _)| *n == node) {
            Some(i) => i,
            None => {
                nodes.push((node, NodeRecords::default()));
                nodes.len() - 1
            }
        };
        match kind {
            RECORD_INT_PROPERTY | RECORD_GENERAL_PROPERTY => {
                let name_len = u32_at(bytes, at + RECORD_HEADER).unwrap_or(0) as usize;
                let name_at = at + RECORD_HEADER + 4;
                let name = bytes.get(name_at..name_at + name_len).unwrap_or_default();
                let record = &mut nodes[index].1;
                if name == b"xnCropping\0" {
                    record.has_cropping = true;
                } else if name == b"xnIsGenerating\0"
                    && kind == RECORD_INT_PROPERTY
                    && payload == 0
                    && fields as usize == cropping_record(node, 0).len()
                {
                    record.is_generating_at = Some(at);
                }
            }
            RECORD_NEW_DATA => {
                // Properties count only if they come before the stream's first frame.
                if let Some((_, record)) = nodes.get_mut(index)
                    && !record.has_cropping
                    && let Some(position) = record.is_generating_at.take()
                {
                    let mut undo = [0u8; 8];
                    if let Some(raw) = bytes.get(position + 20..position + 28) {
                        undo.copy_from_slice(raw);
                    }
                    let patch = cropping_record(node, u64::from_le_bytes(undo));
                    let target = bytes
                        .get_mut(position..position + patch.len())
                        .ok_or_else(|| format!("truncated record at byte {position}"))?;
                    target.copy_from_slice(&patch);
                    record.has_cropping = true;
                    record.repaired = true;
                }
            }
            RECORD_END => break,
            _ => {}
        }
        if (fields as usize) < RECORD_HEADER {
            return Err(format!("record at byte {at} is shorter than its header"));
        }
        at += fields as usize + payload as usize;
    }
    Ok(nodes.iter().filter(|(_, r)| r.repaired).count())
}

/// How many streams of a recording being written have started: the recorder writes a
/// `NODE_DATA_BEGIN` record per stream when it processes its start request (`Recorder::onStart`)
/// and takes frames only from then on. A record still being written ends the count.
pub(super) fn started_streams(bytes: &[u8]) -> usize {
    let mut started = 0;
    let mut at = FILE_HEADER;
    while at + RECORD_HEADER <= bytes.len() && bytes.get(at..at + 4) == Some(&RECORD_MAGIC[..]) {
        let (Some(kind), Some(fields), Some(payload)) = (
            u32_at(bytes, at + 4),
            u32_at(bytes, at + 12),
            u32_at(bytes, at + 16),
        ) else {
            break;
        };
        let end = at + fields as usize + payload as usize;
        if (fields as usize) < RECORD_HEADER || end > bytes.len() {
            break;
        }
        if kind == RECORD_NODE_DATA_BEGIN {
            started += 1;
        }
        at = end;
    }
    started
}

/// [`add_missing_cropping`] on a file.
pub(super) fn repair_recording(path: &Path) -> Result<usize, String> {
    let mut bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let repaired = add_missing_cropping(&mut bytes)?;
    if repaired > 0 {
        std::fs::write(path, &bytes).map_err(|e| format!("{}: {e}", path.display()))?;
    }
    Ok(repaired)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(kind: u32, node: u32, fields: &[u8], payload: &[u8]) -> Vec<u8> {
        let mut r = Vec::new();
        r.extend_from_slice(RECORD_MAGIC);
        r.extend_from_slice(&kind.to_le_bytes());
        r.extend_from_slice(&node.to_le_bytes());
        r.extend_from_slice(&((RECORD_HEADER + fields.len()) as u32).to_le_bytes());
        r.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        r.extend_from_slice(&0u64.to_le_bytes());
        r.extend_from_slice(fields);
        r.extend_from_slice(payload);
        r
    }

    fn int_property(node: u32, name: &str, value: u64) -> Vec<u8> {
        let mut fields = Vec::new();
        fields.extend_from_slice(&(name.len() as u32 + 1).to_le_bytes());
        fields.extend_from_slice(name.as_bytes());
        fields.push(0);
        fields.extend_from_slice(&8u32.to_le_bytes());
        fields.extend_from_slice(&value.to_le_bytes());
        record(RECORD_INT_PROPERTY, node, &fields, &[])
    }

    fn recording(nodes_with_cropping: &[bool]) -> Vec<u8> {
        let mut file = b"NI10".to_vec();
        file.extend_from_slice(&[1, 0, 1, 0, 0, 0, 0, 0]);
        file.extend_from_slice(&u64::MAX.to_le_bytes());
        file.extend_from_slice(&(nodes_with_cropping.len() as u32).to_le_bytes());
        for (i, &cropping) in nodes_with_cropping.iter().enumerate() {
            let node = i as u32 + 1;
            file.extend(int_property(node, "xnIsGenerating", 1));
            if cropping {
                file.extend(cropping_record(node, 0));
            }
        }
        for node in 1..=nodes_with_cropping.len() as u32 {
            file.extend(record(RECORD_NEW_DATA, node, &[0; 12], &[7; 5]));
        }
        file.extend(record(RECORD_END, 0, &[], &[]));
        file
    }

    #[test]
    fn the_cropping_record_is_as_long_as_the_record_it_replaces() {
        assert_eq!(
            cropping_record(1, 0).len(),
            int_property(1, "xnIsGenerating", 1).len()
        );
    }

    #[test]
    fn only_streams_without_cropping_are_repaired_in_place() {
        let original = recording(&[false, true]);
        let mut repaired = original.clone();
        assert_eq!(add_missing_cropping(&mut repaired), Ok(1));
        assert_eq!(repaired.len(), original.len(), "no offset moves");
        // Node 1's xnIsGenerating became xnCropping; node 2 and every frame are untouched.
        let first = FILE_HEADER;
        let len = cropping_record(1, 0).len();
        assert_eq!(&repaired[first..first + len], &cropping_record(1, 0)[..]);
        assert_eq!(&repaired[first + len..], &original[first + len..]);
        // Repairing again finds nothing to do.
        let mut again = repaired.clone();
        assert_eq!(add_missing_cropping(&mut again), Ok(0));
        assert_eq!(again, repaired);
    }

    #[test]
    fn started_streams_are_counted_from_their_data_begin_records() {
        let mut file = recording(&[true, true]);
        assert_eq!(started_streams(&file), 0);
        let data_begin = record(RECORD_NODE_DATA_BEGIN, 1, &[0; 12], &[]);
        let end = file.len() - RECORD_HEADER;
        file.splice(end..end, data_begin.iter().copied());
        assert_eq!(started_streams(&file), 1);
        // A half-written record is not counted.
        let cut = end + data_begin.len() - 3;
        assert_eq!(started_streams(&file[..cut]), 0);
    }

    #[test]
    fn other_files_are_refused() {
        assert!(add_missing_cropping(&mut b"PK\x03\x04 not a recording".to_vec()).is_err());
        let mut corrupt = recording(&[false]);
        corrupt[FILE_HEADER..FILE_HEADER + 4].copy_from_slice(b"XXXX");
        assert!(add_missing_cropping(&mut corrupt).is_err());
        let mut old = recording(&[false]);
        old[6] = 0; // format 1.0.0
        assert!(
            add_missing_cropping(&mut old)
                .unwrap_err()
                .contains("older")
        );
    }
}
