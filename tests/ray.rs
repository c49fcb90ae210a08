//! The Ray driver (`python/rangegan_ray.py`) on a real local Ray cluster, against the
//! single-process `convert` of the same 12-file dataset; the checks themselves are in
//! `tests/py/test_ray.py` (byte-identical outputs, a killed worker, an idle rerun).

mod common;

use common::*;
use rangegan_mcap::io::Family;

#[test]
fn ray_driver_matches_one_process_and_survives_a_killed_worker() {
    let Some(python) = python() else { return };
    let has_ray = std::process::Command::new(&python)
        .args(["-c", "import ray"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_ray {
        assert!(
            std::env::var("CI").is_err(),
            "CI must install python/requirements.txt (.ci/run)"
        );
        eprintln!("skipped: no Ray in {}; run .ci/run once", python.display());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (input, single) = (dir.path().join("in"), dir.path().join("single"));
    for i in 0..12 {
        let path = input.join(format!("day{}/drive{i:02}.mcap", i % 3));
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        // Enough scans that a conversion is still running when the worker is killed.
        write_recording(&path, &[Family::Ros2, Family::Foxglove], 30 + i, None);
    }
    let o = run(&[
        "--quiet",
        "convert",
        input.to_str().unwrap(),
        single.to_str().unwrap(),
        "--quality",
        "off",
        "--jobs",
        "2",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = std::process::Command::new(&python)
        .arg("tests/py/test_ray.py")
        .args([
            env!("CARGO_BIN_EXE_rangegan-mcap"),
            input.to_str().unwrap(),
            single.to_str().unwrap(),
            dir.path().to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        stderr(&o)
    );
}
