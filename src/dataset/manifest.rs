//! The manifest of a converted dataset: one JSON line per input file saying what was
//! read (relative path, size, content hash), what was written (path, hash), how it went
//! and with which tool version and arguments. Lines are appended one at a time and
//! synced, so a killed run leaves at most one torn last line, which the next run drops.
//! A rerun skips an input whose latest line still matches.

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};

/// The manifest's file name in the output folder.
pub const MANIFEST_NAME: &str = "rangegan-manifest.jsonl";

/// The manifest a shard writes (shards' manifests concatenate into the whole).
pub fn manifest_name(shard: Option<super::Shard>) -> String {
    match shard {
        None => MANIFEST_NAME.to_string(),
        Some(s) => format!("rangegan-manifest.shard-{}-of-{}.jsonl", s.index, s.count),
    }
}

/// Whether `name` is a manifest file (the whole or a shard's).
pub fn is_manifest_name(name: &str) -> bool {
    name.starts_with("rangegan-manifest") && name.ends_with(".jsonl")
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Converted; the output is complete.
    Ok,
    /// Not converted (see `error`); no output was written.
    Failed,
    /// Up to date from an earlier run (reported in summaries; not appended).
    Skipped,
}

/// One input file's line.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Entry {
    /// Input path relative to its dataset folder (`/` separators).
    pub input: String,
    pub input_size: u64,
    /// `blake3:<hex>` of the input's bytes.
    pub input_hash: String,
    /// Output path relative to the output folder.
    pub output: String,
    #[serde(default)]
    pub output_size: Option<u64>,
    #[serde(default)]
    pub output_hash: Option<String>,
    pub status: Status,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Input records copied (schemas, channels, messages, attachments, metadata).
    pub records_copied: u64,
    pub scans: u64,
    pub malformed: u64,
    pub warnings: u64,
    pub seconds: f64,
    pub tool: String,
    pub version: String,
    /// The conversion's settings (every flag that changes the output bytes).
    pub args: String,
}

/// `blake3:<hex>` of a file's bytes.
pub fn hash_file(path: &Path) -> anyhow::Result<String> {
    let mut file = File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    let mut hasher = blake3::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = file
            .read(&mut buf)
            .with_context(|| format!("cannot read {}", path.display()))?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(format!("blake3:{}", hasher.finalize().to_hex()))
}

/// A short digest of what a flag's path names, so a rerun sees the file change under the same
/// name: `blake3:<16 hex>` of a file, or of a folder's files (names and bytes, in name order,
/// not recursive); `None` where the path names nothing (a built-in sensor's name).
pub fn path_digest(path: &Path) -> Option<String> {
    let mut hasher = blake3::Hasher::new();
    if path.is_file() {
        hasher.update(hash_file(path).ok()?.as_bytes());
    } else if path.is_dir() {
        let mut files: Vec<PathBuf> = std::fs::read_dir(path)
            .ok()?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        for f in files {
            hasher.update(f.file_name()?.as_encoded_bytes());
            hasher.update(hash_file(&f).ok()?.as_bytes());
        }
    } else {
        return None;
    }
    Some(format!("blake3:{}", &hasher.finalize().to_hex()[..16]))
}

/// What a conversion of one file counted, as its manifest line records it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Counts {
    /// Input records copied (schemas, channels, messages, attachments, metadata).
    pub records_copied: u64,
    pub scans: u64,
    pub malformed: u64,
    pub warnings: u64,
    pub seconds: f64,
}

/// What was read and how it went (`result`: the conversion's counts, or its error); the
/// output fields are filled by [`finish_entry`].
pub fn manifest_entry(
    rel_input: &str,
    size: u64,
    input_hash: String,
    rel_output: &str,
    settings: &str,
    result: Result<Counts, String>,
) -> Entry {
    let (status, error, counts) = match result {
        Ok(c) => (Status::Ok, None, c),
        Err(e) => (Status::Failed, Some(e), Counts::default()),
    };
    Entry {
        input: rel_input.into(),
        input_size: size,
        input_hash,
        output: rel_output.into(),
        output_size: None,
        output_hash: None,
        status,
        error,
        records_copied: counts.records_copied,
        scans: counts.scans,
        malformed: counts.malformed,
        warnings: counts.warnings,
        seconds: counts.seconds,
        tool: "rangegan-mcap".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        args: settings.into(),
    }
}

