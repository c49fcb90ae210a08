//! Streaming MCAP reader on the mcap crate's sans-io `LinearReader`: reads any
//! `Read + Seek` front to back, one record (or one chunk) in memory at a time, so memory
//! does not grow with the file. Every length read from the file is checked against
//! what the file (or [`MAX_RECORD_BYTES`]) can hold before anything is allocated.
//! Chunks are opened here rather than inside the crate so that a corrupt chunk can be
//! named (offset, topics, time range) and skipped, and a truncated file yields every
//! complete record before the damage. When the footer and summary section are intact
//! (CRC-checked), the summary supplies schemas and channels whose own records were
//! lost, and its chunk index lets reading resume after a damaged record.

use std::collections::{BTreeSet, HashMap, HashSet};
use std::io::{Read, Seek, SeekFrom};

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
    /// File offset of the chunk record.
    pub offset: u64,
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
            "{} in the chunk at offset {} of {} from {} s to {} s",
            self.reason,
            self.offset,
            topics,
            t(self.start_nanos),
            t(self.end_nanos)
        )
    }
}

/// A record that could not be read (not a chunk: those are [`BadChunk`]s), and
/// the bytes skipped to get past it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct BadRecord {
    /// File offset of the record's opcode.
    pub offset: u64,
    /// Its kind, e.g. "chunk index (opcode 0x08)", as far as it could be read.
    pub record: String,
    pub reason: String,
    /// Bytes from `offset` to where reading goes on (0: the record alone).
    pub skipped_bytes: u64,
}

impl std::fmt::Display for BadRecord {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} at offset {}: {}",
            self.record, self.offset, self.reason
        )?;
        if self.skipped_bytes > 0 {
            write!(
                f,
                "; the next chunk in the summary's chunk index starts {} bytes later",
                self.skipped_bytes
            )?;
        }
        Ok(())
    }
}

