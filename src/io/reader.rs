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

/// One field of a record's layout, as far as lengths go.
#[derive(Clone, Copy)]
enum Field {
    Fixed(usize),
    /// u32 length + bytes (strings and schema data).
    Bytes32,
    /// u64 length + bytes (chunk records, attachment data).
    Bytes64,
    /// u32 byte length + entries of two u32-length strings.
    StringMap,
    /// Everything to the end (message data).
    Rest,
}

/// The fields of each record kind (MCAP specification), for [`check_lengths`].
fn layout(opcode: u8) -> &'static [Field] {
    use Field::*;
    match opcode {
        op::HEADER => &[Bytes32, Bytes32],
        op::SCHEMA => &[Fixed(2), Bytes32, Bytes32, Bytes32],
        op::CHANNEL => &[Fixed(4), Bytes32, Bytes32, StringMap],
        op::MESSAGE => &[Fixed(22), Rest],
        op::CHUNK => &[Fixed(28), Bytes32, Bytes64],
        op::MESSAGE_INDEX => &[Fixed(2), Bytes32],
        op::CHUNK_INDEX => &[Fixed(32), Bytes32, Fixed(8), Bytes32, Fixed(16)],
        op::ATTACHMENT => &[Fixed(16), Bytes32, Bytes32, Bytes64, Fixed(4)],
        op::ATTACHMENT_INDEX => &[Fixed(40), Bytes32, Bytes32],
        op::STATISTICS => &[Fixed(42), Bytes32],
        op::METADATA => &[Bytes32, StringMap],
        op::METADATA_INDEX => &[Fixed(16), Bytes32],
        _ => &[Rest],
    }
}

/// Checks every length field of a record against the record's own size before the
/// mcap crate parses it: its parser allocates what a length field says first, so a
/// flipped bit in one would ask for gigabytes.
fn check_lengths(opcode: u8, data: &[u8]) -> Result<(), String> {
    let mut at = 0usize;
    let take = |at: &mut usize, n: u64, what: &str| -> Result<(), String> {
        let left = (data.len() - *at) as u64;
        if n > left {
            return Err(format!(
                "{what} of {n} bytes at byte {} of the record, only {left} left",
                *at
            ));
        }
        *at += n as usize;
        Ok(())
    };
    let read_len = |at: &mut usize, width: usize| -> Result<u64, String> {
        let bytes = data
            .get(*at..*at + width)
            .ok_or_else(|| format!("record cut short at byte {}", *at))?;
        *at += width;
        let mut buf = [0u8; 8];
        buf[..width].copy_from_slice(bytes);
        Ok(u64::from_le_bytes(buf))
    };
    for field in layout(opcode) {
        match *field {
            Field::Fixed(n) => take(&mut at, n as u64, "fixed fields")?,
            Field::Bytes32 => {
                let n = read_len(&mut at, 4)?;
                take(&mut at, n, "a field")?;
            }
            Field::Bytes64 => {
                let n = read_len(&mut at, 8)?;
                take(&mut at, n, "a field")?;
            }
            Field::StringMap => {
                let n = read_len(&mut at, 4)?;
                let end = at;
                take(&mut at, n, "a map")?;
                let mut inner = end;
                while inner < at {
                    for _ in 0..2 {
                        let len = data
                            .get(inner..inner + 4)
                            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
                            .ok_or("map entry cut short")?;
                        inner = inner
                            .checked_add(4 + len)
                            .filter(|&e| e <= at)
                            .ok_or_else(|| format!("map entry of {len} bytes overruns its map"))?;
                    }
                }
            }
            Field::Rest => return Ok(()),
        }
    }
    Ok(())
}

/// `mcap::parse_record` after [`check_lengths`].
fn parse_record(opcode: u8, data: &[u8]) -> Result<Record<'_>, String> {
    check_lengths(opcode, data)?;
    mcap::parse_record(opcode, data).map_err(|e| e.to_string())
}

/// The kind of record with `opcode`, for messages.
fn record_kind(opcode: u8) -> String {
    let name = match opcode {
        op::HEADER => "header",
        op::FOOTER => "footer",
        op::SCHEMA => "schema",
        op::CHANNEL => "channel",
        op::MESSAGE => "message",
        op::CHUNK => "chunk",
        op::MESSAGE_INDEX => "message index",
        op::CHUNK_INDEX => "chunk index",
        op::ATTACHMENT => "attachment",
        op::ATTACHMENT_INDEX => "attachment index",
        op::STATISTICS => "statistics",
        op::METADATA => "metadata",
        op::METADATA_INDEX => "metadata index",
        op::SUMMARY_OFFSET => "summary offset",
        op::DATA_END => "data end",
        _ => "unknown record",
    };
    format!("{name} (opcode {opcode:#04x})")
}

