//! `convert` over folders of recordings through the built binary: outputs keep their
//! relative paths and match the one-file form byte for byte, a bad file does not stop the
//! others, the manifest lets reruns skip what is done, and `--jobs` / `--shard` change
//! nothing in the outputs.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::*;
use rangegan_mcap::io::Family;

/// Writes `rels` below `root` as small recordings (scan count from the index, so files differ).
fn write_dataset(root: &Path, rels: &[&str]) {
    for (i, rel) in rels.iter().enumerate() {
        let path = root.join(rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        write_recording(&path, &[Family::Ros2], 2 + i % 3, Some(64 * 1024));
    }
}

/// Every file below `root` (relative path -> bytes).
fn tree(root: &Path) -> BTreeMap<String, Vec<u8>> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(root, root, &mut out);
    out
}

/// The recordings of an output folder (manifests left out).
fn outputs(root: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut t = tree(root);
    t.retain(|k, _| k.ends_with(".mcap"));
    t
}

fn manifest_lines(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn convert_dataset(args: &[&str]) -> std::process::Output {
    let mut all = vec!["--quiet", "convert", "--quality", "off"];
    all.extend_from_slice(args);
    run(&all)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn a_folder_converts_like_each_file_alone_and_a_rerun_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("in"), dir.path().join("out"));
    write_dataset(&input, &["a/x.mcap", "a/y.mcap", "b/c/z.mcap"]);
    std::fs::write(input.join("a/bad.mcap"), b"not a recording").unwrap();
    let inputs_before = tree(&input);

    let o = convert_dataset(&[s(&input), s(&out), "--jobs", "2"]);
    assert_eq!(o.status.code(), Some(4), "one bad file: {}", stderr(&o));
    assert!(stderr(&o).contains("bad.mcap"), "{}", stderr(&o));
    assert_eq!(tree(&input), inputs_before, "inputs are never modified");
    let converted = outputs(&out);
    let rels: Vec<&str> = converted.keys().map(|k| k.as_str()).collect();
    assert_eq!(rels, ["a/x.mcap", "a/y.mcap", "b/c/z.mcap"]);

    // Each output is what the one-file form writes for it (named by its relative path).
    for (rel, bytes) in &converted {
        let single = dir.path().join("single.mcap");
        let o = bin()
            .current_dir(&input)
            .args([
                "--quiet",
                "convert",
                "--quality",
                "off",
                rel,
                s(&single),
                "--force",
            ])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(std::fs::read(&single).unwrap() == *bytes, "{rel} differs");
    }

    let manifest = out.join("rangegan-manifest.jsonl");
    let lines = manifest_lines(&manifest);
    assert_eq!(lines.len(), 4);
    let by_input: BTreeMap<&str, &serde_json::Value> = lines
        .iter()
        .map(|l| (l["input"].as_str().unwrap(), l))
        .collect();
    assert_eq!(by_input["a/bad.mcap"]["status"], "failed");
    let x = by_input["a/x.mcap"];
    assert_eq!(
        (x["status"].as_str(), x["scans"].as_u64()),
        (Some("ok"), Some(2))
    );
    assert_eq!(
        x["output_size"].as_u64(),
        Some(converted["a/x.mcap"].len() as u64)
    );
    assert!(x["input_hash"].as_str().unwrap().starts_with("blake3:"));
    assert!(x["args"].as_str().unwrap().contains("--quality off"));

    // A rerun retries only the failed file; the others are up to date.
    let o = convert_dataset(&[s(&input), s(&out), "--json"]);
    assert_eq!(o.status.code(), Some(4));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["total"]["skipped"], 3, "{summary}");
    assert_eq!(manifest_lines(&manifest).len(), 5);
    assert_eq!(outputs(&out), converted);

    // A killed run leaves a torn last line; a changed input and a deleted output are redone.
    std::fs::remove_file(input.join("a/bad.mcap")).unwrap();
    let mut text = std::fs::read(&manifest).unwrap();
    text.extend_from_slice(b"{\"input\":\"a/x.mc");
    std::fs::write(&manifest, text).unwrap();
    write_recording(&input.join("a/y.mcap"), &[Family::Ros1], 3, None);
    std::fs::remove_file(out.join("b/c/z.mcap")).unwrap();
    let o = convert_dataset(&[s(&input), s(&out), "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (
            summary["total"]["ok"].as_u64(),
            summary["total"]["skipped"].as_u64()
        ),
        (Some(2), Some(1))
    );
    let lines = manifest_lines(&manifest);
    assert_eq!(lines.len(), 7, "torn line cut, two new lines");
    assert_eq!(outputs(&out)["b/c/z.mcap"], converted["b/c/z.mcap"]);

    // Nothing left to do; --force redoes every file.
    let o = convert_dataset(&[s(&input), s(&out), "--json"]);
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["total"]["ok"], 0);
    let o = convert_dataset(&[s(&input), s(&out), "--json", "--force"]);
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["total"]["ok"], 3);

    // A file a flag names is recorded with a digest of it: the same name with other
    // contents is not up to date.
    let profile = dir.path().join("sensor.json");
    let hdl64e = rangegan_mcap::lidar::SensorProfile::kitti_hdl64e();
    let ok = |args: &[&str]| {
        let o = convert_dataset(args);
        let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        summary["total"]["ok"].as_u64().unwrap()
    };
    let with_sensor = [s(&input), s(&out), "--json", "--sensor", s(&profile)];
    std::fs::write(&profile, serde_json::to_string(&hdl64e).unwrap()).unwrap();
    assert_eq!(ok(&with_sensor), 3);
    assert_eq!(ok(&with_sensor), 0);
    std::fs::write(&profile, serde_json::to_string_pretty(&hdl64e).unwrap()).unwrap();
    assert_eq!(ok(&with_sensor), 3, "a changed --sensor file");
    let args = manifest_lines(&manifest).last().unwrap()["args"].clone();
    assert!(
        args.as_str().unwrap().contains("sensor.json@blake3:"),
        "{args}"
    );
}

