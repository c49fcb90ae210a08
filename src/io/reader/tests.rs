//! Damaged files built record by record, read back through [`super::read_records`].

use super::*;
use chunk::decompress;

/// A channel record whose topic length claims 4 GB: refused by the length check,
/// so the mcap parser never allocates it.
#[test]
fn length_fields_beyond_the_record_are_refused() {
    let mut channel = Vec::new();
    channel.extend_from_slice(&1u16.to_le_bytes());
    channel.extend_from_slice(&0u16.to_le_bytes());
    channel.extend_from_slice(&u32::MAX.to_le_bytes());
    channel.extend_from_slice(b"/points");
    let err = parse_record(op::CHANNEL, &channel).unwrap_err();
    assert!(err.contains("4294967295 bytes"), "{err}");
    // The same record with true lengths parses.
    let mut good = Vec::new();
    good.extend_from_slice(&1u16.to_le_bytes());
    good.extend_from_slice(&0u16.to_le_bytes());
    for text in ["/points", "json"] {
        good.extend_from_slice(&(text.len() as u32).to_le_bytes());
        good.extend_from_slice(text.as_bytes());
    }
    good.extend_from_slice(&0u32.to_le_bytes());
    assert!(
        matches!(parse_record(op::CHANNEL, &good), Ok(Record::Channel(c)) if c.topic == "/points")
    );
}

/// `bytes` (a whole MCAP file) with `records` (opcode, body) spliced in before its
/// data end record.
fn splice_before_data_end(bytes: &[u8], records: &[(u8, Vec<u8>)]) -> Vec<u8> {
    let mut at = 8;
    while bytes[at] != op::DATA_END {
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap());
        at += 9 + len as usize;
    }
    let mut out = bytes[..at].to_vec();
    for (opcode, body) in records {
        out.push(*opcode);
        out.extend_from_slice(&(body.len() as u64).to_le_bytes());
        out.extend_from_slice(body);
    }
    out.extend_from_slice(&bytes[at..]);
    out
}

/// An unchunked MCAP file with one JSON channel `/a` and no messages: its bytes, schema
/// id and channel id.
fn one_channel_file() -> (Vec<u8>, u16, u16) {
    let mut file = std::io::Cursor::new(Vec::new());
    let mut w = mcap::WriteOptions::new()
        .use_chunks(false)
        .create(&mut file)
        .unwrap();
    let schema = w.add_schema("custom/Thing", "jsonschema", b"{}").unwrap();
    let channel = w
        .add_channel(schema, "/a", "json", &Default::default())
        .unwrap();
    w.finish().unwrap();
    drop(w);
    (file.into_inner(), schema, channel)
}

fn channel_body(id: u16, schema: u16, topic: &str, encoding: &str) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(&id.to_le_bytes());
    b.extend_from_slice(&schema.to_le_bytes());
    for text in [topic, encoding] {
        b.extend_from_slice(&(text.len() as u32).to_le_bytes());
        b.extend_from_slice(text.as_bytes());
    }
    b.extend_from_slice(&0u32.to_le_bytes());
    b
}

fn message_body(channel: u16, time: u64) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(&channel.to_le_bytes());
    b.extend_from_slice(&0u32.to_le_bytes());
    b.extend_from_slice(&time.to_le_bytes());
    b.extend_from_slice(&time.to_le_bytes());
    b.extend_from_slice(b"{}");
    b
}

