//! Datasets of recordings: which `*.mcap` files a set of input paths holds (sorted, each
//! with the relative path its output keeps), which of them a shard takes, and the
//! manifest that lets a rerun skip what is already done.

pub mod manifest;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

/// One recording of a dataset.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatasetFile {
    /// Where it is read from.
    pub path: PathBuf,
    /// Its path relative to the input it was found under, with `/` separators; its output
    /// has the same relative path below the output folder.
    pub rel: String,
    pub size: u64,
    /// Its relative path holds bytes that are not UTF-8, so `rel` is a lossy rendering
    /// that could not name its output (two such names may even render alike): such a file
    /// is refused, by name, rather than written under another name.
    pub lossy_name: bool,
}

/// Every `*.mcap` below `inputs` (files are taken as given, folders searched recursively),
/// sorted by relative path. Folders in `exclude` (the output folder) are not searched, so
/// an output folder inside an input folder never becomes input. Two inputs with the same
/// relative path are an error.
pub fn list(inputs: &[PathBuf], exclude: &[PathBuf]) -> anyhow::Result<Vec<DatasetFile>> {
    let exclude: Vec<PathBuf> = exclude
        .iter()
        .filter_map(|p| p.canonicalize().ok())
        .collect();
    let mut found: BTreeMap<String, DatasetFile> = BTreeMap::new();
    for input in inputs {
        let meta =
            std::fs::metadata(input).with_context(|| format!("cannot read {}", input.display()))?;
        let mut files = Vec::new();
        if meta.is_dir() {
            walk(input, input, &exclude, &mut files)?;
        } else {
            let name = input
                .file_name()
                .with_context(|| format!("{} is not a file path", input.display()))?;
            files.push(DatasetFile {
                path: input.clone(),
                rel: name.to_string_lossy().into_owned(),
                size: meta.len(),
                lossy_name: name.to_str().is_none(),
            });
        }
        for f in files {
            if f.lossy_name {
                // Refused later, by its own path: it takes part in no name collision.
                found.insert(format!("{}\0{}", f.rel, f.path.display()), f);
                continue;
            }
            if let Some(other) = found.get(&f.rel) {
                bail!(
                    "{} and {} would both be written as {}; convert them into different output folders",
                    other.path.display(),
                    f.path.display(),
                    f.rel
                );
            }
            found.insert(f.rel.clone(), f);
        }
    }
    Ok(found.into_values().collect())
}

fn walk(
    root: &Path,
    dir: &Path,
    exclude: &[PathBuf],
    out: &mut Vec<DatasetFile>,
) -> anyhow::Result<()> {
    if let Ok(canonical) = dir.canonicalize()
        && exclude.contains(&canonical)
    {
        return Ok(());
    }
    let entries =
        std::fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))?;
    for entry in entries {
        let entry = entry.with_context(|| format!("cannot list {}", dir.display()))?;
        let path = entry.path();
        // Symlinked folders are not followed (no loops); symlinked files are read.
        let kind = entry.file_type()?;
        let meta = if kind.is_symlink() {
            match std::fs::metadata(&path) {
                Ok(m) if m.is_file() => m,
                _ => continue,
            }
        } else if kind.is_dir() {
            walk(root, &path, exclude, out)?;
            continue;
        } else {
            entry.metadata()?
        };
        let is_mcap = path.extension().is_some_and(|e| e == "mcap");
        let hidden = entry.file_name().to_string_lossy().starts_with('.');
        if meta.is_file() && is_mcap && !hidden {
            let rel = path.strip_prefix(root).unwrap_or(&path);
            let lossy_name = rel.to_str().is_none();
            let rel: Vec<String> = rel
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            out.push(DatasetFile {
                path: path.clone(),
                rel: rel.join("/"),
                size: meta.len(),
                lossy_name,
            });
        }
    }
    Ok(())
}

/// Shard `index` of `count`: a fixed subset of the dataset chosen by a hash of each file's
/// relative path, so every machine agrees on it without talking to the others.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    pub index: u64,
    pub count: u64,
}

impl Shard {
    /// Parses `I/N` (0 <= I < N).
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let parsed = text
            .split_once('/')
            .and_then(|(i, n)| Some((i.trim().parse().ok()?, n.trim().parse().ok()?)));
        match parsed {
            Some((index, count)) if index < count => Ok(Shard { index, count }),
            _ => bail!("--shard {text}: give I/N with 0 <= I < N, e.g. 0/4"),
        }
    }

    /// Whether the file with relative path `rel` belongs to this shard.
    pub fn contains(&self, rel: &str) -> bool {
        let hash = blake3::hash(rel.as_bytes());
        let mut word = [0u8; 8];
        word.copy_from_slice(&hash.as_bytes()[..8]);
        u64::from_le_bytes(word) % self.count == self.index
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shards_partition_the_dataset() {
        let rels: Vec<String> = (0..200)
            .map(|i| format!("day{}/run{i}.mcap", i % 7))
            .collect();
        let shards: Vec<Shard> = (0..4).map(|i| Shard { index: i, count: 4 }).collect();
        let mut sizes = [0usize; 4];
        for rel in &rels {
            let owners: Vec<usize> = (0..4).filter(|&i| shards[i].contains(rel)).collect();
            assert_eq!(owners.len(), 1, "{rel} in {owners:?}");
            sizes[owners[0]] += 1;
        }
        // A hash spreads the files: no shard gets less than half its share.
        assert!(sizes.iter().all(|&n| n > 25), "{sizes:?}");
        assert_eq!(Shard::parse("3/4").unwrap(), shards[3]);
        for bad in ["4/4", "1", "a/b", "-1/3"] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn lists_recordings_sorted_skipping_the_output_folder() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("in");
        for rel in [
            "b/2.mcap",
            "a/1.mcap",
            "a/notes.txt",
            "c.mcap",
            "out/x.mcap",
            "a/.1.mcap.7.tmp",
        ] {
            let p = root.join(rel);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(&p, b"x").unwrap();
        }
        let files = list(std::slice::from_ref(&root), &[root.join("out")]).unwrap();
        let rels: Vec<&str> = files.iter().map(|f| f.rel.as_str()).collect();
        assert_eq!(rels, ["a/1.mcap", "b/2.mcap", "c.mcap"]);
        // A file given twice (as itself and inside its folder) is refused.
        let twice = list(&[root.join("c.mcap"), root.clone()], &[]);
        assert!(twice.unwrap_err().to_string().contains("c.mcap"));
    }
}