#[test]
fn jobs_and_shards_write_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in");
    let rels: Vec<String> = (0..8).map(|i| format!("d{}/r{i}.mcap", i % 3)).collect();
    write_dataset(&input, &rels.iter().map(|r| r.as_str()).collect::<Vec<_>>());
    let run_into = |name: &str, extra: &[&str]| -> PathBuf {
        let out = dir.path().join(name);
        let mut args = vec![s(&input), s(&out)];
        args.extend_from_slice(extra);
        let o = convert_dataset(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        out
    };
    let one = outputs(&run_into("one", &["--jobs", "1", "--threads", "1"]));
    assert_eq!(one.len(), 8);
    assert_eq!(outputs(&run_into("three", &["--jobs", "3"])), one);
    let sharded = dir.path().join("sharded");
    let mut taken = Vec::new();
    for i in 0..3 {
        let shard = format!("{i}/3");
        run_into("sharded", &["--shard", &shard, "--jobs", "2"]);
        let m = sharded.join(format!("rangegan-manifest.shard-{i}-of-3.jsonl"));
        taken.extend(
            manifest_lines(&m)
                .into_iter()
                .map(|l| l["input"].as_str().unwrap().to_string()),
        );
    }
    assert_eq!(outputs(&sharded), one, "union of shards = one process");
    taken.sort();
    assert_eq!(
        taken,
        rels.iter()
            .cloned()
            .collect::<std::collections::BTreeSet<_>>()
            .into_iter()
            .collect::<Vec<_>>(),
        "each file in exactly one shard"
    );
    // A whole run afterwards finds every shard's work done.
    let o = convert_dataset(&[s(&input), s(&sharded), "--dry-run"]);
    let listing = String::from_utf8_lossy(&o.stdout);
    assert_eq!(
        listing.lines().filter(|l| l.starts_with("skip")).count(),
        8,
        "{listing}"
    );
}

