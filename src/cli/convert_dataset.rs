//! `rangegan-mcap convert IN... OUT` over a dataset: every `*.mcap` below the inputs is
//! converted to the same relative path below OUT, several files at a time, each output
//! atomic; the manifest records every file so a rerun converts only what changed, and a
//! shard takes a fixed subset so machines can split a dataset without talking.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use anyhow::{Context, bail};
use rayon::prelude::*;

use super::convert::{self, ConvertArgs, Counters, FileConverter};
use super::{GlobalArgs, Outcome};
use crate::dataset::manifest::{self, Entry, ManifestWriter, Status};
use crate::dataset::{self, DatasetFile, Shard};

/// Dataset mode: several inputs, a folder, or an output folder that exists.
pub fn is_dataset(args: &ConvertArgs) -> bool {
    args.inputs.len() > 1 || args.inputs[0].is_dir() || args.output.is_dir()
}

/// What a run does with one file.
struct Planned {
    file: DatasetFile,
    input_hash: Result<String, String>,
    todo: Todo,
}

/// The plan for one file.
enum Todo {
    /// No output yet (or `--force`): convert.
    New,
    /// The output is stale, for this reason: convert again.
    Stale(&'static str),
    /// The output is up to date: its manifest line.
    UpToDate(Box<Entry>),
    /// The output exists and is not ours: refused, with the reason.
    Refused(String),
}

/// Hashes every file and compares it with its latest manifest line. An existing output
/// that the manifest does not show as written by this tool is refused: `--force` overwrites
/// it only when it does not lie in one of `input_dirs`, whose files are inputs and are never
/// overwritten (nor is an output there that changed since this tool wrote it).
fn plan(
    files: Vec<DatasetFile>,
    out: &Path,
    input_dirs: &[PathBuf],
    settings: &str,
    force: bool,
) -> anyhow::Result<Vec<Planned>> {
    let earlier = manifest::load_latest(out)?;
    let in_input = input_dirs
        .iter()
        .find(|dir| crate::io::writer::lies_in(out, dir));
    let in_input_folder = |output: &Path, dir: &Path| {
        Todo::Refused(format!(
            "{} lies in the input folder {} and is not an unchanged output of this tool: it is an input, never overwritten; write to a folder outside the inputs",
            output.display(),
            dir.display()
        ))
    };
    Ok(files
        .into_par_iter()
        .map(|file| {
            let input_hash = manifest::hash_file(&file.path).map_err(|e| format!("{e:#}"));
            let output = out.join(&file.rel);
            let ours = earlier.get(&file.rel).filter(|e| e.status == Status::Ok);
            let todo = match (output.exists(), ours, &input_hash) {
                _ if file.lossy_name => Todo::Refused(format!(
                    "{:?}: the file's name is not UTF-8, so its output could not keep its relative path; rename it",
                    file.path
                )),
                (true, None, _) => match in_input {
                    Some(dir) => in_input_folder(&output, dir),
                    None if force => Todo::New,
                    None => Todo::Refused(format!(
                        "{} exists and is not in the manifest; pass --force to overwrite it",
                        output.display()
                    )),
                },
                (exists, Some(e), Ok(hash)) => {
                    let why = manifest::stale_reason(e, hash, settings, &output)
                        .unwrap_or(Some("output unreadable"));
                    match (why, in_input) {
                        (Some("output changed" | "output unreadable"), Some(dir)) if exists => {
                            in_input_folder(&output, dir)
                        }
                        _ if force => Todo::New,
                        (None, _) => Todo::UpToDate(Box::new(e.clone())),
                        (Some(why), _) => Todo::Stale(why),
                    }
                }
                _ => Todo::New,
            };
            Planned {
                file,
                input_hash,
                todo,
            }
        })
        .collect())
}

/// The totals of a run.
#[derive(Debug, Default, serde::Serialize)]
struct Totals {
    files: usize,
    ok: usize,
    failed: usize,
    skipped: usize,
    bytes_read: u64,
    scans: u64,
    seconds: f64,
    files_per_s: f64,
    scans_per_s: f64,
}

pub fn run(global: &GlobalArgs, args: &ConvertArgs) -> anyhow::Result<Outcome> {
    let out = &args.output;
    if out.is_file() {
        bail!(
            "{}: converting several files or a folder needs an output folder",
            out.display()
        );
    }
    for input in &args.inputs {
        let same = input.canonicalize().ok() == out.canonicalize().ok() && out.exists();
        if same {
            bail!(
                "{}: output folder is an input; write to another folder (inputs are never modified)",
                out.display()
            );
        }
    }
    let shard = args
        .dataset
        .shard
        .as_deref()
        .map(Shard::parse)
        .transpose()?;
    let mut files = dataset::list(&args.inputs, std::slice::from_ref(out))?;
    if let Some(s) = shard {
        files.retain(|f| s.contains(&f.rel));
    }
    let settings = convert::output_settings(args);
    let started = std::time::Instant::now();
    let input_dirs: Vec<PathBuf> = args.inputs.iter().filter(|i| i.is_dir()).cloned().collect();
    let planned = plan(files, out, &input_dirs, &settings, args.force)?;
    if args.dataset.dry_run {
        return dry_run(global, &planned);
    }
    create_output_folder(out)?;
    let todo: Vec<&Planned> = planned
        .iter()
        .filter(|p| !matches!(p.todo, Todo::UpToDate(_)))
        .collect();
    let mut entries: Vec<Entry> = planned
        .iter()
        .filter_map(|p| match &p.todo {
            Todo::UpToDate(e) => Some(Entry {
                status: Status::Skipped,
                ..(**e).clone()
            }),
            _ => None,
        })
        .collect();
    if !global.quiet && !entries.is_empty() {
        eprintln!(
            "{} of {} files up to date (--force converts them again)",
            entries.len(),
            planned.len()
        );
    }
    let mut data_skipped = false;
    if !todo.is_empty() {
        let manifest_path = out.join(manifest::manifest_name(shard));
        let writer = Mutex::new(ManifestWriter::open(&manifest_path)?);
        let decoding = super::decoding::resolve(&args.decode, &args.channels)?;
        super::decoding::warn_uncalibrated(global, decoding.as_ref());
        let counters = Counters::default();
        let converter = FileConverter::new(args, decoding.as_ref(), &counters)?;
        let bytes = todo.iter().map(|p| p.file.size).sum();
        let bar = super::progress_bar(global, bytes);
        let done = convert::with_progress(&bar, &counters, Some(todo.len()), || {
            convert_all(global, args, &todo, &converter, &counters, &writer)
        })?;
        data_skipped = done.data_skipped;
        let done = done.entries;
        entries.extend(done);
    }
    let failed = entries
        .iter()
        .filter(|e| e.status == Status::Failed)
        .count();
    let totals = totals(&entries, started.elapsed().as_secs_f64());
    if global.json {
        let summary = serde_json::json!({ "output": out.display().to_string(), "files": entries, "total": totals });
        println!("{}", serde_json::to_string_pretty(&summary)?);
    }
    if !global.quiet {
        eprintln!(
            "{} files: {} converted, {} up to date, {} failed; {} scans in {:.1} s ({:.2} files/s, {:.1} scans/s)",
            totals.files,
            totals.ok,
            totals.skipped,
            totals.failed,
            totals.scans,
            totals.seconds,
            totals.files_per_s,
            totals.scans_per_s,
        );
    }
    Ok(if failed > 0 {
        Outcome::FilesFailed
    } else if data_skipped && args.strict {
        Outcome::DataSkipped
    } else {
        Outcome::Success
    })
}

fn totals(entries: &[Entry], seconds: f64) -> Totals {
    let count = |s: Status| entries.iter().filter(|e| e.status == s).count();
    let converted = entries.iter().filter(|e| e.status == Status::Ok);
    let scans = converted.clone().map(|e| e.scans).sum();
    Totals {
        files: entries.len(),
        ok: count(Status::Ok),
        failed: count(Status::Failed),
        skipped: count(Status::Skipped),
        bytes_read: converted.map(|e| e.input_size).sum(),
        scans,
        seconds,
        files_per_s: count(Status::Ok) as f64 / seconds.max(1e-9),
        scans_per_s: scans as f64 / seconds.max(1e-9),
    }
}

/// `--dry-run`: each file with what a run would do.
fn dry_run(global: &GlobalArgs, planned: &[Planned]) -> anyhow::Result<Outcome> {
    let rows: Vec<serde_json::Value> = planned
        .iter()
        .map(|p| {
            let (action, reason) = match &p.todo {
                Todo::UpToDate(_) => ("skip", "up to date"),
                Todo::Refused(why) => ("refuse", why.as_str()),
                Todo::Stale(why) => ("convert", *why),
                Todo::New => ("convert", "new"),
            };
            serde_json::json!({
                "input": p.file.rel, "path": p.file.path.display().to_string(), "size": p.file.size,
                "action": action, "reason": reason,
            })
        })
        .collect();
    if global.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({ "files": rows }))?
        );
    } else {
        for r in &rows {
            println!(
                "{}\t{}\t{}",
                r["action"].as_str().unwrap_or(""),
                r["input"].as_str().unwrap_or(""),
                r["reason"].as_str().unwrap_or("")
            );
        }
    }
    Ok(Outcome::Success)
}