/// Errors that stop reading.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("{0}")]
    Io(#[from] std::io::Error),
    #[error("not an MCAP file or unreadable from the start: {0}")]
    NotMcap(String),
    #[error("{0}; use --on-error skip to drop this chunk and go on")]
    BadChunk(BadChunk),
    #[error("{0}; use --on-error skip to skip it and go on")]
    BadRecord(BadRecord),
    /// An id defined twice with different contents: what was recorded under it after the
    /// second definition cannot be told apart from what came before, so no copy is faithful.
    #[error("{0}")]
    Redefined(String),
    #[error(transparent)]
    Visitor(#[from] anyhow::Error),
}

impl ReadError {
    /// The error as a command that stops at damage (it has no `--on-error`) reports it: the
    /// file named, and for a damaged chunk or record the advice that works there.
    pub fn for_strict_reader(self, path: &std::path::Path) -> anyhow::Error {
        let advice = |what: &dyn std::fmt::Display| {
            anyhow::anyhow!(
                "{}: {what}; this command stops at damage: `rangegan-mcap convert --on-error skip --channels range {} REPAIRED.mcap` copies every readable record first",
                path.display(),
                path.display()
            )
        };
        match self {
            ReadError::BadChunk(bad) => advice(&bad),
            ReadError::BadRecord(bad) => advice(&bad),
            other => anyhow::anyhow!("{}: {other}", path.display()),
        }
    }
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
    /// Whether a footer with an intact (CRC-checked) summary section was found and used
    /// to resolve channels and to resynchronise after damage.
    pub summary_used: bool,
    pub bad_chunks: Vec<BadChunk>,
    pub bad_records: Vec<BadRecord>,
    /// Records rebuilt from the summary section because their own copy was lost.
    pub from_summary: Vec<String>,
    /// Damage read through with nothing lost (e.g. an uncompressed chunk whose declared
    /// size is wrong), one sentence each.
    pub repaired: Vec<String>,
}

impl ReadReport {
    /// Whether anything of the input was skipped or could not be read.
    pub fn damaged(&self) -> bool {
        self.stopped.is_some() || !self.bad_chunks.is_empty() || !self.bad_records.is_empty()
    }
}

/// Largest record or decompressed chunk read into memory when the file size does not
/// bound it (a stream); with a known size, a record may not be longer than the file.
pub const MAX_RECORD_BYTES: u64 = 1 << 32;

/// Reads `src` to the end, calling `visit` with every record in file order; records
/// inside chunks are visited in place of their chunk. Index and summary records
/// are passed on too (a copier ignores them). `file_len` (if known) bounds every
/// length read from the file and sizes the unread tail of a truncated file; with it,
/// an intact summary section (CRC-checked) supplies schemas and channels whose own
/// records were lost, and its chunk index lets reading resume after a damaged record.
/// `progress` gets the bytes read so far.
pub fn read_records<R: Read + Seek>(
    mut src: R,
    file_len: Option<u64>,
    on_error: OnError,
    visit: impl FnMut(&Record<'_>) -> anyhow::Result<()>,
    progress: impl FnMut(u64),
) -> Result<ReadReport, ReadError> {
    let summary = file_len.and_then(|len| Summary::read(&mut src, len).ok());
    src.seek(SeekFrom::Start(0))?;
    let mut walk = Walk {
        file_len,
        on_error,
        summary,
        report: ReadReport {
            bytes_read: 8,
            ..Default::default()
        },
        topics: HashMap::new(),
        seen_schemas: HashSet::new(),
        seen_channels: HashSet::new(),
        definitions: HashMap::new(),
        offset: 0,
        chunks_read: HashSet::new(),
        recovery_tried: HashSet::new(),
        pending_bad: None,
        in_summary_section: false,
        visit,
        progress,
    };
    walk.report.summary_used = walk.summary.is_some();
    walk.run(src)?;
    Ok(walk.report)
}

/// One pass over the file: framing by the mcap crate's `LinearReader`, records parsed,
/// checked and visited here.
struct Walk<V, P> {
    file_len: Option<u64>,
    on_error: OnError,
    summary: Option<Summary>,
    report: ReadReport,
    topics: HashMap<u16, String>,
    seen_schemas: HashSet<u16>,
    seen_channels: HashSet<u16>,
    /// Each schema and channel id's first definition, to refuse a conflicting second one.
    definitions: HashMap<(Definition, u16), (String, u64)>,
    /// File offset of the record (or chunk) being visited.
    offset: u64,
    /// Offsets of the chunk records read (or found broken) so far.
    chunks_read: HashSet<u64>,
    /// Chunk offsets already used to recover from damage, so recovery never loops.
    recovery_tried: HashSet<u64>,
    /// A broken chunk is completed from the message indexes that follow it (they
    /// list its messages per channel) before it is reported or fails the read.
    pending_bad: Option<(BadChunk, BTreeSet<u16>, u64)>,
    /// Past the data end record: damage here loses no message.
    in_summary_section: bool,
    visit: V,
    progress: P,
}

fn linear_reader(skip_start_magic: bool, limit: u64) -> LinearReader {
    let limit = usize::try_from(limit).unwrap_or(usize::MAX);
    LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_emit_chunks(true)
            .with_skip_start_magic(skip_start_magic)
            .with_record_length_limit(limit),
    )
}

/// A fresh reader for the records from file offset `at` on (the file's magic is behind).
fn reader_at<R: Seek>(src: &mut R, at: u64, limit: u64) -> Result<LinearReader, ReadError> {
    src.seek(SeekFrom::Start(at))?;
    Ok(linear_reader(true, limit))
}

impl<V, P> Walk<V, P>
where
    V: FnMut(&Record<'_>) -> anyhow::Result<()>,
    P: FnMut(u64),
{
    fn run<R: Read + Seek>(&mut self, mut src: R) -> Result<(), ReadError> {
        let limit = self
            .file_len
            .unwrap_or(MAX_RECORD_BYTES)
            .min(MAX_RECORD_BYTES);
        let mut reader = linear_reader(false, limit);
        // File offset of the next byte handed to the reader, and of the next record.
        let (mut fed, mut next_record) = (0u64, 8u64);
        let mut seen_any = false;
        loop {
            let Some(event) = reader.next_event() else {
                break;
            };
            let failure = match event {
                Ok(LinearReadEvent::ReadRequest(n)) => {
                    match self.feed(&mut src, &mut reader, fed, n)? {
                        Ok(got) => {
                            fed += got;
                            continue;
                        }
                        Err(why) => why,
                    }
                }
                Ok(LinearReadEvent::Record { opcode, data }) => {
                    seen_any = true;
                    let len = 9 + data.len() as u64;
                    if opcode == op::CHUNK
                        && let Some(indexed) = self.indexed_chunk_length(next_record)
                        && indexed != len
                        && self.read_chunk_by_index(&mut src, next_record, indexed)?
                    {
                        // The length field disagrees with the CRC-checked index: the index wins.
                        self.report.repaired.push(format!(
                            "chunk at offset {next_record}: its record length says {len} bytes, the summary's chunk index {indexed}; read by the index"
                        ));
                        let at = next_record + indexed;
                        reader = reader_at(&mut src, at, limit)?;
                        (fed, next_record) = (at, at);
                        continue;
                    }
                    self.record(next_record, opcode, data)?;
                    next_record += len;
                    self.report.bytes_read += len + if opcode == op::FOOTER { 8 } else { 0 };
                    (self.progress)(self.report.bytes_read);
                    continue;
                }
                Err(e) => e.to_string(),
            };
            // Damage before the first record: only an intact summary can tell this is MCAP.
            if !seen_any && self.summary.is_none() {
                return Err(ReadError::NotMcap(failure));
            }
            self.settle_bad_chunk()?;
            // A chunk the index knows starts here, framed wrong: read it by the index's length.
            if let Some(indexed) = self.indexed_chunk_length(next_record)
                && self.recovery_tried.insert(next_record)
                && self.read_chunk_by_index(&mut src, next_record, indexed)?
            {
                self.report.repaired.push(format!(
                    "chunk at offset {next_record}: unreadable as framed ({failure}); read by the summary's chunk index ({indexed} bytes)"
                ));
                let at = next_record + indexed;
                reader = reader_at(&mut src, at, limit)?;
                (fed, next_record) = (at, at);
                continue;
            }
            match self.resync_target(next_record) {
                Some(target) => {
                    let record = peek_record_kind(&mut src, next_record);
                    let reason = if target < next_record {
                        format!(
                            "{failure}; the record before it was framed wrong, and reading resumed at the chunk at offset {target} of the summary's chunk index"
                        )
                    } else {
                        failure
                    };
                    self.damaged_record(BadRecord {
                        offset: next_record,
                        record,
                        reason,
                        skipped_bytes: target.saturating_sub(next_record),
                    })?;
                    reader = reader_at(&mut src, target, limit)?;
                    (fed, next_record) = (target, target);
                }
                None => {
                    self.stop(next_record, failure);
                    return Ok(());
                }
            }
        }
        self.settle_bad_chunk()
    }

    /// Reads up to `n` requested bytes into the reader; a request the rest of the file
    /// cannot satisfy is refused before anything is allocated.
    fn feed<R: Read>(
        &mut self,
        src: &mut R,
        reader: &mut LinearReader,
        fed: u64,
        n: usize,
    ) -> Result<Result<u64, String>, ReadError> {
        if let Some(len) = self.file_len
            && fed.saturating_add(n as u64) > len
        {
            return Ok(Err(format!(
                "a record needs {} more bytes at offset {fed}, but the file ends {} bytes later (truncated recording or damaged length field)",
                n,
                len.saturating_sub(fed)
            )));
        }
        let buf = reader.insert(n);
        let got = loop {
            match src.read(buf) {
                Ok(k) => break k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(ReadError::Io(e)),
            }
        };
        reader.notify_read(got);
        Ok(Ok(got as u64))
    }

    /// Where reading can go on after damage at `offset`: the first chunk of the summary's
    /// chunk index after the last chunk read that has not been read, even one before
    /// `offset` (a record framed too long swallows what follows it), else the summary
    /// section itself. Each chunk serves as a target once, so recovery cannot loop.
    fn resync_target(&mut self, offset: u64) -> Option<u64> {
        let s = self.summary.as_ref()?;
        let floor = self.chunks_read.iter().copied().max().unwrap_or(0);
        let target = s
            .chunk_offsets
            .iter()
            .copied()
            .find(|&o| {
                o > floor
                    && o != offset
                    && !self.chunks_read.contains(&o)
                    && !self.recovery_tried.contains(&o)
            })
            .or((s.start > offset).then_some(s.start))?;
        self.recovery_tried.insert(target);
        Some(target)
    }

    /// The whole record length (opcode and length field included) that the summary's chunk
    /// index gives the chunk starting at `offset`.
    fn indexed_chunk_length(&self, offset: u64) -> Option<u64> {
        self.summary
            .as_ref()?
            .chunks
            .iter()
            .find(|c| c.chunk_start_offset == offset)
            .map(|c| c.chunk_length)
    }

    /// Reads the chunk at `offset` as `length` bytes (from the chunk index) and visits it;
    /// false when those bytes are not a chunk record the file can hold.
    fn read_chunk_by_index<R: Read + Seek>(
        &mut self,
        src: &mut R,
        offset: u64,
        length: u64,
    ) -> Result<bool, ReadError> {
        let fits = self
            .file_len
            .is_some_and(|len| offset.checked_add(length).is_some_and(|end| end <= len));
        if !(9..=MAX_RECORD_BYTES).contains(&length) || !fits {
            return Ok(false);
        }
        src.seek(SeekFrom::Start(offset))?;
        let mut buf = vec![0u8; length as usize];
        src.read_exact(&mut buf)?;
        if buf[0] != op::CHUNK || parse_record(op::CHUNK, &buf[9..]).is_err() {
            return Ok(false);
        }
        self.record(offset, op::CHUNK, &buf[9..])?;
        self.report.bytes_read += length;
        (self.progress)(self.report.bytes_read);
        Ok(true)
    }

    fn stop(&mut self, offset: u64, why: String) {
        self.report.stopped = Some(if why.contains("UnexpectedEof") || why.contains("ends") {
            format!(
                "the file ends in the middle of the record at offset {offset} (truncated recording): {why}"
            )
        } else {
            format!("unreadable record at offset {offset}: {why}")
        });
        self.report.unread_bytes = self
            .file_len
            .map_or(0, |len| len.saturating_sub(self.report.bytes_read));
    }

    /// A damaged record: fatal under [`OnError::Fail`] unless it lies in the summary
    /// section (indexes only; every message was read before it).
    fn damaged_record(&mut self, bad: BadRecord) -> Result<(), ReadError> {
        if self.on_error == OnError::Fail && !self.in_summary_section {
            return Err(ReadError::BadRecord(bad));
        }
        self.report.bad_records.push(bad);
        Ok(())
    }

    /// One framed record at file offset `offset`.
    fn record(&mut self, offset: u64, opcode: u8, data: &[u8]) -> Result<(), ReadError> {
        self.offset = offset;
        if opcode == op::CHUNK {
            self.chunks_read.insert(offset);
        }
        if opcode == op::MESSAGE_INDEX {
            if let Some((_, channels, indexed)) = self.pending_bad.as_mut()
                && let Ok(Record::MessageIndex(index)) = parse_record(opcode, data)
            {
                channels.insert(index.channel_id);
                *indexed += index.records.len() as u64;
            }
        } else {
            self.settle_bad_chunk()?;
        }
        match opcode {
            op::FOOTER => self.report.complete = true,
            op::DATA_END => self.in_summary_section = true,
            _ => {}
        }
        match parse_record(opcode, data) {
            Ok(Record::Chunk { header, data }) => self.chunk(offset, &header, &data),
            Ok(rec) => self.emit(&rec),
            Err(e) if opcode == op::CHUNK => {
                let bad = self.bad_chunk_at(offset, format!("unreadable chunk header: {e}"));
                self.pending_bad = Some((bad, BTreeSet::new(), 0));
                Ok(())
            }
            Err(e) => match lenient::parse(opcode, data) {
                Some((rec, note)) => {
                    self.report.repaired.push(format!(
                        "{} at offset {offset}: {note}",
                        record_kind(opcode)
                    ));
                    self.emit(&rec)
                }
                None => self.damaged_record(BadRecord {
                    offset,
                    record: record_kind(opcode),
                    reason: e,
                    skipped_bytes: 0,
                }),
            },
        }
    }

    fn chunk(
        &mut self,
        offset: u64,
        header: &mcap::records::ChunkHeader,
        data: &[u8],
    ) -> Result<(), ReadError> {
        let records = match open_chunk(header, data) {
            Ok((records, note)) => {
                if let Some(note) = note {
                    self.report
                        .repaired
                        .push(format!("{note} (chunk at offset {offset})"));
                }
                records
            }
            Err(reason) => {
                let mut bad = describe_bad_chunk(reason, header, data, &self.topics);
                bad.offset = offset;
                self.pending_bad = Some((bad, BTreeSet::new(), 0));
                return Ok(());
            }
        };
        let mut damage = None;
        let mut skipped = Vec::new();
        let walked = for_each_record(
            &records,
            |rec| {
                self.emit(rec).map_err(|e| match e {
                    ReadError::Visitor(e) => e,
                    other => anyhow::anyhow!("{other}"),
                })
            },
            |at, opcode, error| skipped.push((at, opcode, error)),
        );
        for (at, opcode, reason) in skipped {
            self.damaged_record(BadRecord {
                offset,
                record: format!("{} at byte {at} of the chunk", record_kind(opcode)),
                reason,
                skipped_bytes: 0,
            })?;
        }
        match walked {
            Ok(()) => {}
            Err(ChunkWalk::Visitor(e)) => return Err(ReadError::Visitor(e)),
            Err(ChunkWalk::Record { at, error }) => damage = Some((at, error)),
        }
        if let Some((at, error)) = damage {
            let mut bad = describe_bad_chunk(
                format!(
                    "record at byte {at} of the chunk is unreadable ({error}); the chunk's later records are lost"
                ),
                header,
                &[],
                &self.topics,
            );
            bad.offset = offset;
            self.pending_bad = Some((bad, BTreeSet::new(), 0));
        }
        Ok(())
    }

    /// What the summary's chunk index says about the chunk at `offset`.
    fn bad_chunk_at(&self, offset: u64, reason: String) -> BadChunk {
        let index = self
            .summary
            .as_ref()
            .and_then(|s| s.chunks.iter().find(|c| c.chunk_start_offset == offset));
        let topics = index
            .map(|c| {
                c.message_index_offsets
                    .keys()
                    .map(|id| self.topic_name(*id))
                    .collect()
            })
            .unwrap_or_default();
        BadChunk {
            reason,
            topics,
            start_nanos: index.map_or(0, |c| c.message_start_time),
            end_nanos: index.map_or(0, |c| c.message_end_time),
            messages: 0,
            offset,
        }
    }

    fn topic_name(&self, id: u16) -> String {
        self.topics
            .get(&id)
            .cloned()
            .or_else(|| self.summary.as_ref().and_then(|s| s.topic(id)))
            .unwrap_or_else(|| format!("channel {id}"))
    }

    /// Visits `rec`, first visiting the summary's copy of a schema or channel it
    /// refers to whose own record was lost (e.g. in a skipped chunk).
    fn emit(&mut self, rec: &Record<'_>) -> Result<(), ReadError> {
        let (schema, channel) = match rec {
            Record::Channel(c) => (Some(c.schema_id), None),
            Record::Message { header, .. } => (None, Some(header.channel_id)),
            _ => (None, None),
        };
        if let Some(id) = channel
            && !self.seen_channels.contains(&id)
            && let Some(c) = self
                .summary
                .as_ref()
                .and_then(|s| s.channels.get(&id).cloned())
        {
            self.report
                .from_summary
                .push(format!("channel {id} ({})", c.topic));
            self.emit(&Record::Channel(c))?;
        }
        if let Some(id) = schema.filter(|&s| s != 0)
            && !self.seen_schemas.contains(&id)
            && let Some((header, data)) = self
                .summary
                .as_ref()
                .and_then(|s| s.schemas.get(&id).cloned())
        {
            self.report
                .from_summary
                .push(format!("schema {id} ({})", header.name));
            self.emit(&Record::Schema {
                header,
                data: data.into(),
            })?;
        }
        self.check_definition(rec)?;
        match rec {
            Record::Schema { header, .. } => {
                self.seen_schemas.insert(header.id);
            }
            Record::Channel(c) => {
                self.seen_channels.insert(c.id);
                self.topics.insert(c.id, c.topic.clone());
            }
            _ => {}
        }
        (self.visit)(rec)?;
        Ok(())
    }

    /// Refuses a schema or channel id defined again with other contents (repeating the same
    /// definition, as chunks and the summary do, is fine).
    fn check_definition(&mut self, rec: &Record<'_>) -> Result<(), ReadError> {
        let Some((kind, id, described)) = Definition::of(rec) else {
            return Ok(());
        };
        match self.definitions.get(&(kind, id)) {
            None => {
                self.definitions
                    .insert((kind, id), (described, self.offset));
                Ok(())
            }
            Some((first, _)) if *first == described => Ok(()),
            Some((first, at)) => Err(ReadError::Redefined(format!(
                "{kind} id {id} is defined twice with different contents: as {first} (at offset {at}) and as {described} (at offset {}); ids must be unique in an MCAP file, and the messages recorded under this one cannot be told apart",
                self.offset
            ))),
        }
    }

    /// Reports (or, with [`OnError::Fail`], raises) a broken chunk once the message
    /// indexes after it have been counted in.
    fn settle_bad_chunk(&mut self) -> Result<(), ReadError> {
        let Some((mut bad, channels, indexed)) = self.pending_bad.take() else {
            return Ok(());
        };
        bad.messages = bad.messages.max(indexed);
        for id in channels {
            let topic = self.topic_name(id);
            if !bad.topics.contains(&topic) {
                bad.topics.push(topic);
            }
        }
        if self.on_error == OnError::Fail {
            return Err(ReadError::BadChunk(bad));
        }
        self.report.bad_chunks.push(bad);
        Ok(())
    }
}

/// The two kinds of record that define an id other records refer to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Definition {
    Schema,
    Channel,
}

impl Definition {
    /// The kind, id and a description of everything a definition says (two definitions
    /// agree when their descriptions do).
    fn of(rec: &Record<'_>) -> Option<(Self, u16, String)> {
        match rec {
            Record::Schema { header, data } => Some((
                Definition::Schema,
                header.id,
                format!(
                    "'{}' ({} encoding, {} bytes, CRC32 {:08x})",
                    header.name,
                    header.encoding,
                    data.len(),
                    crc32fast::hash(data)
                ),
            )),
            Record::Channel(c) => Some((
                Definition::Channel,
                c.id,
                format!(
                    "topic '{}' (schema {}, {} messages, metadata {:?})",
                    c.topic, c.schema_id, c.message_encoding, c.metadata
                ),
            )),
            _ => None,
        }
    }
}

impl std::fmt::Display for Definition {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Definition::Schema => "schema",
            Definition::Channel => "channel",
        })
    }
}

mod chunk;
mod lenient;
mod record;
mod summary;

use chunk::{ChunkWalk, describe_bad_chunk, for_each_record, open_chunk};
use record::{parse_record, peek_record_kind, record_kind};
pub use summary::Summary;
#[cfg(test)]
mod tests;