/// A channel id defined again for another topic would merge two topics' messages: the
/// read stops and names the id, both topics and both offsets, whatever `on_error` says.
/// The same definition repeated is read as one channel.
#[test]
fn a_channel_id_redefined_for_another_topic_stops_the_read() {
    let (bytes, schema, channel) = one_channel_file();
    let read = |extra: &[(u8, Vec<u8>)]| {
        let bytes = splice_before_data_end(&bytes, extra);
        let mut topics = Vec::new();
        let len = bytes.len() as u64;
        let result = read_records(
            std::io::Cursor::new(bytes),
            Some(len),
            OnError::Skip,
            |rec| {
                if let Record::Channel(c) = rec {
                    topics.push(c.topic.clone());
                }
                Ok(())
            },
            |_| {},
        );
        (result, topics)
    };
    let same = channel_body(channel, schema, "/a", "json");
    let (result, topics) = read(&[
        (op::MESSAGE, message_body(channel, 1)),
        (op::CHANNEL, same),
        (op::MESSAGE, message_body(channel, 2)),
    ]);
    assert!(result.is_ok(), "{result:?}");
    assert!(topics.iter().all(|t| t == "/a"), "{topics:?}");
    let other = channel_body(channel, schema, "/b", "json");
    let (result, _) = read(&[
        (op::MESSAGE, message_body(channel, 1)),
        (op::CHANNEL, other),
        (op::MESSAGE, message_body(channel, 2)),
    ]);
    let Err(ReadError::Redefined(message)) = result else {
        panic!("expected a refusal, got {result:?}");
    };
    for needle in [
        format!("channel id {channel}"),
        "'/a'".into(),
        "'/b'".into(),
    ] {
        assert!(message.contains(&needle), "{needle} missing: {message}");
    }
}

/// A message too short to parse inside a chunk whose framing is intact: that record
/// alone is reported, the messages after it are read.
#[test]
fn a_short_record_inside_a_chunk_costs_only_itself() {
    let (file, _, channel) = one_channel_file();
    let mut records = Vec::new();
    for body in [
        message_body(channel, 1),
        vec![0u8; 5], // a message record needs 22 bytes before its data
        message_body(channel, 3),
    ] {
        records.push(op::MESSAGE);
        records.extend_from_slice(&(body.len() as u64).to_le_bytes());
        records.extend_from_slice(&body);
    }
    let mut chunk = Vec::new();
    for v in [1u64, 3, records.len() as u64] {
        chunk.extend_from_slice(&v.to_le_bytes());
    }
    chunk.extend_from_slice(&crc32fast::hash(&records).to_le_bytes());
    chunk.extend_from_slice(&0u32.to_le_bytes()); // no compression
    chunk.extend_from_slice(&(records.len() as u64).to_le_bytes());
    chunk.extend_from_slice(&records);
    let bytes = splice_before_data_end(&file, &[(op::CHUNK, chunk)]);
    let len = bytes.len() as u64;
    let mut times = Vec::new();
    let report = read_records(
        std::io::Cursor::new(&bytes),
        Some(len),
        OnError::Skip,
        |rec| {
            if let Record::Message { header, .. } = rec {
                times.push(header.log_time);
            }
            Ok(())
        },
        |_| {},
    )
    .unwrap();
    assert_eq!(times, [1, 3]);
    assert!(report.bad_chunks.is_empty(), "{:?}", report.bad_chunks);
    assert_eq!(report.bad_records.len(), 1);
    assert!(
        report.bad_records[0].record.contains("of the chunk"),
        "{:?}",
        report.bad_records
    );
    // Without --on-error skip the read stops, naming the record.
    let failed = read_records(
        std::io::Cursor::new(&bytes),
        Some(len),
        OnError::Fail,
        |_| Ok(()),
        |_| {},
    );
    assert!(matches!(failed, Err(ReadError::BadRecord(_))), "{failed:?}");
}

fn string_field(b: &mut Vec<u8>, text: &str) {
    b.extend_from_slice(&(text.len() as u32).to_le_bytes());
    b.extend_from_slice(text.as_bytes());
}

