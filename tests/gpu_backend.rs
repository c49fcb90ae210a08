//! The GPU training path proven without a GPU: `train --backend wgpu` on a software Vulkan
//! device (Mesa's lavapipe in CI) takes the same first steps as the CPU backend, within a
//! stated tolerance, and the checkpoint it writes resumes on the CPU. Needs a build with
//! `--features wgpu`: the tests' own binary when they are built with it (as CI does, with
//! `RANGEGAN_REQUIRE_WGPU=1` so that the test cannot skip there), or the one named by
//! `RANGEGAN_WGPU_BIN`; elsewhere it skips with a message.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use common::*;

/// Relative difference allowed between the backends' losses at each of the first three
/// steps: the same weights and batches, other summation orders and fused kernels (on
/// lavapipe: 1e-6 for D and 1e-4 for G at the first step, 3e-3 for G by the third, as
/// Adam's normalised steps carry the first differences on).
const LOSS_TOLERANCE: f64 = 0.01;

fn wgpu_binary() -> Option<PathBuf> {
    if cfg!(feature = "wgpu") {
        return Some(PathBuf::from(env!("CARGO_BIN_EXE_rangegan-mcap")));
    }
    let bin = std::env::var_os("RANGEGAN_WGPU_BIN").map(PathBuf::from);
    if bin.is_none() {
        assert!(
            std::env::var_os("RANGEGAN_REQUIRE_WGPU").is_none(),
            "RANGEGAN_REQUIRE_WGPU is set, but these tests were built without `--features wgpu` and RANGEGAN_WGPU_BIN names no wgpu build"
        );
        eprintln!(
            "skipped: set RANGEGAN_WGPU_BIN to a `cargo build --release --features wgpu` binary (and have a Vulkan device, e.g. Mesa's lavapipe)"
        );
    }
    bin
}

fn ok(o: Output, what: &str) -> Output {
    assert!(o.status.success(), "{what}: {}", stderr(&o));
    o
}

/// The logged (loss_d, loss_g) lines of a run.
fn losses(run: &Path) -> Vec<(f64, f64)> {
    std::fs::read_to_string(run.join("log.jsonl"))
        .unwrap()
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            (v["loss_d"].as_f64().unwrap(), v["loss_g"].as_f64().unwrap())
        })
        .collect()
}

fn images(run: &Path) -> u64 {
    let text = std::fs::read_to_string(run.join("checkpoint/state.json")).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["images"].as_u64().unwrap()
}

#[test]
fn wgpu_training_matches_the_cpu_and_resumes_there() {
    let Some(wgpu) = wgpu_binary() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("sim.bin");
    // A small simulated dataset (64 beams x 64 columns), cached once for both runs.
    let seed_run = dir.path().join("cache-run");
    ok(
        run(&[
            "--quiet",
            "train",
            seed_run.to_str().unwrap(),
            "--sim-scans",
            "8",
            "--columns",
            "64",
            "--cache",
            cache.to_str().unwrap(),
            "--batch",
            "2",
            "--total-images",
            "2",
        ]),
        "the dataset cache",
    );
    // Both runs start from one saved config (the dataset's sensor, batch 2, seed 5), with
    // a log line per step.
    let text = std::fs::read_to_string(seed_run.join("config.json")).unwrap();
    let mut config: serde_json::Value = serde_json::from_str(&text).unwrap();
    config["log_every_steps"] = 1.into();
    config["seed"] = 5.into();
    config["batch_size"] = 2.into();
    let train = |bin: Option<&Path>, run_dir: &Path, backend: &str, images: &str| {
        if !run_dir.exists() {
            std::fs::create_dir(run_dir).unwrap();
            std::fs::write(run_dir.join("config.json"), config.to_string()).unwrap();
        }
        let args = [
            "--quiet",
            "train",
            run_dir.to_str().unwrap(),
            "--cache",
            cache.to_str().unwrap(),
            "--backend",
            backend,
            "--total-images",
            images,
        ];
        match bin {
            Some(b) => Command::new(b).args(args).output().unwrap(),
            None => run(&args),
        }
    };
    let (cpu, gpu) = (dir.path().join("cpu"), dir.path().join("gpu"));
    ok(train(None, &cpu, "flex", "6"), "the CPU run");
    ok(train(Some(&wgpu), &gpu, "wgpu", "6"), "the wgpu run");
    let (a, b) = (losses(&cpu), losses(&gpu));
    assert!(a.len() == 3 && b.len() == 3, "{a:?} {b:?}");
    for ((d_cpu, g_cpu), (d_gpu, g_gpu)) in a.iter().zip(&b) {
        for (x, y) in [(d_cpu, d_gpu), (g_cpu, g_gpu)] {
            let rel = (x - y).abs() / x.abs().max(1e-3);
            eprintln!("loss cpu {x:.6} wgpu {y:.6}: relative difference {rel:.2e}");
            assert!(rel <= LOSS_TOLERANCE, "cpu {x} wgpu {y}");
        }
    }
    // The wgpu run's checkpoint resumes on the CPU.
    assert_eq!(images(&gpu), 6);
    ok(
        train(None, &gpu, "flex", "10"),
        "resuming the wgpu run on the CPU",
    );
    assert_eq!(images(&gpu), 10);
}