/// The kind and declared length of the record at `offset`, read without trusting it.
fn peek_record_kind<R: Read + Seek>(src: &mut R, offset: u64) -> String {
    let mut head = [0u8; 9];
    let read = src
        .seek(SeekFrom::Start(offset))
        .and_then(|_| src.read_exact(&mut head));
    match read {
        Ok(()) => format!(
            "{} declaring {} bytes",
            record_kind(head[0]),
            u64::from_le_bytes(head[1..9].try_into().unwrap_or_default())
        ),
        Err(_) => "record".into(),
    }
}

/// The summary section of a file whose footer and summary are intact: its schemas and
/// channels, and where each chunk starts.
#[derive(Debug, Default)]
pub struct Summary {
    /// File offset of the summary section.
    pub start: u64,
    pub schemas: HashMap<u16, (mcap::records::SchemaHeader, Vec<u8>)>,
    pub channels: HashMap<u16, mcap::records::Channel>,
    pub chunks: Vec<mcap::records::ChunkIndex>,
    /// Chunk start offsets, ascending.
    pub chunk_offsets: Vec<u64>,
}

/// Footer record (opcode, length, summary start, summary offset start, CRC) + end magic.
const FOOTER_AND_MAGIC: u64 = 1 + 8 + 20 + 8;

/// Largest summary section read into memory.
const MAX_SUMMARY_BYTES: u64 = 256 << 20;

impl Summary {
    /// Reads and checks the footer and summary section of a `file_len`-byte file.
    pub fn read<R: Read + Seek>(src: &mut R, file_len: u64) -> Result<Summary, String> {
        if file_len < 8 + FOOTER_AND_MAGIC {
            return Err("too short for a footer".into());
        }
        let footer_at = file_len - FOOTER_AND_MAGIC;
        let mut tail = [0u8; FOOTER_AND_MAGIC as usize];
        src.seek(SeekFrom::Start(footer_at))
            .and_then(|_| src.read_exact(&mut tail))
            .map_err(|e| e.to_string())?;
        if tail[0] != op::FOOTER || tail[29..] != mcap::MAGIC[..] {
            return Err("no footer".into());
        }
        let u64_at = |k: usize| u64::from_le_bytes(tail[k..k + 8].try_into().unwrap_or_default());
        let (start, crc) = (
            u64_at(9),
            u32::from_le_bytes(tail[25..29].try_into().unwrap_or_default()),
        );
        if start < 8 || start >= footer_at || footer_at - start > MAX_SUMMARY_BYTES {
            return Err(format!("footer gives an impossible summary start {start}"));
        }
        let mut bytes = vec![0u8; (footer_at - start) as usize];
        src.seek(SeekFrom::Start(start))
            .and_then(|_| src.read_exact(&mut bytes))
            .map_err(|e| e.to_string())?;
        if crc != 0 {
            let mut hasher = crc32fast::Hasher::new();
            hasher.update(&bytes);
            hasher.update(&tail[..25]);
            if hasher.finalize() != crc {
                return Err("summary CRC mismatch".into());
            }
        }
        let mut summary = Summary {
            start,
            ..Default::default()
        };
        let mut unreadable = false;
        for_each_record(
            &bytes,
            |rec| {
                summary.add(rec);
                Ok(())
            },
            |_, _, _| unreadable = true,
        )
        .ok()
        .filter(|_| !unreadable)
        .ok_or_else(|| "unreadable summary record".to_string())?;
        summary.chunk_offsets = summary
            .chunks
            .iter()
            .map(|c| c.chunk_start_offset)
            .collect();
        summary.chunk_offsets.sort_unstable();
        summary.chunk_offsets.retain(|&o| o >= 8 && o < start);
        Ok(summary)
    }

    fn add(&mut self, rec: &Record<'_>) {
        match rec {
            Record::Schema { header, data } => {
                self.schemas
                    .insert(header.id, (header.clone(), data.to_vec()));
            }
            Record::Channel(c) => {
                self.channels.insert(c.id, c.clone());
            }
            Record::ChunkIndex(c) => self.chunks.push(c.clone()),
            _ => {}
        }
    }

