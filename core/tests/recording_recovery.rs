//! Damaged recordings: cut off mid-write, a corrupt chunk, no summary. The reader never panics,
//! gives back every message it can, and says what it lost.

mod recording_support;

use recording_support::{Rng, meta, record, small_chunks, traffic};
use relight_core::StreamMessage;
use relight_core::recording::{ChunkInfo, RecordingError, RecordingReader};

/// A recording of many chunks and the messages written to it (host times strictly increase in
/// write order, so each chunk holds exactly the messages inside its time range).
fn fixture() -> (Vec<u8>, Vec<StreamMessage>, Vec<ChunkInfo>) {
    let messages = traffic(24, 48, 32, 42);
    let bytes = record(&messages, &small_chunks());
    let chunks = RecordingReader::from_bytes(bytes.clone()).unwrap().chunks();
    let with_messages = chunks.iter().filter(|c| c.uncompressed_size > 0).count();
    assert!(
        with_messages >= 4,
        "fixture needs 4+ message chunks, has {with_messages}"
    );
    (bytes, messages, chunks)
}

fn in_chunk(msg: &StreamMessage, chunk: &ChunkInfo) -> bool {
    let host_ns = msg.stamp().host_ns;
    chunk.message_start_ns <= host_ns && host_ns <= chunk.message_end_ns
}

/// Chunks that hold messages (chunk 0 holds only schemas and channels).
fn message_chunks(chunks: &[ChunkInfo]) -> Vec<&ChunkInfo> {
    chunks.iter().filter(|c| c.message_end_ns > 0).collect()
}

#[test]
fn cut_anywhere_keeps_every_complete_chunk_and_says_where() {
    let (bytes, messages, chunks) = fixture();
    let header_end = {
        // magic, then the header record: opcode, u64 length, body.
        let length = u64::from_le_bytes(bytes[9..17].try_into().unwrap()) as usize;
        8 + 9 + length
    };
    let mut cuts: Vec<usize> = (1..15).map(|i| bytes.len() * i * 7 / 100).collect();
    let last = chunks.last().unwrap();
    cuts.extend([
        header_end,
        header_end + 1,
        last.offset as usize + 3,
        last.data_offset as usize + last.compressed_size as usize / 2,
        last.end_offset as usize,
        last.end_offset as usize + 1,
        bytes.len() - 1,
        bytes.len() - 8,
    ]);
    cuts.extend(chunks.iter().map(|c| c.end_offset as usize));
    cuts.extend(chunks.iter().map(|c| c.end_offset as usize - 1));

    for cut in cuts {
        let reader = RecordingReader::from_bytes(bytes[..cut].to_vec())
            .unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        let complete: Vec<&ChunkInfo> = chunks
            .iter()
            .filter(|c| c.end_offset as usize <= cut)
            .collect();
        let expected: Vec<&StreamMessage> = messages
            .iter()
            .filter(|m| complete.iter().any(|c| in_chunk(m, c)))
            .collect();
        let read: Vec<StreamMessage> = reader
            .messages()
            .collect::<Result<_, _>>()
            .unwrap_or_else(|e| panic!("cut at {cut}: {e}"));
        assert_eq!(read.len(), expected.len(), "cut at {cut}");
        assert!(
            read.iter().zip(&expected).all(|(r, e)| r == *e),
            "cut at {cut}"
        );

        let warnings = reader.warnings();
        let truncation = warnings
            .iter()
            .find(|w| w.starts_with("recording truncated"))
            .unwrap_or_else(|| panic!("cut at {cut}: no truncation warning in {warnings:?}"));
        assert!(truncation.contains(&format!("byte {cut}")), "{truncation}");
        // The count is of MCAP messages: each stream message, and the frame_info, camera_info
        // and /tf beside it (at most three more), and the /tf_static before the first.
        let counted: usize = truncation
            .rsplit_once("read ")
            .and_then(|(_, rest)| rest.split(' ').next()?.parse().ok())
            .unwrap_or_else(|| panic!("no count in {truncation}"));
        assert!(
            (expected.len()..=expected.len() * 3 + 1).contains(&counted),
            "{counted} MCAP messages for {} stream messages: {truncation}",
            expected.len()
        );
        if cut >= last.end_offset as usize {
            assert_eq!(reader.meta(), &meta(), "cut at {cut}");
        }
    }
}

#[test]
fn cut_inside_magic_or_header_is_a_clear_error() {
    let (bytes, _, _) = fixture();
    let length = u64::from_le_bytes(bytes[9..17].try_into().unwrap()) as usize;
    for cut in (0..8 + 9 + length).step_by(3) {
        match RecordingReader::from_bytes(bytes[..cut].to_vec()) {
            Err(RecordingError::NotMcap { reason }) => {
                assert!(reason.contains("cut off"), "cut at {cut}: {reason}");
            }
            other => panic!("cut at {cut}: expected NotMcap, got {other:?}"),
        }
    }
    let err = RecordingReader::from_bytes(b"PK\x03\x04 not an mcap at all".to_vec()).unwrap_err();
    assert!(err.to_string().contains("magic"), "{err}");
}