/// A metadata record with a repeated key keeps the last value, an attachment with a
/// wrong CRC is returned as read; both are reported as repaired, and nothing fails.
#[test]
fn repeated_metadata_keys_and_attachment_crcs_are_read_as_reference_readers_do() {
    let mut file = std::io::Cursor::new(Vec::new());
    let mut w = mcap::WriteOptions::new()
        .use_chunks(false)
        .create(&mut file)
        .unwrap();
    w.finish().unwrap();
    drop(w);
    let mut map = Vec::new();
    for text in ["k", "first", "k", "last"] {
        string_field(&mut map, text);
    }
    let mut metadata = Vec::new();
    string_field(&mut metadata, "calib");
    metadata.extend_from_slice(&(map.len() as u32).to_le_bytes());
    metadata.extend_from_slice(&map);
    let mut attachment = Vec::new();
    attachment.extend_from_slice(&5u64.to_le_bytes());
    attachment.extend_from_slice(&6u64.to_le_bytes());
    string_field(&mut attachment, "a.txt");
    string_field(&mut attachment, "text/plain");
    attachment.extend_from_slice(&3u64.to_le_bytes());
    attachment.extend_from_slice(b"abc");
    attachment.extend_from_slice(&0xdead_beefu32.to_le_bytes());
    let bytes = splice_before_data_end(
        &file.into_inner(),
        &[(op::METADATA, metadata), (op::ATTACHMENT, attachment)],
    );
    let len = bytes.len() as u64;
    let (mut value, mut data) = (None, None);
    let report = read_records(
        std::io::Cursor::new(bytes),
        Some(len),
        OnError::Fail,
        |rec| {
            match rec {
                Record::Metadata(m) => value = m.metadata.get("k").cloned(),
                Record::Attachment { data: d, .. } => data = Some(d.to_vec()),
                _ => {}
            }
            Ok(())
        },
        |_| {},
    )
    .unwrap();
    assert_eq!(value.as_deref(), Some("last"));
    assert_eq!(data.as_deref(), Some(&b"abc"[..]));
    assert_eq!(report.repaired.len(), 2, "{:?}", report.repaired);
    assert!(
        report.repaired[0].contains("\"k\""),
        "{:?}",
        report.repaired
    );
    assert!(
        report.repaired[1].contains("CRC mismatch"),
        "{:?}",
        report.repaired
    );
    assert!(!report.damaged());
}

/// A chunk that inflates past its declared size is cut at the size plus one byte.
#[test]
fn decompression_stops_one_byte_past_the_declared_size() {
    let data = zstd::bulk::compress(&[7u8; 100_000], 3).unwrap();
    let header = mcap::records::ChunkHeader {
        message_start_time: 0,
        message_end_time: 0,
        uncompressed_size: 10,
        uncompressed_crc: 0,
        compression: "zstd".into(),
        compressed_size: data.len() as u64,
    };
    assert_eq!(decompress(&header, &data).unwrap().len(), 11);
    let err = open_chunk(&header, &data).unwrap_err();
    assert!(err.contains("11 or more bytes, header says 10"), "{err}");
}

/// An empty chunk is empty for every compression; an uncompressed chunk with a wrong
/// declared size gives its records with a note, unless its CRC disagrees.
#[test]
fn empty_chunks_and_wrong_sizes_of_uncompressed_chunks_lose_nothing() {
    let header = |compression: &str, size: u64, crc: u32| mcap::records::ChunkHeader {
        message_start_time: 0,
        message_end_time: 0,
        uncompressed_size: size,
        uncompressed_crc: crc,
        compression: compression.into(),
        compressed_size: 0,
    };
    for compression in ["", "zstd", "lz4"] {
        let (records, note) = open_chunk(&header(compression, 0, 0), &[]).unwrap();
        assert!(records.is_empty() && note.is_none(), "{compression}");
    }
    let data = [1u8, 2, 3, 4, 5];
    let (records, note) = open_chunk(&header("", 9, 0), &data).unwrap();
    assert_eq!(records, data);
    assert!(note.unwrap().contains("declares 9"));
    let crc = crc32fast::hash(&data);
    assert!(open_chunk(&header("", 9, crc), &data).is_ok());
    let err = open_chunk(&header("", 9, crc ^ 1), &data).unwrap_err();
    assert!(err.contains("CRC mismatch"), "{err}");
    // A compressed chunk's declared size still decides.
    assert!(
        open_chunk(
            &header("zstd", 3, 0),
            &zstd::bulk::compress(&data, 3).unwrap()
        )
        .is_err()
    );
}
