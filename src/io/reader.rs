//! Streaming MCAP reader on the mcap crate's sans-io `LinearReader`: reads any
//! `Read` front to back, one record (or one chunk) in memory at a time, so memory
//! does not grow with the file. Chunks are opened here rather than inside the
//! crate so that a corrupt chunk can be named (topics, time range) and skipped,
//! and a truncated file yields every complete record before the damage.

use std::collections::{BTreeSet, HashMap};
use std::io::Read;

use mcap::records::{Record, op};
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};

/// What to do with a chunk whose CRC or compression is broken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OnError {
    /// Stop with an error naming the chunk.
    #[default]
    Fail,
    /// Report the chunk's records as lost and go on.
    Skip,
}

/// A chunk that could not be read, with what we know of its contents.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BadChunk {
    pub reason: String,
    pub topics: Vec<String>,
    pub start_nanos: u64,
    pub end_nanos: u64,
    /// Messages in the chunk as far as they could be counted (0 if unknown).
    pub messages: u64,
}

impl std::fmt::Display for BadChunk {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let t = |n: u64| format!("{}.{:09}", n / 1_000_000_000, n % 1_000_000_000);
        let topics = if self.topics.is_empty() {
            "unknown topics".to_string()
        } else {
            self.topics.join(", ")
        };
        write!(
            f,
            "{} in the chunk of {} from {} s to {} s",
            self.reason,
            topics,
            t(self.start_nanos),
            t(self.end_nanos)
        )
    }
}

/// Errors that stop reading.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("{0}")]
    Io(#[from] std::io::Error),
    #[error("not an MCAP file or unreadable from the start: {0}")]
    NotMcap(mcap::McapError),
    #[error("{0}; use --on-error skip to drop this chunk and go on")]
    BadChunk(BadChunk),
    #[error("{0}")]
    Record(mcap::McapError),
    #[error(transparent)]
    Visitor(#[from] anyhow::Error),
}

/// How the read ended, for the summary.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct ReadReport {
    /// Bytes of complete records (and magic) read.
    pub bytes_read: u64,
    /// Bytes after the last complete record when the file ended early or broke.
    pub unread_bytes: u64,
    /// Why reading stopped early, if it did.
    pub stopped: Option<String>,
    /// Whether the footer and end magic were reached.
    pub complete: bool,
    pub bad_chunks: Vec<BadChunk>,
}