/// Adds the output's size and hash to an entry of a converted file.
pub fn finish_entry(entry: &mut Entry, output: &Path) -> anyhow::Result<()> {
    // A --strict run that skipped data keeps no output.
    if entry.status == Status::Ok && output.exists() {
        entry.output_size = Some(std::fs::metadata(output)?.len());
        entry.output_hash = Some(hash_file(output)?);
    }
    Ok(())
}

/// The latest line per input of every manifest in `dir` (the whole and the shards'), so a
/// run resumes whatever split the earlier runs used. Unreadable lines (a torn last line)
/// are ignored.
pub fn load_latest(dir: &Path) -> anyhow::Result<HashMap<String, Entry>> {
    let mut latest = HashMap::new();
    let Ok(listing) = std::fs::read_dir(dir) else {
        return Ok(latest); // no output folder yet
    };
    let mut names: Vec<PathBuf> = listing
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| is_manifest_name(&n.to_string_lossy()))
        })
        .collect();
    names.sort();
    for path in names {
        refuse_unsafe_manifest(&path)?;
        let bytes =
            std::fs::read(&path).with_context(|| format!("cannot read {}", path.display()))?;
        // A damaged line (torn, or not UTF-8) says nothing about any file: its file is
        // converted again, and the lines around it still count.
        for line in bytes.split(|&b| b == b'\n') {
            if let Ok(e) = serde_json::from_slice::<Entry>(line) {
                latest.insert(e.input.clone(), e);
            }
        }
    }
    Ok(latest)
}

/// Refuses a manifest path that is not a plain file of its own: a symlink or a hard link
/// (appending would write into whatever file it shares, an input recording, say) or a
/// FIFO or device (reading it would hang). A path that does not exist yet is fine.
pub fn refuse_unsafe_manifest(path: &Path) -> anyhow::Result<()> {
    let Ok(meta) = std::fs::symlink_metadata(path) else {
        return Ok(());
    };
    let what = if meta.file_type().is_symlink() {
        Some("a symlink")
    } else if !meta.is_file() {
        Some("not a regular file")
    } else if links(&meta) > 1 {
        Some("a hard link shared with another file")
    } else {
        None
    };
    match what {
        Some(what) => anyhow::bail!(
            "{} is {what}; a manifest is never written through a link or into a special file (remove it, or write to another folder)",
            path.display()
        ),
        None => Ok(()),
    }
}

#[cfg(unix)]
fn links(meta: &std::fs::Metadata) -> u64 {
    std::os::unix::fs::MetadataExt::nlink(meta)
}

#[cfg(not(unix))]
fn links(_: &std::fs::Metadata) -> u64 {
    1
}

/// Why an earlier line does not let a rerun skip its input, or `None` when it does.
pub fn stale_reason(
    earlier: &Entry,
    input_hash: &str,
    args: &str,
    output: &Path,
) -> anyhow::Result<Option<&'static str>> {
    Ok(Some(if earlier.status != Status::Ok {
        "failed before"
    } else if earlier.input_hash != input_hash {
        "input changed"
    } else if earlier.args != args || earlier.version != env!("CARGO_PKG_VERSION") {
        "other settings or tool version"
    } else if !output.is_file() {
        "output missing"
    } else if std::fs::metadata(output)?.len() != earlier.output_size.unwrap_or(u64::MAX)
        || earlier.output_hash.as_deref() != Some(hash_file(output)?.as_str())
    {
        "output changed"
    } else {
        return Ok(None);
    }))
}

/// A manifest open for appending.
pub struct ManifestWriter {
    file: File,
    path: PathBuf,
}

