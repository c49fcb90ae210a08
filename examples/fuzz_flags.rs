//! A campaign over the command line: every value-taking flag of every subcommand (read
//! from the binary's own `--help`, so new flags are covered without a list to keep) is
//! given absurd values (0, -1, NaN, inf, 1e308, 100000, 2^32 + 1, 2^64), one at a time,
//! on small valid inputs, under a 3 GiB address space and a time limit. A panic (exit
//! 101), an abort or a crash is a bug; an exit of 0-4 is an answer; a run past the limit
//! is listed as slow (a value that asks for much work, not always a bug).
//!
//!     cargo build --release && cargo run --release --example fuzz_flags -- [--seconds 20] [--only CMD]
//!
//! Prints one line per finding and a summary; exits 1 if anything crashed.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rangegan_mcap::io::decoders::{DecodedCloud, Family};
use rangegan_mcap::io::encoders;
use rangegan_mcap::lidar::{Scan, SensorProfile};

const VALUES: [&str; 8] = [
    "0",
    "-1",
    "NaN",
    "inf",
    "1e308",
    "100000",
    "4294967297",
    "18446744073709551616",
];

/// Flags that take a value but are not worth fuzzing here: they name files or choose
/// among fixed words (clap refuses anything else before the command runs).
const SKIPPED: [&str; 4] = ["--help", "--version", "--report", "--out"];

fn binary() -> PathBuf {
    let exe = std::env::current_exe().expect("own path");
    // target/release/examples/fuzz_flags -> target/release/rangegan-mcap
    exe.parent()
        .and_then(Path::parent)
        .map(|d| d.join("rangegan-mcap"))
        .filter(|p| p.exists())
        .expect("build the binary first: cargo build --release")
}

/// A 16-beam wall at 8 m, 360 columns, ring field included.
fn wall() -> Scan {
    let grid = SensorProfile::builtin("vlp16")
        .expect("built-in profile")
        .with_columns(360)
        .angle_grid();
    let mut scan = Scan::from_xyz(
        (0..grid.len())
            .map(|k| grid.direction(k).map(|d| d * 8.0))
            .collect(),
    );
    scan.ring = Some((0..grid.len()).map(|k| (15 - k / 360) as u16).collect());
    scan
}

/// A recording of two ROS 2 scans.
fn recording(path: &Path) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).expect("create"));
    let mut w = mcap::WriteOptions::new().create(file).expect("writer");
    let s = encoders::schema(Family::Ros2, encoders::Kind::Cloud);
    let schema = w.add_schema(&s.name, &s.encoding, &s.data).expect("schema");
    let id = w
        .add_channel(schema, "/points", "cdr", &BTreeMap::new())
        .expect("channel");
    for k in 0..2u64 {
        let cloud = DecodedCloud {
            scan: wall(),
            stamp_nanos: k,
            frame_id: "lidar".into(),
            notes: Vec::new(),
        };
        let data = encoders::encode_scan(Family::Ros2, &cloud, &[]);
        let t = 1_000_000_000 + k * 100_000_000;
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: k as u32,
            log_time: t,
            publish_time: t,
        };
        w.write_to_known_channel(&header, &data).expect("message");
    }
    w.finish().expect("finish");
}

/// The value-taking long flags in a `--help` text.
fn flags(help: &str) -> Vec<String> {
    let mut out = Vec::new();
    for line in help.lines().map(str::trim_start) {
        let Some(rest) = line.strip_prefix("--").or_else(|| {
            line.split_once(", --")
                .filter(|(short, _)| short.starts_with('-'))
                .map(|(_, r)| r)
        }) else {
            continue;
        };
        let mut words = rest.split_whitespace();
        let name = words.next().unwrap_or_default();
        let takes_value = words.next().is_some_and(|w| w.starts_with('<'));
        let flag = format!("--{name}");
        if takes_value && !SKIPPED.contains(&flag.as_str()) && !out.contains(&flag) {
            out.push(flag);
        }
    }
    out
}

enum Verdict {
    Answer,
    Crash(String),
    Slow,
}