#[test]
fn dataset_flags_and_folders_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in");
    write_dataset(&input, &["x.mcap"]);
    let file = input.join("x.mcap");
    let out = dir.path().join("o");
    for (args, expected) in [
        (vec![s(&input), s(&input)], "output folder is an input"),
        (
            vec![s(&file), s(&out), "--shard", "0/2"],
            "convert datasets",
        ),
        (vec![s(&input), s(&out), "--shard", "2/2"], "0 <= I < N"),
        (
            vec![s(&input), s(&out), "--channels", "depth"],
            "decoded channels need",
        ),
        (vec![s(&input), s(&file)], "needs an output folder"),
    ] {
        let o = convert_dataset(&args);
        assert!(!o.status.success(), "{args:?}");
        assert!(stderr(&o).contains(expected), "{args:?}: {}", stderr(&o));
    }
    // An output folder inside the input folder is never read as input.
    let inner = input.join("converted");
    assert!(convert_dataset(&[s(&input), s(&inner)]).status.success());
    let o = convert_dataset(&[s(&input), s(&inner), "--force", "--json"]);
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["total"]["files"], 1);
    // An output not in the manifest is not overwritten without --force.
    let foreign = dir.path().join("foreign");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("x.mcap"), b"someone else's").unwrap();
    let o = convert_dataset(&[s(&input), s(&foreign)]);
    assert_eq!(o.status.code(), Some(4));
    assert_eq!(
        std::fs::read(foreign.join("x.mcap")).unwrap(),
        b"someone else's"
    );
    // An output folder inside the input folder whose file is not ours: that file is an
    // input, refused even with --force, and the error does not suggest --force.
    let sub = input.join("sub");
    std::fs::create_dir_all(&sub).unwrap();
    std::fs::write(sub.join("x.mcap"), b"an input").unwrap();
    for flags in [vec![], vec!["--force"]] {
        let mut args = vec![s(&input), s(&sub)];
        args.extend(flags);
        let o = convert_dataset(&args);
        assert_eq!(o.status.code(), Some(4), "{args:?}: {}", stderr(&o));
        assert!(stderr(&o).contains("input folder"), "{}", stderr(&o));
        assert!(!stderr(&o).contains("--force"), "{}", stderr(&o));
        assert_eq!(std::fs::read(sub.join("x.mcap")).unwrap(), b"an input");
    }
    #[cfg(unix)]
    links_at_the_outputs_are_named(&input, dir.path());
}

/// OUT as a symlink that points nowhere is named as such (folder and one-file form), and a
/// manifest that links to an input recording is refused without touching the recording.
#[cfg(unix)]
fn links_at_the_outputs_are_named(input: &Path, dir: &Path) {
    use std::os::unix::fs::symlink;
    let nowhere = dir.join("nowhere");
    let folder = dir.join("dangling-folder");
    symlink(nowhere.join("o"), &folder).unwrap();
    let o = convert_dataset(&[s(input), s(&folder)]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("dangling-folder is a symlink")
            && stderr(&o).contains("does not exist"),
        "{}",
        stderr(&o)
    );
    let file = dir.join("dangling.mcap");
    symlink(nowhere.join("x.mcap"), &file).unwrap();
    let o = convert_dataset(&[s(&input.join("x.mcap")), s(&file)]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("dangling.mcap exists (a symlink"),
        "{}",
        stderr(&o)
    );
    assert!(std::fs::read_link(&file).is_ok(), "the link was replaced");
    let out = dir.join("linked-manifest");
    std::fs::create_dir_all(&out).unwrap();
    let recording = input.join("x.mcap");
    let before = std::fs::read(&recording).unwrap();
    symlink(&recording, out.join("rangegan-manifest.jsonl")).unwrap();
    let o = convert_dataset(&[s(input), s(&out)]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("is a symlink"), "{}", stderr(&o));
    assert_eq!(std::fs::read(&recording).unwrap(), before);
}

/// The topics of a recording's messages.
fn topics(path: &Path) -> std::collections::BTreeSet<String> {
    let bytes = std::fs::read(path).unwrap();
    mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(|m| m.unwrap().channel.topic.clone())
        .collect()
}

