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
    /// This output's channels by topic and family: one topic carried by channels of two
    /// families (ROS 2 and Foxglove, say) gets a channel of each, so every message is in
    /// the encoding its channel declares.
    own_channels: HashMap<(String, Family), u16>,
    own_sequence: HashMap<u16, u32>,
    /// Topics of input channels (copied or announced by the input's summary): our own
    /// channels never take one of these names.
    input_topics: HashSet<String>,
    pub copied: CopyCounts,
    /// What was changed to keep the output readable (a channel's missing schema, a
    /// renamed output topic), one sentence each, for the command's warnings.
    pub notes: Vec<String>,
}

/// Refuses to write `out` when it is one of `inputs`: the same path, a symlink to it or
/// a hard link of it (same device and inode). Inputs are never modified, `--force` or not.
pub fn refuse_overwriting_inputs(out: &Path, inputs: &[&Path]) -> anyhow::Result<()> {
    for input in inputs {
        if same_file(out, input) || (input.is_dir() && lies_in(out, input)) {
            bail!(
                "{}: output is the input {}; write to another file (inputs are never modified)",
                out.display(),
                input.display()
            );
        }
    }
    Ok(())
}

/// Whether `path` (which need not exist) lies inside the folder `dir`: a model folder, say,
/// whose files are all inputs.
pub fn lies_in(path: &Path, dir: &Path) -> bool {
    let Ok(dir) = dir.canonicalize() else {
        return false;
    };
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    match (parent.canonicalize(), path.file_name()) {
        (Ok(p), Some(name)) => p.join(name).starts_with(&dir),
        _ => false,
    }
}

/// Whether `a` and `b` name one file: equal paths, equal canonical paths, or (on Unix)
/// the same device and inode.
pub fn same_file(a: &Path, b: &Path) -> bool {
    if a == b {
        return true;
    }
    if let (Ok(x), Ok(y)) = (a.canonicalize(), b.canonicalize())
        && x == y
    {
        return true;
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if let (Ok(x), Ok(y)) = (std::fs::metadata(a), std::fs::metadata(b)) {
            return x.dev() == y.dev() && x.ino() == y.ino();
        }
    }
    false
}

/// A write error naming the output file and the operating system's reason.
fn write_error(path: &Path, e: mcap::McapError) -> anyhow::Error {
    match e {
        mcap::McapError::Io(io) => anyhow::anyhow!("cannot write {}: {io}", path.display()),
        other => anyhow::anyhow!("cannot write {}: {other}", path.display()),
    }
}

impl McapOutput {
    /// Starts writing `path` (via a temporary file in the same folder). An existing
    /// `path` is refused unless `force`.
    pub fn create(path: &Path, force: bool) -> anyhow::Result<Self> {
        Self::create_with(path, force, WriterSettings::default())
    }