#[test]
fn corrupt_chunk_costs_only_its_own_messages() {
    let (bytes, messages, chunks) = fixture();
    for chunk in message_chunks(&chunks) {
        let mut damaged = bytes.clone();
        let middle = chunk.data_offset as usize + chunk.compressed_size as usize / 2;
        for byte in &mut damaged[middle..middle + 16] {
            *byte ^= 0x5a;
        }
        let reader = RecordingReader::from_bytes(damaged).unwrap();
        let mut read = Vec::new();
        let mut errors = Vec::new();
        for item in reader.messages() {
            match item {
                Ok(msg) => read.push(msg),
                Err(e) => errors.push(e),
            }
        }
        assert_eq!(errors.len(), 1, "chunk {}: {errors:?}", chunk.index);
        match &errors[0] {
            RecordingError::CorruptChunk { index, offset, .. } => {
                assert_eq!((*index, *offset), (chunk.index, chunk.offset));
                let text = errors[0].to_string();
                assert!(text.contains(&format!("chunk {}", chunk.index)), "{text}");
            }
            other => panic!("expected CorruptChunk, got {other}"),
        }
        let expected: Vec<&StreamMessage> =
            messages.iter().filter(|m| !in_chunk(m, chunk)).collect();
        assert_eq!(read.len(), expected.len(), "chunk {}", chunk.index);
        assert!(read.iter().zip(&expected).all(|(r, e)| r == *e));
    }
}

#[test]
fn missing_summary_still_reads_linearly() {
    let (bytes, messages, _) = fixture();
    let footer = mcap::read::footer(&bytes).unwrap();
    let summary_start = footer.summary_start as usize;
    // Without the summary but with the data end record, and without both.
    for cut in [summary_start, summary_start - 13] {
        let reader = RecordingReader::from_bytes(bytes[..cut].to_vec()).unwrap();
        assert!(!reader.has_summary());
        let read: Vec<StreamMessage> = reader.messages().collect::<Result<_, _>>().unwrap();
        assert_eq!(read, messages, "cut at {cut}");
        assert_eq!(reader.meta(), &meta());
        assert_eq!(reader.warnings().len(), 1, "{:?}", reader.warnings());
    }
    // A summary section that is garbage (footer intact) is not needed either.
    let mut damaged = bytes.clone();
    let footer_start = bytes.len() - 8 - 9 - 20;
    for byte in &mut damaged[summary_start..footer_start] {
        *byte = 0xff;
    }
    let reader = RecordingReader::from_bytes(damaged).unwrap();
    let read: Vec<StreamMessage> = reader.messages().collect::<Result<_, _>>().unwrap();
    assert_eq!(read, messages);
}

#[test]
fn random_damage_never_panics() {
    let (bytes, messages, _) = fixture();
    let mut rng = Rng::new(99);
    for _ in 0..150 {
        let mut damaged = bytes.clone();
        for _ in 0..1 + rng.next_u64() % 8 {
            let at = (rng.next_u64() % damaged.len() as u64) as usize;
            damaged[at] = rng.next_u64() as u8;
        }
        if rng.unit_f32() < 0.33 {
            damaged.truncate((rng.next_u64() % damaged.len() as u64) as usize);
        }
        if let Ok(reader) = RecordingReader::from_bytes(damaged) {
            let _ = reader.warnings();
            let read = reader.messages().filter(Result::is_ok).count();
            assert!(read <= messages.len() + 1);
        }
    }
}

/// One corrupted record-length field used to end the walk there: 9 of 220 messages came back
/// although the summary's chunk index was intact. The reader now resumes from the index, and
/// frames the damaged chunk itself with the index's length, so nothing is lost.
#[test]
fn a_corrupt_record_length_resumes_at_the_indexed_chunks() {
    let (bytes, messages, chunks) = fixture();
    for chunk in message_chunks(&chunks) {
        for bad_length in [u64::MAX, 1 << 40, 3] {
            let mut damaged = bytes.clone();
            let at = chunk.offset as usize + 1;
            damaged[at..at + 8].copy_from_slice(&bad_length.to_le_bytes());
            let reader = RecordingReader::from_bytes(damaged).unwrap();
            let read: Vec<StreamMessage> = reader
                .messages()
                .collect::<Result<_, _>>()
                .unwrap_or_else(|e| panic!("chunk {} length {bad_length}: {e}", chunk.index));
            assert_eq!(read, messages, "chunk {} length {bad_length}", chunk.index);
            let warnings = reader.warnings();
            {
                assert!(
                    warnings
                        .iter()
                        .any(|w| w.contains("resumed from the summary's chunk index")),
                    "{warnings:?}"
                );
            }
        }
    }
}