/// The files a run converted (or failed), and whether any had data skipped (what
/// `--strict` turns into exit code 3).
struct Converted {
    entries: Vec<Entry>,
    data_skipped: bool,
}

/// Converts `todo` on `--jobs` workers, each with its share of the threads; appends each
/// file's manifest line as soon as it is done.
fn convert_all(
    global: &GlobalArgs,
    args: &ConvertArgs,
    todo: &[&Planned],
    converter: &FileConverter<'_>,
    counters: &Counters,
    writer: &Mutex<ManifestWriter>,
) -> anyhow::Result<Converted> {
    let data_skipped = AtomicBool::new(false);
    let threads = global
        .threads
        .or_else(|| std::thread::available_parallelism().ok().map(|n| n.get()))
        .unwrap_or(1);
    let jobs = args.dataset.jobs.clamp(1, todo.len().max(1));
    let per_job = (threads / jobs).max(1);
    let next = AtomicUsize::new(0);
    let entries = Mutex::new(Vec::new());
    std::thread::scope(|scope| -> anyhow::Result<()> {
        let workers: Vec<_> = (0..jobs)
            .map(|_| {
                scope.spawn(|| -> anyhow::Result<()> {
                    let pool = rayon::ThreadPoolBuilder::new()
                        .num_threads(per_job)
                        .build()?;
                    loop {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(p) = todo.get(i) else {
                            return Ok(());
                        };
                        let entry = pool.install(|| {
                            convert_one(global, args, p, converter, counters, &data_skipped)
                        });
                        let line = writer
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .append(&entry);
                        entries
                            .lock()
                            .unwrap_or_else(|e| e.into_inner())
                            .push(entry);
                        line?;
                    }
                })
            })
            .collect();
        for w in workers {
            w.join()
                .map_err(|_| anyhow::anyhow!("a conversion worker panicked"))??;
        }
        Ok(())
    })?;
    let mut entries = entries.into_inner().unwrap_or_else(|e| e.into_inner());
    entries.sort_by(|a, b| a.input.cmp(&b.input));
    Ok(Converted {
        entries,
        data_skipped: data_skipped.into_inner(),
    })
}

