//! Helpers shared by the hostile-input tests (`tests/hostile.rs`, `tests/hostile_outputs.rs`):
//! the binary under an address-space limit, `convert` with the usual flags, a temporary
//! input and output, and readers of the JSON report and of an output's channels.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::common::stderr;

/// Address space allowed to a command under test (KiB): far below what the damaged
/// lengths and ring counts used to allocate (1e12 bytes, 21.8 GB).
pub const ADDRESS_SPACE_KIB: u64 = 3 << 20;

/// Runs the binary with `args` under an address-space limit, so an allocation sized by
/// a damaged length fails the test instead of the machine.
pub fn run_limited(args: &[&str]) -> Output {
    let mut cmd = std::process::Command::new("sh");
    cmd.arg("-c")
        .arg(format!("ulimit -v {ADDRESS_SPACE_KIB}; exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_rangegan-mcap"))
        .args(args);
    cmd.output().expect("binary runs")
}

/// `convert --quality off` (range images only) with extra flags.
pub fn convert(input: &Path, output: &Path, flags: &[&str]) -> Output {
    let mut args = vec![
        "convert",
        input.to_str().unwrap(),
        output.to_str().unwrap(),
        "--quality",
        "off",
        "--quiet",
        "--force",
    ];
    args.extend_from_slice(flags);
    run_limited(&args)
}

/// A temporary folder with the paths of an input and an output in it.
pub fn in_out() -> (tempfile::TempDir, PathBuf, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    (dir, input, output)
}

/// `o` exited with `code` and its stderr says `needle`.
pub fn expect_exit(o: &Output, code: i32, needle: &str) {
    assert_eq!(o.status.code(), Some(code), "{}", stderr(o));
    assert!(stderr(o).contains(needle), "{}", stderr(o));
}

pub fn json(o: &Output) -> serde_json::Value {
    serde_json::from_slice(&o.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}\n{}", String::from_utf8_lossy(&o.stdout), stderr(o)))
}

pub fn no_temporary_files(dir: &Path) {
    let left: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".tmp"))
        .collect();
    assert!(left.is_empty(), "temporary files left behind: {left:?}");
}

pub fn copied_messages(report: &serde_json::Value) -> u64 {
    report["report"]["copied"]["messages"].as_u64().unwrap()
}

/// Topics of a file's channels, as the `mcap` crate's reader lists them.
pub fn output_topics(path: &Path) -> Vec<String> {
    let bytes = std::fs::read(path).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
    let mut topics: Vec<String> = summary.channels.values().map(|c| c.topic.clone()).collect();
    topics.sort();
    topics
}