    /// [`create`](Self::create) with the given chunking and compression.
    pub fn create_with(path: &Path, force: bool, settings: WriterSettings) -> anyhow::Result<Self> {
        if std::fs::symlink_metadata(path).is_ok() && !force {
            match std::fs::read_link(path) {
                // A symlink that points nowhere is still something standing at OUT.
                Ok(target) if !path.exists() => bail!(
                    "{} exists (a symlink to {}, which does not exist); pass --force to replace the link",
                    path.display(),
                    target.display()
                ),
                _ => bail!("{} exists; pass --force to overwrite it", path.display()),
            }
        }
        let dir = path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let name = path
            .file_name()
            .with_context(|| format!("{} is not a file path", path.display()))?;
        let name = name.to_string_lossy();
        super::cleanup::remove_stale(dir, &name);
        let tmp_path = dir.join(format!(".{name}.{}.tmp", std::process::id()));
        let file = File::create(&tmp_path)
            .with_context(|| format!("cannot create {}", tmp_path.display()))?;
        super::cleanup::register(&tmp_path);
        let options = mcap::WriteOptions::new()
            .compression(settings.compression)
            .compression_level(3)
            .chunk_size(settings.chunk_size)
            .library(format!("rangegan-mcap {}", env!("CARGO_PKG_VERSION")));
        let writer = match options.create(BufWriter::with_capacity(1 << 20, file)) {
            Ok(w) => w,
            Err(e) => {
                let _ = std::fs::remove_file(&tmp_path);
                super::cleanup::release(&tmp_path);
                return Err(write_error(path, e));
            }
        };
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
            input_topics: HashSet::new(),
            copied: CopyCounts::default(),
            notes: Vec::new(),
        })
    }

    /// Runs one write on the MCAP writer; an error names OUT and the OS error.
    fn write<T>(
        &mut self,
        f: impl FnOnce(&mut mcap::Writer<BufWriter<File>>) -> mcap::McapResult<T>,
    ) -> anyhow::Result<T> {
        let writer = self
            .writer
            .as_mut()
            .context("MCAP writer already finished")?;
        f(writer).map_err(|e| write_error(&self.path, e))
    }

    /// Topics the input will bring (e.g. from its summary section): our own channels
    /// keep clear of them even before their channel records are copied.
    pub fn reserve_input_topics<'t>(&mut self, topics: impl IntoIterator<Item = &'t str>) {
        self.input_topics
            .extend(topics.into_iter().map(str::to_string));
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
                self.write(|w| w.add_schema_with_id(id, &header.name, &header.encoding, data))?;
                self.schema_ids.insert(header.id, id);
                self.copied.schemas += 1;
            }
            Record::Channel(c) => {
                if self.channel_ids.contains_key(&c.id) {
                    return Ok(true);
                }
                let schema_id = match c.schema_id {
                    0 => 0,
                    s => match self.schema_ids.get(&s) {
                        Some(&id) => id,
                        None => {
                            self.notes.push(format!(
                                "channel {} names schema {s}, which the input does not hold; its messages were copied on a channel without schema",
                                c.topic
                            ));
                            0
                        }
                    },
                };
                let id = Self::claim(&mut self.used_channel_ids, c.id)?;
                self.input_topics.insert(c.topic.clone());
                self.write(|w| {
                    w.add_channel_with_id(id, schema_id, &c.topic, &c.message_encoding, &c.metadata)
                })?;
                self.channel_ids.insert(c.id, id);
                self.copied.channels += 1;
            }
            Record::Message { header, data } => {
                let Some(&channel_id) = self.channel_ids.get(&header.channel_id) else {
                    self.copied.orphan_messages += 1;
                    return Ok(false);
                };
                let header = MessageHeader {
                    channel_id,
                    ..*header
                };
                self.write(|w| w.write_to_known_channel(&header, data))?;
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
                self.write(|w| w.attach(&attachment))?;
                self.copied.attachments += 1;
            }
            Record::Metadata(m) => {
                self.write(|w| w.write_metadata(m))?;
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
    /// Own ids count down from the top so they rarely meet input ids. A topic an input
    /// channel already has gets a `~N` suffix (said in [`notes`](Self::notes)), so no
    /// output holds two channels of one name with different schemas.
    pub fn own_channel(&mut self, topic: &str, family: Family, kind: Kind) -> anyhow::Result<u16> {
        if let Some(&id) = self.own_channels.get(&(topic.to_string(), family)) {
            return Ok(id);
        }
        let name = self.free_topic(topic);
        let schema_id = match self.own_schemas.get(&(family, kind)) {
            Some(&id) => id,
            None => {
                let s = encoders::schema(family, kind);
                let id = (1..=u16::MAX)
                    .rev()
                    .find(|i| !self.used_schema_ids.contains(i))
                    .context("no schema id left")?;
                self.used_schema_ids.insert(id);
                self.write(|w| w.add_schema_with_id(id, &s.name, &s.encoding, &s.data))?;
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
        self.write(|w| w.add_channel_with_id(id, schema_id, &name, encoding, &BTreeMap::new()))?;
        self.own_channels.insert((topic.to_string(), family), id);
        Ok(id)
    }

    /// Whether a channel of this output's own has `topic`.
    fn owns_topic(&self, topic: &str) -> bool {
        self.own_channels.keys().any(|(t, _)| t == topic)
    }

    /// `topic`, or `topic~2`, `topic~3`, ... when an input channel already has that name.
    fn free_topic(&mut self, topic: &str) -> String {
        if !self.input_topics.contains(topic) {
            return topic.to_string();
        }
        let name = (2..)
            .map(|k| format!("{topic}~{k}"))
            .find(|n| !self.input_topics.contains(n) && !self.owns_topic(n))
            .unwrap_or_default();
        self.notes.push(format!(
            "the input already has a channel {topic}; this output's is named {name}"
        ));
        name
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
        self.write(|w| w.write_to_known_channel(&header, data))
    }

    /// Writes a metadata record of our own.
    pub fn write_metadata(
        &mut self,
        name: &str,
        entries: BTreeMap<String, String>,
    ) -> anyhow::Result<()> {
        let metadata = mcap::records::Metadata {
            name: name.into(),
            metadata: entries,
        };
        self.write(|w| w.write_metadata(&metadata))
    }

    /// Completes the file (summary, footer), syncs it and renames it into place. On
    /// any error the temporary file is removed and the target left as it was.
    pub fn finish(mut self) -> anyhow::Result<()> {
        self.write(|w| w.finish())?;
        let writer = self.writer.take().context("MCAP writer already finished")?;
        let result = writer
            .into_inner()
            .into_inner()
            .map_err(|e| e.into_error())
            .and_then(|file| file.sync_all())
            .map_err(|e| anyhow::anyhow!("cannot write {}: {e}", self.path.display()))
            .and_then(|()| {
                std::fs::rename(&self.tmp_path, &self.path).with_context(|| {
                    format!(
                        "cannot move {} to {}",
                        self.tmp_path.display(),
                        self.path.display()
                    )
                })
            });
        if result.is_err() {
            let _ = std::fs::remove_file(&self.tmp_path);
        }
        super::cleanup::release(&self.tmp_path);
        result
    }

    /// Abandons the output: the temporary file is removed and the target left as it was.
    pub fn discard(self) {}

    /// Abandons the output and removes what stood at its path before (which this run
    /// was allowed to replace), so no earlier file passes for this run's output.
    pub fn discard_and_clear_target(self) -> anyhow::Result<()> {
        let path = self.path.clone();
        drop(self);
        match std::fs::remove_file(&path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                Err(anyhow::anyhow!("cannot remove {}: {e}", path.display()))
            }
            _ => Ok(()),
        }
    }
}

impl Drop for McapOutput {
    fn drop(&mut self) {
        // Not finished: drop the partial temporary file, never the target.
        if self.writer.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp_path);
            super::cleanup::release(&self.tmp_path);
        }
    }
}