impl ManifestWriter {
    /// Opens (or creates) `path` for appending; a torn last line left by a killed run is cut
    /// off first, so the next line starts on a line of its own.
    pub fn open(path: &Path) -> anyhow::Result<Self> {
        refuse_unsafe_manifest(path)?;
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(path)
            .with_context(|| format!("cannot open {}", path.display()))?;
        let mut text = Vec::new();
        file.read_to_end(&mut text)?;
        if !text.is_empty() && !text.ends_with(b"\n") {
            let keep = text.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
            file.set_len(keep as u64)?;
        }
        drop(file);
        // Appending (O_APPEND), not writing at a position found once: two runs into one
        // folder then each put their whole lines at the end, never over each other's.
        let file = OpenOptions::new()
            .append(true)
            .open(path)
            .with_context(|| format!("cannot open {}", path.display()))?;
        Ok(ManifestWriter {
            file,
            path: path.to_path_buf(),
        })
    }

    /// Appends one line (in one write) and syncs it to disk.
    pub fn append(&mut self, entry: &Entry) -> anyhow::Result<()> {
        let mut line = serde_json::to_vec(entry)?;
        line.push(b'\n');
        self.file
            .write_all(&line)
            .and_then(|_| self.file.sync_data())
            .with_context(|| format!("cannot append to {}", self.path.display()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(input: &str, status: Status) -> Entry {
        Entry {
            input: input.into(),
            input_size: 1,
            input_hash: "blake3:aa".into(),
            output: input.into(),
            output_size: Some(3),
            output_hash: None,
            status,
            error: None,
            records_copied: 0,
            scans: 0,
            malformed: 0,
            warnings: 0,
            seconds: 0.0,
            tool: "rangegan-mcap".into(),
            version: env!("CARGO_PKG_VERSION").into(),
            args: "--quality off".into(),
        }
    }

    #[test]
    fn a_torn_last_line_is_dropped_and_the_latest_line_wins() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(MANIFEST_NAME);
        let mut w = ManifestWriter::open(&path).unwrap();
        w.append(&entry("a.mcap", Status::Failed)).unwrap();
        w.append(&entry("a.mcap", Status::Ok)).unwrap();
        drop(w);
        // A run killed in the middle of a line.
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(b"{\"input\":\"b.mc").unwrap();
        drop(f);
        let mut w = ManifestWriter::open(&path).unwrap();
        w.append(&entry("c.mcap", Status::Ok)).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(text.lines().count(), 3);
        assert!(
            text.lines()
                .all(|l| serde_json::from_str::<Entry>(l).is_ok())
        );
        let latest = load_latest(dir.path()).unwrap();
        assert_eq!(latest.len(), 2);
        assert_eq!(latest["a.mcap"].status, Status::Ok);
        // A line that is not UTF-8 is passed over; the lines after it still count.
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(b"{\"input\":\"\xff\xfe\"}\n").unwrap();
        drop(f);
        let mut w = ManifestWriter::open(&path).unwrap();
        w.append(&entry("d.mcap", Status::Ok)).unwrap();
        let latest = load_latest(dir.path()).unwrap();
        assert_eq!(latest.len(), 3);
        assert!(latest.contains_key("d.mcap"));
    }

    #[test]
    fn an_entry_records_the_counts_or_the_error_and_then_the_output() {
        let counts = Counts {
            records_copied: 7,
            scans: 3,
            malformed: 1,
            warnings: 2,
            seconds: 0.5,
        };
        let ok = manifest_entry(
            "a.mcap",
            10,
            "blake3:aa".into(),
            "a.mcap",
            "--quality off",
            Ok(counts),
        );
        assert_eq!((ok.status, ok.error.as_deref()), (Status::Ok, None));
        assert_eq!(
            (ok.records_copied, ok.scans, ok.malformed, ok.warnings),
            (7, 3, 1, 2)
        );
        assert_eq!((ok.seconds, ok.args.as_str()), (0.5, "--quality off"));
        let failed = manifest_entry(
            "a.mcap",
            10,
            String::new(),
            "a.mcap",
            "",
            Err("boom".into()),
        );
        assert_eq!(
            (failed.status, failed.error.as_deref()),
            (Status::Failed, Some("boom"))
        );
        assert_eq!(
            (failed.records_copied, failed.scans, failed.seconds),
            (0, 0, 0.0)
        );

        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("a.mcap");
        let mut e = ok.clone();
        finish_entry(&mut e, &out).unwrap();
        assert_eq!(
            (e.output_size, e.output_hash.as_deref()),
            (None, None),
            "no output"
        );
        std::fs::write(&out, b"abc").unwrap();
        finish_entry(&mut e, &out).unwrap();
        assert_eq!(e.output_size, Some(3));
        assert_eq!(e.output_hash, Some(hash_file(&out).unwrap()));
        let mut f = failed.clone();
        finish_entry(&mut f, &out).unwrap();
        assert_eq!(f.output_size, None, "a failed file keeps no output");
    }

    #[test]
    fn only_a_matching_line_with_its_output_skips() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("a.mcap");
        let mut e = entry("a.mcap", Status::Ok);
        let reason = |e: &Entry, hash: &str, args: &str| stale_reason(e, hash, args, &out).unwrap();
        assert_eq!(
            reason(&e, "blake3:aa", "--quality off"),
            Some("output missing")
        );
        std::fs::write(&out, b"abc").unwrap();
        assert_eq!(
            reason(&e, "blake3:aa", "--quality off"),
            Some("output changed")
        );
        e.output_hash = Some(hash_file(&out).unwrap());
        assert_eq!(reason(&e, "blake3:aa", "--quality off"), None);
        assert_eq!(
            reason(&e, "blake3:bb", "--quality off"),
            Some("input changed")
        );
        assert_eq!(
            reason(&e, "blake3:aa", "--quality fast"),
            Some("other settings or tool version")
        );
        e.status = Status::Failed;
        assert_eq!(
            reason(&e, "blake3:aa", "--quality off"),
            Some("failed before")
        );
    }

    /// Two runs appending to one manifest at once (each opened before the other wrote):
    /// every line is whole, none is blank, and none is lost.
    #[test]
    fn two_writers_on_one_manifest_never_write_over_each_other() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(MANIFEST_NAME);
        let mut a = ManifestWriter::open(&path).unwrap();
        let mut b = ManifestWriter::open(&path).unwrap();
        for k in 0..20 {
            a.append(&entry(&format!("a{k}.mcap"), Status::Ok)).unwrap();
            b.append(&entry(&format!("b{k}.mcap"), Status::Ok)).unwrap();
        }
        let text = std::fs::read_to_string(&path).unwrap();
        assert_eq!(text.lines().count(), 40);
        assert!(
            text.lines()
                .all(|l| serde_json::from_str::<Entry>(l).is_ok())
        );
        assert_eq!(load_latest(dir.path()).unwrap().len(), 40);
    }

    /// A manifest that is a symlink, a hard link or a FIFO is refused before it is read or
    /// written, and the file it shares is left as it was.
    #[cfg(unix)]
    #[test]
    fn a_manifest_through_a_link_or_a_fifo_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("input.mcap");
        std::fs::write(&input, b"recording bytes without a newline").unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        let path = out.join(MANIFEST_NAME);
        std::os::unix::fs::symlink(&input, &path).unwrap();
        let err = ManifestWriter::open(&path).err().unwrap().to_string();
        assert!(err.contains("a symlink"), "{err}");
        assert!(load_latest(&out).is_err());
        std::fs::remove_file(&path).unwrap();
        std::fs::hard_link(&input, &path).unwrap();
        let err = ManifestWriter::open(&path).err().unwrap().to_string();
        assert!(err.contains("hard link"), "{err}");
        std::fs::remove_file(&path).unwrap();
        let made = std::process::Command::new("mkfifo").arg(&path).status();
        if made.is_ok_and(|s| s.success()) {
            let err = load_latest(&out).err().unwrap().to_string();
            assert!(err.contains("not a regular file"), "{err}");
        }
        assert_eq!(
            std::fs::read(&input).unwrap(),
            b"recording bytes without a newline"
        );
    }
}