/// Reads `src` to the end, calling `visit` with every record in file order; records
/// inside chunks are visited in place of their chunk. Index and summary records
/// are passed on too (a copier ignores them). `file_len` (if known) sizes the
/// unread tail of a truncated file. `progress` gets the bytes read so far.
pub fn read_records(
    mut src: impl Read,
    file_len: Option<u64>,
    on_error: OnError,
    mut visit: impl FnMut(&Record<'_>) -> anyhow::Result<()>,
    mut progress: impl FnMut(u64),
) -> Result<ReadReport, ReadError> {
    let opts = LinearReaderOptions::default()
        .with_emit_chunks(true)
        .with_record_length_limit(1 << 32);
    let mut reader = LinearReader::new_with_options(opts);
    let mut report = ReadReport {
        bytes_read: 8,
        ..Default::default()
    };
    let mut topics: HashMap<u16, String> = HashMap::new();
    let mut seen_any = false;
    // A broken chunk is completed from the message indexes that follow it (they
    // list its messages per channel) before it is reported or fails the read.
    let mut pending_bad: Option<(BadChunk, BTreeSet<u16>, u64)> = None;
    while let Some(event) = reader.next_event() {
        let (opcode, data) = match event {
            Ok(LinearReadEvent::ReadRequest(n)) => {
                let buf = reader.insert(n);
                let got = loop {
                    match src.read(buf) {
                        Ok(k) => break k,
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                        Err(e) => return Err(ReadError::Io(e)),
                    }
                };
                reader.notify_read(got);
                continue;
            }
            Ok(LinearReadEvent::Record { opcode, data }) => (opcode, data),
            Err(e) if !seen_any => return Err(ReadError::NotMcap(e)),
            Err(e) => {
                settle_bad_chunk(&mut pending_bad, &topics, on_error, &mut report)?;
                report.stopped = Some(match e {
                    mcap::McapError::UnexpectedEof => {
                        "the file ends in the middle of a record (truncated recording)".into()
                    }
                    other => format!("unreadable record: {other}"),
                });
                report.unread_bytes =
                    file_len.map_or(0, |len| len.saturating_sub(report.bytes_read));
                return Ok(report);
            }
        };
        seen_any = true;
        report.bytes_read += 9 + data.len() as u64;
        if opcode == op::MESSAGE_INDEX {
            if let Some((_, channels, indexed)) = pending_bad.as_mut()
                && let Ok(Record::MessageIndex(index)) = mcap::parse_record(opcode, data)
            {
                channels.insert(index.channel_id);
                *indexed += index.records.len() as u64;
            }
        } else {
            settle_bad_chunk(&mut pending_bad, &topics, on_error, &mut report)?;
        }
        if opcode == op::FOOTER {
            report.complete = true;
            report.bytes_read += 8;
        }
        if opcode == op::CHUNK {
            let chunk = mcap::parse_record(opcode, data).map_err(ReadError::Record)?;
            if let Record::Chunk { header, data } = chunk {
                match open_chunk(&header, &data) {
                    Ok(records) => {
                        for_each_record(&records, |rec| {
                            note_channel(&mut topics, rec);
                            visit(rec)
                        })
                        .map_err(|e| match e {
                            ChunkWalk::Record(e) => ReadError::Record(e),
                            ChunkWalk::Visitor(e) => ReadError::Visitor(e),
                        })?;
                    }
                    Err(reason) => {
                        let bad = describe_bad_chunk(reason, &header, &data, &topics);
                        pending_bad = Some((bad, BTreeSet::new(), 0));
                    }
                }
            }
        } else {
            let rec = mcap::parse_record(opcode, data).map_err(ReadError::Record)?;
            note_channel(&mut topics, &rec);
            visit(&rec)?;
        }
        progress(report.bytes_read);
    }
    settle_bad_chunk(&mut pending_bad, &topics, on_error, &mut report)?;
    Ok(report)
}

/// Reports (or, with [`OnError::Fail`], raises) a broken chunk once the message
/// indexes after it have been counted in.
fn settle_bad_chunk(
    pending: &mut Option<(BadChunk, BTreeSet<u16>, u64)>,
    topics: &HashMap<u16, String>,
    on_error: OnError,
    report: &mut ReadReport,
) -> Result<(), ReadError> {
    let Some((mut bad, channels, indexed)) = pending.take() else {
        return Ok(());
    };
    bad.messages = bad.messages.max(indexed);
    for id in channels {
        let topic = topics
            .get(&id)
            .cloned()
            .unwrap_or_else(|| format!("channel {id}"));
        if !bad.topics.contains(&topic) {
            bad.topics.push(topic);
        }
    }
    if on_error == OnError::Fail {
        return Err(ReadError::BadChunk(bad));
    }
    report.bad_chunks.push(bad);
    Ok(())
}

fn note_channel(topics: &mut HashMap<u16, String>, rec: &Record<'_>) {
    if let Record::Channel(c) = rec {
        topics.insert(c.id, c.topic.clone());
    }
}

/// Decompresses a chunk and checks its CRC; returns its records' bytes.
fn open_chunk(header: &mcap::records::ChunkHeader, data: &[u8]) -> Result<Vec<u8>, String> {
    let size =
        usize::try_from(header.uncompressed_size).map_err(|_| "chunk too large".to_string())?;
    let records = match header.compression.as_str() {
        "" => data.to_vec(),
        "zstd" => zstd::bulk::decompress(data, size).map_err(|e| format!("zstd: {e}"))?,
        "lz4" => {
            let mut out = Vec::with_capacity(size);
            lz4::Decoder::new(data)
                .and_then(|mut d| d.read_to_end(&mut out))
                .map_err(|e| format!("lz4: {e}"))?;
            out
        }
        other => return Err(format!("unsupported chunk compression '{other}'")),
    };
    if records.len() != size {
        return Err(format!(
            "chunk holds {} bytes, header says {size}",
            records.len()
        ));
    }
    if header.uncompressed_crc != 0 {
        let calculated = crc32fast::hash(&records);
        if calculated != header.uncompressed_crc {
            return Err(format!(
                "CRC mismatch (saved {:#010x}, calculated {calculated:#010x})",
                header.uncompressed_crc
            ));
        }
    }
    Ok(records)
}

enum ChunkWalk {
    Record(mcap::McapError),
    Visitor(anyhow::Error),
}

/// Walks the records packed in a chunk: opcode (1), length (8), body.
fn for_each_record(
    mut buf: &[u8],
    mut f: impl FnMut(&Record<'_>) -> anyhow::Result<()>,
) -> Result<(), ChunkWalk> {
    while !buf.is_empty() {
        if buf.len() < 9 {
            return Err(ChunkWalk::Record(mcap::McapError::UnexpectedEoc));
        }
        let opcode = buf[0];
        let len = u64::from_le_bytes(buf[1..9].try_into().unwrap_or_default());
        let end = usize::try_from(len)
            .ok()
            .and_then(|l| l.checked_add(9))
            .filter(|&e| e <= buf.len());
        let Some(end) = end else {
            return Err(ChunkWalk::Record(mcap::McapError::UnexpectedEoc));
        };
        let rec = mcap::parse_record(opcode, &buf[9..end]).map_err(ChunkWalk::Record)?;
        f(&rec).map_err(ChunkWalk::Visitor)?;
        buf = &buf[end..];
    }
    Ok(())
}

/// Best-effort description of a broken chunk: its time range from the header and
/// the topics of whatever message records can still be parsed out of it.
fn describe_bad_chunk(
    reason: String,
    header: &mcap::records::ChunkHeader,
    data: &[u8],
    topics: &HashMap<u16, String>,
) -> BadChunk {
    let mut channels = BTreeSet::new();
    let mut messages = 0u64;
    let mut own_topics = HashMap::new();
    // A CRC mismatch still decompresses: look inside. Broken compression yields nothing.
    let records = match header.compression.as_str() {
        "" => Some(data.to_vec()),
        "zstd" => zstd::bulk::decompress(data, header.uncompressed_size as usize).ok(),
        "lz4" => {
            let mut out = Vec::new();
            lz4::Decoder::new(data)
                .and_then(|mut d| d.read_to_end(&mut out))
                .ok()
                .map(|_| out)
        }
        _ => None,
    };
    if let Some(records) = records {
        let _ = for_each_record(&records, |rec| {
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
        });
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
    }
}
