//! Atomic MCAP output: records are written to a temporary file beside the target
//! and renamed over it only after `finish()`; a failed or abandoned write leaves
//! the target untouched. Copies input schemas, channels, messages, attachments and
//! metadata unchanged (ids kept where free) and adds our own output channels.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use mcap::records::{MessageHeader, Record};

use super::decoders::Family;
use super::encoders::{self, Kind};

/// Where an output record came from, for counting what was copied.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct CopyCounts {
    pub schemas: u64,
    pub channels: u64,
    pub messages: u64,
    pub attachments: u64,
    pub metadata: u64,
    /// Messages whose channel was never defined (e.g. it sat in a skipped chunk).
    pub orphan_messages: u64,
}

/// How output files are chunked and compressed.
#[derive(Debug, Clone, Copy)]
pub struct WriterSettings {
    /// `None` writes uncompressed chunks.
    pub compression: Option<mcap::Compression>,
    /// Target bytes per chunk before compression; `None` writes no chunks.
    pub chunk_size: Option<u64>,
}

impl Default for WriterSettings {
    fn default() -> Self {
        WriterSettings {
            compression: Some(mcap::Compression::Zstd),
            chunk_size: Some(4 * 1024 * 1024),
        }
    }
}

/// An MCAP file being written; becomes visible at its path only on [`finish`](Self::finish).
pub struct McapOutput {
    writer: Option<mcap::Writer<BufWriter<File>>>,
    tmp_path: PathBuf,
    path: PathBuf,
    schema_ids: HashMap<u16, u16>,
    channel_ids: HashMap<u16, u16>,
    used_schema_ids: HashSet<u16>,
    used_channel_ids: HashSet<u16>,
    own_schemas: HashMap<(Family, Kind), u16>,
    own_channels: HashMap<String, u16>,
    own_sequence: HashMap<u16, u32>,
    pub copied: CopyCounts,
}

impl McapOutput {
    /// Starts writing `path` (via a temporary file in the same folder). An existing
    /// `path` is refused unless `force`.
    pub fn create(path: &Path, force: bool) -> anyhow::Result<Self> {
        Self::create_with(path, force, WriterSettings::default())
    }

    /// [`create`](Self::create) with the given chunking and compression.
    pub fn create_with(path: &Path, force: bool, settings: WriterSettings) -> anyhow::Result<Self> {
        if path.exists() && !force {
            bail!("{} exists; pass --force to overwrite it", path.display());
        }
        let dir = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let name = path
            .file_name()
            .with_context(|| format!("{} is not a file path", path.display()))?;
        let tmp_path = dir.join(format!(
            ".{}.{}.tmp",
            name.to_string_lossy(),
            std::process::id()
        ));
        let file = File::create(&tmp_path)
            .with_context(|| format!("cannot create {}", tmp_path.display()))?;
        let options = mcap::WriteOptions::new()
            .compression(settings.compression)
            .compression_level(3)
            .chunk_size(settings.chunk_size)
            .library(format!("rangegan-mcap {}", env!("CARGO_PKG_VERSION")));
        let writer = options
            .create(BufWriter::with_capacity(1 << 20, file))
            .context("cannot start MCAP writer")?;
        Ok(McapOutput {
            writer: Some(writer),
            tmp_path,
            path: path.to_path_buf(),
            schema_ids: HashMap::new(),
            channel_ids: HashMap::new(),
            used_schema_ids: HashSet::new(),
            used_channel_ids: HashSet::new(),
            own_schemas: HashMap::new(),
            own_channels: HashMap::new(),
            own_sequence: HashMap::new(),
            copied: CopyCounts::default(),
        })
    }

    fn writer(&mut self) -> anyhow::Result<&mut mcap::Writer<BufWriter<File>>> {
        self.writer.as_mut().context("MCAP writer already finished")
    }

    /// The input id if still free, else the next free one (ids are per-file handles,
    /// so renumbering changes nothing a reader sees).
    fn claim(used: &mut HashSet<u16>, wanted: u16) -> anyhow::Result<u16> {
        let id = if wanted != 0 && !used.contains(&wanted) {
            wanted
        } else {
            (1..=u16::MAX)
                .find(|i| !used.contains(i))
                .context("more than 65535 ids")?
        };
        used.insert(id);
        Ok(id)
    }