fn run(bin: &Path, args: &[String], limit: Duration, scratch: &Path) -> Verdict {
    let mut child = Command::new("sh")
        .arg("-c")
        .arg("ulimit -v 3145728; exec \"$0\" \"$@\"")
        .arg(bin)
        .args(args)
        .current_dir(scratch)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn");
    let start = Instant::now();
    loop {
        if let Ok(Some(status)) = child.try_wait() {
            let mut err = String::new();
            if let Some(mut e) = child.stderr.take() {
                use std::io::Read;
                let _ = e.read_to_string(&mut err);
            }
            let last = err.lines().last().unwrap_or_default().to_string();
            return match status.code() {
                Some(101) => Verdict::Crash(format!("panic: {last}")),
                Some(c) if (0..=4).contains(&c) => Verdict::Answer,
                Some(c) => Verdict::Crash(format!("exit {c}: {last}")),
                None => Verdict::Crash(format!("killed by a signal: {last}")),
            };
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            return Verdict::Slow;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn main() {
    let mut limit = Duration::from_secs(20);
    let mut only: Option<String> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--seconds" => {
                limit = Duration::from_secs_f64(
                    args.next().and_then(|v| v.parse().ok()).unwrap_or(20.0),
                )
            }
            "--only" => only = args.next(),
            other => panic!("unknown argument {other}"),
        }
    }
    let bin = binary();
    let dir = tempfile::tempdir().expect("scratch folder");
    let d = dir.path();
    recording(&d.join("in.mcap"));
    let kitti = d.join("kitti/velodyne");
    std::fs::create_dir_all(&kitti).expect("kitti folder");
    let points: Vec<u8> = wall()
        .xyz
        .iter()
        .flat_map(|p| [p[0], p[1], p[2], 0.5])
        .flat_map(f32::to_le_bytes)
        .collect();
    std::fs::write(kitti.join("000000.bin"), points).expect("scan");
    // Each command on inputs it accepts; the flag under test is appended.
    let commands: Vec<(&str, Vec<&str>)> = vec![
        ("info", vec!["info", "in.mcap"]),
        ("convert", vec!["convert", "in.mcap", "out.mcap", "--force"]),
        ("import", vec!["import", "kitti", "out.mcap", "--force"]),
        (
            "simulate",
            vec![
                "simulate",
                "--scene",
                "1",
                "--sensor",
                "vlp16",
                "--scans",
                "1",
                "--physics",
                "ideal",
                "out.mcap",
                "--force",
            ],
        ),
        (
            "render",
            vec![
                "render",
                "--raydrop",
                "global",
                "in.mcap",
                "out.mcap",
                "--force",
            ],
        ),
        ("sample", vec!["sample", "--n", "1", "out.mcap", "--force"]),
        (
            "diagnose",
            vec![
                "diagnose", "--sim", "in.mcap", "--real", "in.mcap", "--report", "rep", "--force",
            ],
        ),
    ];
    let (mut crashes, mut slow, mut runs) = (Vec::new(), Vec::new(), 0usize);
    for (name, base) in &commands {
        if only.as_deref().is_some_and(|o| o != *name) {
            continue;
        }
        let help = Command::new(&bin)
            .arg(base[0])
            .arg("--help")
            .output()
            .expect("help");
        let text = String::from_utf8_lossy(&help.stdout).into_owned();
        for flag in flags(&text) {
            for value in VALUES {
                let mut args: Vec<String> = vec!["--quiet".into()];
                args.extend(base.iter().map(|s| s.to_string()));
                args.push(flag.clone());
                args.push(value.into());
                runs += 1;
                match run(&bin, &args, limit, d) {
                    Verdict::Answer => {}
                    Verdict::Crash(why) => {
                        println!("CRASH {name} {flag} {value}: {why}");
                        crashes.push(format!("{name} {flag} {value}"));
                    }
                    Verdict::Slow => {
                        println!("slow  {name} {flag} {value}: over {} s", limit.as_secs());
                        slow.push(format!("{name} {flag} {value}"));
                    }
                }
            }
        }
    }
    println!(
        "{runs} runs: {} crashes, {} past {} s",
        crashes.len(),
        slow.len(),
        limit.as_secs()
    );
    if !crashes.is_empty() {
        std::process::exit(1);
    }
}