#[test]
fn chosen_channels_and_writer_settings() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in");
    write_dataset(&input, &["x.mcap"]);
    let quick = ["--decoder", "gan", "--w-steps", "2", "--tune-steps", "2"];
    // Decoded channels chosen; the same bytes with 1 and 2 files at once.
    let mut outs = Vec::new();
    for (name, jobs) in [("j1", "1"), ("j2", "2")] {
        let out = dir.path().join(name);
        let mut args = vec![
            "--quiet",
            "convert",
            s(&input),
            s(&out),
            "--channels",
            "raydrop_prob,raydrop_mask",
            "--mask-samples",
            "2",
            "--jobs",
            jobs,
        ];
        args.extend_from_slice(&quick);
        let o = run(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        outs.push(outputs(&out));
    }
    assert_eq!(outs[0], outs[1]);
    let got = topics(&dir.path().join("j1/x.mcap"));
    let ours: Vec<&str> = got
        .iter()
        .filter(|t| t.contains("/rangegan/"))
        .map(|t| t.as_str())
        .collect();
    assert_eq!(
        ours,
        [
            "/lidar_ros2/rangegan/raydrop_mask",
            "/lidar_ros2/rangegan/raydrop_mask_1",
            "/lidar_ros2/rangegan/raydrop_prob"
        ]
    );
    // Compression and chunking change the bytes, never the messages.
    let mut sizes = Vec::new();
    for compression in ["zstd", "lz4", "none"] {
        let out = dir.path().join(compression);
        let o = convert_dataset(&[
            s(&input),
            s(&out),
            "--compression",
            compression,
            "--chunk-size",
            "100000",
            "--channels",
            "range",
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        let path = out.join("x.mcap");
        assert!(topics(&path).contains("/lidar_ros2/rangegan/range"));
        sizes.push(std::fs::metadata(&path).unwrap().len());
    }
    assert!(sizes[0] < sizes[2] && sizes[1] < sizes[2], "{sizes:?}");
    // A chosen grid size that no topic's grid gives is reported, naming the grids written.
    let out = dir.path().join("upsampled.mcap");
    let o = run(&[
        "convert",
        s(&input.join("x.mcap")),
        s(&out),
        "--upsample",
        "2",
        "--channels",
        "depth,points_3x5",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains("--channels points_3x5 was not written") && !err.contains("--channels depth "),
        "{err}"
    );
}

/// Runs the shard command of each recipe in `deploy/` for every shard index (the Slurm script
/// itself, the Kubernetes Job's container command) with `--quality off`: the union of the
/// shards is the single-process conversion.
#[test]
fn deployment_recipes_convert_every_shard() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("recordings");
    let rels: Vec<String> = (0..5).map(|i| format!("r{i}.mcap")).collect();
    write_dataset(&input, &rels.iter().map(|r| r.as_str()).collect::<Vec<_>>());
    let whole = dir.path().join("whole");
    assert!(convert_dataset(&[s(&input), s(&whole)]).status.success());
    let expected = outputs(&whole);
    let bin_dir = Path::new(env!("CARGO_BIN_EXE_rangegan-mcap"))
        .parent()
        .unwrap();
    let path = format!(
        "{}:{}",
        bin_dir.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let quick = |cmd: &str| cmd.replace("--quality fast", "--quality off");

    // Slurm: the script, checked by bash, run once per array index.
    let script = std::fs::read_to_string("deploy/slurm-array.sh").unwrap();
    let o = std::process::Command::new("bash")
        .args(["-n", "deploy/slurm-array.sh"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(script.contains("#SBATCH --array=0-7") && script.contains("SHARDS=${SHARDS:-8}"));
    let slurm_out = dir.path().join("slurm");
    for i in 0..8 {
        let o = std::process::Command::new("bash")
            .arg("-c")
            .arg(quick(&script))
            .args(["slurm-array.sh", s(&input), s(&slurm_out)])
            .env("PATH", &path)
            .env("SLURM_ARRAY_TASK_ID", i.to_string())
            .output()
            .unwrap();
        assert!(o.status.success(), "task {i}: {}", stderr(&o));
    }
    assert_eq!(outputs(&slurm_out), expected);

    // Kubernetes: the Indexed Job parsed as YAML; its container command run per index.
    let Some(python) = python() else { return };
    let parse = "import json, sys, yaml; j = yaml.safe_load(open('deploy/k8s-indexed-job.yaml')); \
        s = j['spec']; c = s['template']['spec']['containers'][0]; \
        print(json.dumps([j['kind'], s['completionMode'], s['completions'], c['env'][0]['value'], c['command'], c['args'][0]]))";
    let o = std::process::Command::new(&python)
        .args(["-c", parse])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let job: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (job[0].as_str(), job[1].as_str()),
        (Some("Job"), Some("Indexed"))
    );
    let shards = job[2].as_u64().unwrap();
    assert_eq!(
        job[3].as_str(),
        Some(shards.to_string().as_str()),
        "SHARDS = completions"
    );
    assert_eq!(job[4], serde_json::json!(["/bin/sh", "-c"]));
    let data = dir.path().to_str().unwrap();
    let k8s_out = dir.path().join("converted");
    for i in 0..shards {
        let cmd = quick(job[5].as_str().unwrap()).replace("/data", data);
        let o = std::process::Command::new("/bin/sh")
            .args(["-c", &cmd])
            .env("PATH", &path)
            .env("SHARDS", shards.to_string())
            .env("JOB_COMPLETION_INDEX", i.to_string())
            .output()
            .unwrap();
        assert!(o.status.success(), "index {i}: {}", stderr(&o));
    }
    assert_eq!(outputs(&k8s_out), expected);
}