    /// Copies one input record. Summary, index and chunk records are not copied
    /// (the writer rebuilds them); returns whether the record was copied.
    pub fn copy_record(&mut self, record: &Record<'_>) -> anyhow::Result<bool> {
        match record {
            Record::Schema { header, data } => {
                if self.schema_ids.contains_key(&header.id) {
                    return Ok(true); // repeated in the summary or another chunk
                }
                let id = Self::claim(&mut self.used_schema_ids, header.id)?;
                self.writer()?
                    .add_schema_with_id(id, &header.name, &header.encoding, data)?;
                self.schema_ids.insert(header.id, id);
                self.copied.schemas += 1;
            }
            Record::Channel(c) => {
                if self.channel_ids.contains_key(&c.id) {
                    return Ok(true);
                }
                let schema_id = match c.schema_id {
                    0 => 0,
                    s => *self
                        .schema_ids
                        .get(&s)
                        .with_context(|| format!("channel {} names unknown schema {s}", c.topic))?,
                };
                let id = Self::claim(&mut self.used_channel_ids, c.id)?;
                self.writer()?.add_channel_with_id(
                    id,
                    schema_id,
                    &c.topic,
                    &c.message_encoding,
                    &c.metadata,
                )?;
                self.channel_ids.insert(c.id, id);
                self.copied.channels += 1;
            }
            Record::Message { header, data } => {
                let Some(&channel_id) = self.channel_ids.get(&header.channel_id) else {
                    self.copied.orphan_messages += 1;
                    return Ok(false);
                };
                self.writer()?.write_to_known_channel(
                    &MessageHeader {
                        channel_id,
                        ..*header
                    },
                    data,
                )?;
                self.copied.messages += 1;
            }
            Record::Attachment { header, data, .. } => {
                let attachment = mcap::Attachment {
                    log_time: header.log_time,
                    create_time: header.create_time,
                    name: header.name.clone(),
                    media_type: header.media_type.clone(),
                    data: std::borrow::Cow::Borrowed(data),
                };
                self.writer()?.attach(&attachment)?;
                self.copied.attachments += 1;
            }
            Record::Metadata(m) => {
                self.writer()?.write_metadata(m)?;
                self.copied.metadata += 1;
            }
            _ => return Ok(false),
        }
        Ok(true)
    }

    /// The id of an input channel in the output, if it was copied.
    pub fn copied_channel(&self, input_id: u16) -> Option<u16> {
        self.channel_ids.get(&input_id).copied()
    }

    /// Adds (once) an output channel `topic` carrying `kind` payloads in `family`.
    /// Own ids count down from the top so they rarely meet input ids.
    pub fn own_channel(&mut self, topic: &str, family: Family, kind: Kind) -> anyhow::Result<u16> {
        if let Some(&id) = self.own_channels.get(topic) {
            return Ok(id);
        }
        let schema_id = match self.own_schemas.get(&(family, kind)) {
            Some(&id) => id,
            None => {
                let s = encoders::schema(family, kind);
                let id = (1..=u16::MAX)
                    .rev()
                    .find(|i| !self.used_schema_ids.contains(i))
                    .context("no schema id left")?;
                self.used_schema_ids.insert(id);
                self.writer()?
                    .add_schema_with_id(id, &s.name, &s.encoding, &s.data)?;
                self.own_schemas.insert((family, kind), id);
                id
            }
        };
        let id = (1..=u16::MAX)
            .rev()
            .find(|i| !self.used_channel_ids.contains(i))
            .context("no channel id left")?;
        self.used_channel_ids.insert(id);
        let encoding = encoders::message_encoding(family);
        self.writer()?
            .add_channel_with_id(id, schema_id, topic, encoding, &BTreeMap::new())?;
        self.own_channels.insert(topic.to_string(), id);
        Ok(id)
    }

    /// Writes a message on one of our own channels.
    pub fn write_own(
        &mut self,
        channel_id: u16,
        log_time: u64,
        publish_time: u64,
        data: &[u8],
    ) -> anyhow::Result<()> {
        let seq = self.own_sequence.entry(channel_id).or_insert(0);
        *seq += 1;
        let header = MessageHeader {
            channel_id,
            sequence: *seq,
            log_time,
            publish_time,
        };
        self.writer()?.write_to_known_channel(&header, data)?;
        Ok(())
    }

    /// Writes a metadata record of our own.
    pub fn write_metadata(
        &mut self,
        name: &str,
        entries: BTreeMap<String, String>,
    ) -> anyhow::Result<()> {
        self.writer()?.write_metadata(&mcap::records::Metadata {
            name: name.into(),
            metadata: entries,
        })?;
        Ok(())
    }

    /// Completes the file (summary, footer), syncs it and renames it into place.
    pub fn finish(mut self) -> anyhow::Result<()> {
        let mut writer = self.writer.take().context("MCAP writer already finished")?;
        writer
            .finish()
            .with_context(|| format!("cannot finish {}", self.tmp_path.display()))?;
        let file = writer
            .into_inner()
            .into_inner()
            .map_err(|e| e.into_error())?;
        file.sync_all()?;
        drop(file);
        std::fs::rename(&self.tmp_path, &self.path).with_context(|| {
            format!(
                "cannot move {} to {}",
                self.tmp_path.display(),
                self.path.display()
            )
        })?;
        Ok(())
    }
}

impl Drop for McapOutput {
    fn drop(&mut self) {
        // Not finished: drop the partial temporary file, never the target.
        if self.writer.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp_path);
        }
    }
}