/// Without the index (the summary is cut away too) the same damage still keeps what came before.
#[test]
fn a_corrupt_record_length_without_summary_keeps_the_chunks_before_it() {
    let (bytes, messages, chunks) = fixture();
    let footer = mcap::read::footer(&bytes).unwrap();
    let chunk = message_chunks(&chunks)[2].clone();
    let mut damaged = bytes[..footer.summary_start as usize].to_vec();
    let at = chunk.offset as usize + 1;
    damaged[at..at + 8].copy_from_slice(&u64::MAX.to_le_bytes());
    let reader = RecordingReader::from_bytes(damaged).unwrap();
    let read: Vec<StreamMessage> = reader.messages().collect::<Result<_, _>>().unwrap();
    let before: Vec<StreamMessage> = messages
        .iter()
        .filter(|m| m.stamp().host_ns < chunk.message_start_ns)
        .cloned()
        .collect();
    assert_eq!(read, before);
}

/// `salvage` copies what a damaged recording holds into a complete one, which reads back whole.
#[test]
fn salvage_writes_a_complete_copy_of_what_is_left() {
    use relight_core::recording::RecordingWriter;
    use relight_core::recording::salvage::{inspect, salvage};
    let (bytes, messages, chunks) = fixture();
    let cut = chunks.last().unwrap().offset as usize + 50;
    let reader = RecordingReader::from_bytes(bytes[..cut].to_vec()).unwrap();
    let found = inspect(&reader);
    assert!(!found.is_clean());
    assert!(!found.has_summary);
    let mut out = std::io::Cursor::new(Vec::new());
    let mut writer = RecordingWriter::new(&mut out, reader.meta()).unwrap();
    let copied = salvage(&reader, &mut writer).unwrap();
    writer.finish().unwrap();
    assert_eq!(copied.total_messages(), found.total_messages());
    let repaired = RecordingReader::from_bytes(out.into_inner()).unwrap();
    assert!(repaired.has_summary(), "{:?}", repaired.warnings());
    assert!(inspect(&repaired).is_clean(), "{:?}", inspect(&repaired));
    let read: Vec<StreamMessage> = repaired.messages().collect::<Result<_, _>>().unwrap();
    assert_eq!(read.len() as u64, found.total_messages());
    assert_eq!(read[..], messages[..read.len()]);
    assert_eq!(repaired.meta(), &meta());
    assert!(inspect(&RecordingReader::from_bytes(bytes).unwrap()).is_clean());
}

/// Inputs the `recording_reader` fuzz target crashed on (fuzz/regressions/): each opens or is
/// refused, and reading it ends, without a panic.
#[test]
fn fuzz_regressions_read_without_panicking() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/regressions/recording_reader");
    let mut inputs = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let bytes = std::fs::read(entry.unwrap().path()).unwrap();
        inputs += 1;
        if let Ok(reader) = RecordingReader::from_bytes(bytes) {
            for message in reader.messages() {
                let _ = message;
            }
            let _ = reader.warnings();
        }
    }
    assert!(inputs > 0, "no inputs in {}", dir.display());
}

/// What a reader makes of a file: its chunks, warnings, summary, and every item of its
/// message iterator (errors by their text).
fn reading(reader: &RecordingReader) -> (Vec<ChunkInfo>, Vec<String>, bool, Vec<String>) {
    let items = reader
        .messages()
        .map(|item| match item {
            Ok(message) => format!("{message:?}"),
            Err(error) => error.to_string(),
        })
        .collect();
    (
        reader.chunks(),
        reader.warnings(),
        reader.has_summary(),
        items,
    )
}

/// `open` reads the file as it needs it instead of loading it; on whole, cut and damaged files
/// alike it reads exactly what `from_bytes` reads from the same bytes.
#[test]
fn a_file_read_on_demand_reads_as_the_same_bytes_in_memory() {
    let (bytes, messages, chunks) = fixture();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("damaged.mcap");
    std::fs::write(&path, &bytes).unwrap();
    let whole: Vec<StreamMessage> = RecordingReader::open(&path)
        .unwrap()
        .messages()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(whole, messages);
    let mut variants = vec![bytes.clone(), bytes[..bytes.len() / 2].to_vec()];
    let chunk = message_chunks(&chunks)[1];
    let mut bad_length = bytes.clone();
    let at = chunk.offset as usize + 1;
    bad_length[at..at + 8].copy_from_slice(&u64::MAX.to_le_bytes());
    variants.push(bad_length);
    let mut bad_crc = bytes.clone();
    bad_crc[chunk.data_offset as usize + 5] ^= 0xff;
    variants.push(bad_crc);
    let mut rng = Rng::new(7);
    for _ in 0..20 {
        let mut damaged = bytes.clone();
        for _ in 0..1 + rng.next_u64() % 4 {
            let at = (rng.next_u64() % damaged.len() as u64) as usize;
            damaged[at] = rng.next_u64() as u8;
        }
        variants.push(damaged);
    }
    for (i, variant) in variants.into_iter().enumerate() {
        std::fs::write(&path, &variant).unwrap();
        let from_file = RecordingReader::open(&path).map(|r| reading(&r));
        let in_memory = RecordingReader::from_bytes(variant).map(|r| reading(&r));
        match (from_file, in_memory) {
            (Ok(file), Ok(memory)) => assert_eq!(file, memory, "variant {i}"),
            (Err(file), Err(memory)) => assert_eq!(file.to_string(), memory.to_string()),
            (file, memory) => panic!("variant {i}: {:?} vs {:?}", file.err(), memory.err()),
        }
    }
}
