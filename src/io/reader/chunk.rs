//! Opening a chunk: decompression bounded by the declared size, the CRC check, walking its
//! records, and naming a chunk that cannot be read (offset, topics, time range).

use std::collections::{BTreeSet, HashMap};
use std::io::Read;

use mcap::records::{Record, op};

use super::record::{parse_record, record_kind};
use super::{BadChunk, MAX_RECORD_BYTES};

/// Decompresses a chunk into at most its declared size, which is checked against
/// [`MAX_RECORD_BYTES`] first: memory follows the bytes actually produced, never a
/// size read from the file.
pub(super) fn decompress(
    header: &mcap::records::ChunkHeader,
    data: &[u8],
) -> Result<Vec<u8>, String> {
    let size = header.uncompressed_size;
    if size > MAX_RECORD_BYTES {
        return Err(format!(
            "declared uncompressed size {size} bytes is over the {MAX_RECORD_BYTES}-byte limit"
        ));
    }
    // Start small: a lying size must not reserve memory; the vector grows as data comes.
    let mut out = Vec::with_capacity((size as usize).min(data.len().saturating_mul(4) + 4096));
    let limit = size + 1; // one byte more reveals a chunk longer than declared
    let read = match header.compression.as_str() {
        "" => data.take(limit).read_to_end(&mut out),
        "zstd" => zstd::stream::read::Decoder::with_buffer(data)
            .and_then(|d| d.take(limit).read_to_end(&mut out)),
        "lz4" => lz4::Decoder::new(data).and_then(|d| d.take(limit).read_to_end(&mut out)),
        other => return Err(format!("unsupported chunk compression '{other}'")),
    };
    read.map_err(|e| format!("{}: {e}", header.compression))?;
    Ok(out)
}

/// Decompresses a chunk and checks its size and CRC; returns its records' bytes, with a
/// note when a wrong declared size was read through. An empty chunk is empty whatever its
/// compression; an uncompressed chunk's records are its data, so a wrong
/// `uncompressed_size` there loses nothing (its CRC, where set, still decides).
pub(super) fn open_chunk(
    header: &mcap::records::ChunkHeader,
    data: &[u8],
) -> Result<(Vec<u8>, Option<String>), String> {
    if data.is_empty() && header.uncompressed_size == 0 {
        return Ok((Vec::new(), None));
    }
    if header.compression.is_empty() && data.len() as u64 != header.uncompressed_size {
        check_crc(header, data)?;
        let note = format!(
            "uncompressed chunk of {} bytes declares {}; its records were read from its data",
            data.len(),
            header.uncompressed_size
        );
        return Ok((data.to_vec(), Some(note)));
    }
    let records = decompress(header, data)?;
    if records.len() as u64 != header.uncompressed_size {
        return Err(format!(
            "chunk holds {}{} bytes, header says {}",
            records.len(),
            if records.len() as u64 > header.uncompressed_size {
                " or more"
            } else {
                ""
            },
            header.uncompressed_size
        ));
    }
    check_crc(header, &records)?;
    Ok((records, None))
}

/// The chunk's CRC of its uncompressed records, where it has one (0: none).
pub(super) fn check_crc(header: &mcap::records::ChunkHeader, records: &[u8]) -> Result<(), String> {
    let calculated = crc32fast::hash(records);
    if header.uncompressed_crc != 0 && calculated != header.uncompressed_crc {
        return Err(format!(
            "CRC mismatch (saved {:#010x}, calculated {calculated:#010x})",
            header.uncompressed_crc
        ));
    }
    Ok(())
}

pub(super) enum ChunkWalk {
    /// The record at byte `at` of the buffer is cut short or unparsable.
    Record {
        at: usize,
        error: String,
    },
    Visitor(anyhow::Error),
}

/// Walks the records packed in a chunk: opcode (1), length (8), body.
pub(super) fn for_each_record(
    buf: &[u8],
    mut f: impl FnMut(&Record<'_>) -> anyhow::Result<()>,
    mut skip: impl FnMut(usize, u8, String),
) -> Result<(), ChunkWalk> {
    let mut at = 0usize;
    while at < buf.len() {
        let rest = &buf[at..];
        if rest.len() < 9 {
            return Err(ChunkWalk::Record {
                at,
                error: "record header cut short".into(),
            });
        }
        let opcode = rest[0];
        let len = u64::from_le_bytes(rest[1..9].try_into().unwrap_or_default());
        let end = usize::try_from(len)
            .ok()
            .and_then(|l| l.checked_add(9))
            .filter(|&e| e <= rest.len());
        let Some(end) = end else {
            return Err(ChunkWalk::Record {
                at,
                error: format!(
                    "{} declares {len} bytes, {} are left",
                    record_kind(opcode),
                    rest.len() - 9
                ),
            });
        };
        // Framing intact, contents not: that record alone is lost; the next one starts
        // where its length says.
        match parse_record(opcode, &rest[9..end]) {
            Ok(rec) => f(&rec).map_err(ChunkWalk::Visitor)?,
            Err(e) => skip(at, opcode, e),
        }
        at += end;
    }
    Ok(())
}

/// Best-effort description of a broken chunk: its time range from the header and
/// the topics of whatever message records can still be parsed out of it.
pub(super) fn describe_bad_chunk(
    reason: String,
    header: &mcap::records::ChunkHeader,
    data: &[u8],
    topics: &HashMap<u16, String>,
) -> BadChunk {
    let mut channels = BTreeSet::new();
    let mut messages = 0u64;
    let mut own_topics = HashMap::new();
    // A CRC mismatch still decompresses: look inside. Broken compression yields nothing.
    if let Ok(records) = decompress(header, data) {
        let mut unparsed_messages = 0u64;
        let _ = for_each_record(
            &records,
            |rec| {
                match rec {
                    Record::Message { header, .. } => {
                        channels.insert(header.channel_id);
                        messages += 1;
                    }
                    Record::Channel(c) => {
                        own_topics.insert(c.id, c.topic.clone());
                    }
                    _ => {}
                }
                Ok(())
            },
            |_, opcode, _| unparsed_messages += u64::from(opcode == op::MESSAGE),
        );
        messages += unparsed_messages;
    }
    let topics = channels
        .iter()
        .map(|id| {
            own_topics
                .get(id)
                .or_else(|| topics.get(id))
                .cloned()
                .unwrap_or_else(|| format!("channel {id}"))
        })
        .collect();
    BadChunk {
        reason,
        topics,
        start_nanos: header.message_start_time,
        end_nanos: header.message_end_time,
        messages,
        offset: 0,
    }
}