/// Creates an output folder (and those above it), with errors that name it; a symlink that
/// points nowhere is named as such.
fn create_output_folder(dir: &Path) -> anyhow::Result<()> {
    if let Ok(target) = std::fs::read_link(dir)
        && !dir.exists()
    {
        anyhow::bail!(
            "{} is a symlink to {}, which does not exist; remove the link or create its target",
            dir.display(),
            target.display()
        );
    }
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create the output folder {}", dir.display()))
}

/// Converts one file of the dataset; its failure becomes its manifest line.
fn convert_one(
    global: &GlobalArgs,
    args: &ConvertArgs,
    p: &Planned,
    converter: &FileConverter<'_>,
    counters: &Counters,
    data_skipped: &AtomicBool,
) -> Entry {
    let output: PathBuf = args.output.join(&p.file.rel);
    let result = match (&p.input_hash, &p.todo) {
        (Err(e), _) => Err(anyhow::anyhow!("{e}")), // names the file
        (_, Todo::Refused(why)) => Err(anyhow::anyhow!("{why}")),
        _ => output
            .parent()
            .map_or(Ok(()), create_output_folder)
            // An output that is its input through a link is refused, as in one-file form.
            .and_then(|_| crate::io::writer::refuse_overwriting_inputs(&output, &[&p.file.path]))
            .and_then(|_| converter.convert(&p.file.path, &p.file.rel, &output, true, counters)),
    };
    match &result {
        Ok(c) => {
            if convert::data_skipped(&c.report) {
                data_skipped.store(true, Ordering::Relaxed);
            }
            convert::print_file_summary(global, &p.file.path, &output, c)
        }
        Err(e) => eprintln!("error: {e:#}"), // errors name the file
    }
    let hash = p.input_hash.clone().unwrap_or_default();
    let mut entry = manifest::manifest_entry(
        &p.file.rel,
        p.file.size,
        hash,
        &p.file.rel,
        &converter.settings,
        result
            .as_ref()
            .map(convert::manifest_counts)
            .map_err(|e| format!("{e:#}")),
    );
    if let Err(e) = manifest::finish_entry(&mut entry, &output) {
        entry.status = Status::Failed;
        entry.error = Some(format!("{e:#}"));
    }
    entry
}