    fn topic(&self, id: u16) -> Option<String> {
        self.channels.get(&id).map(|c| c.topic.clone())
    }
}

/// Decompresses a chunk into at most its declared size, which is checked against
/// [`MAX_RECORD_BYTES`] first: memory follows the bytes actually produced, never a
/// size read from the file.
fn decompress(header: &mcap::records::ChunkHeader, data: &[u8]) -> Result<Vec<u8>, String> {
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
fn open_chunk(
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
fn check_crc(header: &mcap::records::ChunkHeader, records: &[u8]) -> Result<(), String> {
    let calculated = crc32fast::hash(records);
    if header.uncompressed_crc != 0 && calculated != header.uncompressed_crc {
        return Err(format!(
            "CRC mismatch (saved {:#010x}, calculated {calculated:#010x})",
            header.uncompressed_crc
        ));
    }
    Ok(())
}

enum ChunkWalk {
    /// The record at byte `at` of the buffer is cut short or unparsable.
    Record {
        at: usize,
        error: String,
    },
    Visitor(anyhow::Error),
}

/// Walks the records packed in a chunk: opcode (1), length (8), body.
fn for_each_record(
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

/// What the reference readers still read where the mcap crate's parser refuses: a metadata
/// record with a repeated key (the last value wins, as Python's reader keeps it) and an
/// attachment whose CRC does not match (its contents are returned; the copy gets a CRC of its
/// own). Each comes with a note for the report.
mod lenient {
    use std::borrow::Cow;
    use std::collections::BTreeMap;

    use mcap::records::{AttachmentHeader, Metadata, Record, op};

    pub fn parse(opcode: u8, data: &[u8]) -> Option<(Record<'_>, String)> {
        let mut c = Cursor(data);
        match opcode {
            op::METADATA => {
                let name = c.string()?;
                let map_len = usize::try_from(c.u32()?).ok()?;
                let mut map = Cursor(c.take(map_len)?);
                let (mut metadata, mut repeated) = (BTreeMap::new(), Vec::new());
                while !map.0.is_empty() {
                    let (k, v) = (map.string()?, map.string()?);
                    if let Some(old) = metadata.insert(k.clone(), v) {
                        repeated.push(format!("{k:?} (dropped value {old:?})"));
                    }
                }
                (c.0.is_empty() && !repeated.is_empty()).then(|| {
                    let note = format!(
                        "repeated keys in metadata {name:?}, the last value kept: {}",
                        repeated.join(", ")
                    );
                    (Record::Metadata(Metadata { name, metadata }), note)
                })
            }
            op::ATTACHMENT => {
                let (log_time, create_time) = (c.u64()?, c.u64()?);
                let (name, media_type) = (c.string()?, c.string()?);
                let len = usize::try_from(c.u64()?).ok()?;
                let body = c.take(len)?;
                let crc = c.u32()?;
                let calculated = crc32fast::hash(&data[..data.len() - c.0.len() - 4]);
                (c.0.is_empty() && crc != 0 && crc != calculated).then(|| {
                    let note = format!(
                        "attachment {name:?}: CRC mismatch (saved {crc:#010x}, calculated {calculated:#010x}); copied as read"
                    );
                    let header = AttachmentHeader {
                        log_time,
                        create_time,
                        name,
                        media_type,
                    };
                    let rec = Record::Attachment {
                        header,
                        data: Cow::Borrowed(body),
                        crc: calculated,
                    };
                    (rec, note)
                })
            }
            _ => None,
        }
    }

    /// Little-endian fields off the front of a byte slice.
    struct Cursor<'a>(&'a [u8]);

    impl<'a> Cursor<'a> {
        fn take(&mut self, n: usize) -> Option<&'a [u8]> {
            let (head, rest) = (self.0.get(..n)?, self.0.get(n..)?);
            self.0 = rest;
            Some(head)
        }
        fn u32(&mut self) -> Option<u32> {
            Some(u32::from_le_bytes(self.take(4)?.try_into().ok()?))
        }
        fn u64(&mut self) -> Option<u64> {
            Some(u64::from_le_bytes(self.take(8)?.try_into().ok()?))
        }
        fn string(&mut self) -> Option<String> {
            let n = usize::try_from(self.u32()?).ok()?;
            String::from_utf8(self.take(n)?.to_vec()).ok()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
