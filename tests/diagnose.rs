//! End-to-end `diagnose` and `render` through the built binary: a
//! concealed range-dropout case on simulated recordings (real side unorganized,
//! sim side organized), the report files (opened in headless Chromium where
//! installed), rendering the fit and the baselines, and clear errors for bad
//! input; a few concealed pairs of the independent generator.

#[path = "common/browser.rs"]
mod browser;
mod common;
#[path = "common/testgen/mod.rs"]
mod testgen;

use std::path::Path;

use common::{run, stderr};

fn simulate(path: &Path, scene: u64, physics: &str, organized: bool) -> f64 {
    let scene = scene.to_string();
    let p = path.to_str().unwrap();
    let mut args = vec![
        "--json",
        "simulate",
        "--scene",
        &scene,
        "--columns",
        "512",
        "--scans",
        "8",
        "--physics",
        physics,
        "--force",
    ];
    if organized {
        args.push("--organized");
    }
    args.push(p);
    let out = run(&args);
    assert!(out.status.success(), "{}", stderr(&out));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    v["keep_rate"].as_f64().unwrap()
}

/// `diagnose --sim SIM --real REAL --report REPORT EXTRA...`.
fn diagnose(sim: &Path, real: &Path, report: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "diagnose",
        "--sim",
        sim.to_str().unwrap(),
        "--real",
        real.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    run(&args)
}

#[test]
fn diagnose_names_a_concealed_range_dropout_and_render_applies_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let physics = d.join("range.json");
    std::fs::write(
        &physics,
        r#"{"range_dropout": {"range_50_m": 40, "softness": 0.4}}"#,
    )
    .unwrap();
    let real = d.join("real.mcap");
    let keep_real = simulate(&real, 21, physics.to_str().unwrap(), false);
    let ideal = d.join("ideal.mcap");
    let keep_ideal = simulate(&ideal, 22, "ideal", true);
    // Conceal: the sim's uniform dropout matches the global drop rate.
    let prob = 1.0 - keep_real / keep_ideal;
    let uniform = d.join("uniform.json");
    std::fs::write(
        &uniform,
        format!(r#"{{"uniform_dropout": {{"prob": {prob}}}}}"#),
    )
    .unwrap();
    let sim = d.join("sim.mcap");
    let keep_sim = simulate(&sim, 22, uniform.to_str().unwrap(), true);
    assert!(
        (keep_sim - keep_real).abs() < 0.01,
        "{keep_sim} vs {keep_real}"
    );

    let report = d.join("report");
    let out = diagnose(&sim, &real, &report, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let r: serde_json::Value =
        serde_json::from_slice(&std::fs::read(report.join("report.json")).unwrap()).unwrap();
    let effects = r["effects"].as_array().unwrap();
    assert_eq!(effects[0]["id"], "range_dropout", "{r:#}");
    let e = &effects[0];
    assert!(e["confidence"].as_f64().unwrap() > 0.5);
    assert!(!e["location"].as_str().unwrap().is_empty());
    assert!(e["params"]["range_50_m"].as_f64().unwrap() > 20.0);
    assert!(e["fit"]["after"].as_f64() < e["fit"]["before"].as_f64());
    assert!(r["fit"]["after"].as_f64() < r["fit"]["before"].as_f64());
    assert!(r["fit"]["metric"].is_string());
    for f in [
        "report.html",
        "fitted_physics.json",
        "drop_vs_range.png",
        "drop_vs_row.png",
        "example_scan.png",
    ] {
        let bytes = std::fs::read(report.join(f)).unwrap();
        assert!(bytes.len() > 100, "{f}");
        if f.ends_with(".png") {
            assert_eq!(&bytes[1..4], b"PNG");
        }
    }
    let html = std::fs::read_to_string(report.join("report.html")).unwrap();
    assert!(html.contains("range_dropout") && html.contains("drop_vs_range.png"));
    // The summary names the effect in words and says how the fit checks against the
    // held-out scans feature by feature.
    let summary = &html[html.find("id='summary'").unwrap()..html.find("</section>").unwrap()];
    assert!(summary.contains("rays lost with distance"), "{summary}");
    assert!(summary.contains("of the real drop rate in"), "{summary}");
    assert!(r["check"].as_array().unwrap().len() >= 3, "{r}");
    assert!(r["check"][0]["bins"].as_u64().unwrap() > 0, "{r}");
    // As a reader sees it: every image loads, no script error.
    if let Some(page) = browser::render(&report.join("report.html"), d) {
        assert_eq!(page.title, "rangegan-mcap diagnose");
        assert!(page.images >= 8, "{page:?}");
        assert!(page.broken.is_empty(), "images that did not load: {page:?}");
        assert!(page.min_width >= 400, "{page:?}");
        assert!(page.script_errors.is_empty(), "{page:?}");
        // At a laptop's width the answer is on the first screen and nothing runs off the
        // right edge.
        assert!(page.scroll_width <= 1280, "{page:?}");
        assert!(page.summary_top.is_some_and(|top| top < 400.0), "{page:?}");
        // The check sees a missing image.
        let broken = d.join("report_broken");
        std::fs::create_dir(&broken).unwrap();
        for entry in std::fs::read_dir(&report).unwrap() {
            let path = entry.unwrap().path();
            if path.file_name().unwrap() != "drop_vs_row.png" {
                std::fs::copy(&path, broken.join(path.file_name().unwrap())).unwrap();
            }
        }
        let page = browser::render(&broken.join("report.html"), d).unwrap();
        assert_eq!(page.broken, vec!["drop_vs_row.png".to_string()], "{page:?}");
    }
    // The report folder is not overwritten without --force.
    let again = diagnose(&sim, &real, &report, &["--completion", "neighbour"]);
    assert!(!again.status.success());
    assert!(stderr(&again).contains("--force"), "{}", stderr(&again));

    // The fitted physics renders onto the ideal recording and drops rays there.
    let rendered = d.join("rendered.mcap");
    let fitted = report.join("fitted_physics.json");
    let out = run(&[
        "--json",
        "render",
        "--physics",
        fitted.to_str().unwrap(),
        ideal.to_str().unwrap(),
        rendered.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["scans"], 8);
    let keep = v["keep_rate"].as_f64().unwrap();
    assert!(keep < keep_ideal - 0.02, "{keep} vs ideal {keep_ideal}");
    // And the rendered recording is still a recording the tool reads.
    let out = run(&["info", rendered.to_str().unwrap()]);
    assert!(out.status.success(), "{}", stderr(&out));

    // Baselines: the real data's global and per-pixel drop frequency.
    for mode in ["global", "pixel"] {
        let out = run(&[
            "--json",
            "render",
            "--raydrop",
            mode,
            "--real",
            real.to_str().unwrap(),
            ideal.to_str().unwrap(),
            rendered.to_str().unwrap(),
            "--force",
        ]);
        assert!(out.status.success(), "{mode}: {}", stderr(&out));
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let keep = v["keep_rate"].as_f64().unwrap();
        assert!(keep < keep_ideal - 0.02, "{mode}: {keep} vs {keep_ideal}");
    }

    // GAN completion (encoder only, to stay quick): recorded in the report.
    let report_gan = d.join("report_gan");
    let out = diagnose(
        &sim,
        &real,
        &report_gan,
        &["--completion", "gan", "--tune-steps", "0"],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let r: serde_json::Value =
        serde_json::from_slice(&std::fs::read(report_gan.join("report.json")).unwrap()).unwrap();
    assert_eq!(r["inputs"]["completion"], "gan", "{:#}", r["inputs"]);
    assert_eq!(r["inputs"]["completion_fallback_scans"], 0);
    assert!(r["inputs"]["completion_model"].is_string());
    assert!(r["fit"]["after"].as_f64() < r["fit"]["before"].as_f64());
    let out = diagnose(
        &sim,
        &real,
        &d.join("report_args"),
        &["--completion", "neighbour", "--model", "x"],
    );
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("--completion gan"),
        "{}",
        stderr(&out)
    );
}

/// `render --raydrop gan` (paper config E): every simulated scan auto-decoded, its
/// x_n sampled; a readable recording, a plausible drop rate, the same bytes with 1
/// and 2 threads; sharpened, as many drops and fewer of them inside surfaces.
#[test]
fn render_raydrop_gan_drops_rays_deterministically() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ideal = d.join("ideal.mcap");
    let out = run(&[
        "--json",
        "simulate",
        "--scene",
        "23",
        "--columns",
        "512",
        "--scans",
        "3",
        "--physics",
        "ideal",
        "--organized",
        ideal.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let keep_ideal = v["keep_rate"].as_f64().unwrap();
    let render = |threads: &str, name: &str, sharpness: &str| {
        let path = d.join(name);
        let out = run(&[
            "--json",
            "--threads",
            threads,
            "render",
            "--raydrop",
            "gan",
            "--tune-steps",
            "2",
            "--drop-sharpness",
            sharpness,
            ideal.to_str().unwrap(),
            path.to_str().unwrap(),
        ]);
        assert!(out.status.success(), "{}", stderr(&out));
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        (path, v)
    };
    let (one, v) = render("1", "gan1.mcap", "1");
    assert_eq!(v["scans"], 3, "{v}");
    assert_eq!(v["skipped"], 0, "{v}");
    assert!(
        v["applied"].as_str().unwrap().contains("raydrop_gan"),
        "{v}"
    );
    let keep = v["keep_rate"].as_f64().unwrap();
    // x_n drops some rays but not all (the model's drop probability is a
    // probability, not a mask).
    assert!(keep < keep_ideal - 0.005, "{keep} vs ideal {keep_ideal}");
    assert!(keep > 0.1 * keep_ideal, "{keep} vs ideal {keep_ideal}");
    let (two, _) = render("2", "gan2.mcap", "1");
    assert!(
        std::fs::read(&one).unwrap() == std::fs::read(&two).unwrap(),
        "1 and 2 threads give different recordings"
    );
    let (sharp, v) = render("1", "gan_sharp.mcap", "8");
    let keep_sharp = v["keep_rate"].as_f64().unwrap();
    let (inside, inside_sharp) = (holes_inside_surfaces(&one), holes_inside_surfaces(&sharp));
    eprintln!(
        "keep {keep:.3} -> {keep_sharp:.3}; inside surfaces {inside:.4} -> {inside_sharp:.4}"
    );
    assert!((keep_sharp - keep).abs() < 0.02, "{keep} -> {keep_sharp}");
    assert!(inside_sharp < 0.5 * inside, "{inside} -> {inside_sharp}");
    // The output is a recording the tool reads, with every scan.
    let rec = rangegan_mcap::recording::read(
        &one,
        None,
        &rangegan_mcap::recording::Grid::FromRecording { columns: None },
    )
    .unwrap();
    assert_eq!(rec.images.len(), 3);
    assert!(rec.skipped.is_empty());
    let out = run(&["info", one.to_str().unwrap()]);
    assert!(out.status.success(), "{}", stderr(&out));
    // --real is for the frequency baselines only.
    let out = run(&[
        "render",
        "--raydrop",
        "gan",
        "--real",
        ideal.to_str().unwrap(),
        ideal.to_str().unwrap(),
        d.join("x.mcap").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("--real"), "{}", stderr(&out));
}

/// The share of `path`'s rays lost between two returns of one surface: an empty pixel whose
/// nearest returns along the row (within 3 columns each side) lie within 5 % in range.
fn holes_inside_surfaces(path: &Path) -> f64 {
    let grid = rangegan_mcap::recording::Grid::FromRecording { columns: None };
    let rec = rangegan_mcap::recording::read(path, None, &grid).unwrap();
    let (mut holes, mut returns) = (0usize, 0usize);
    for image in &rec.images {
        let w = image.width as isize;
        for row in image.range_m.chunks(image.width) {
            let near = |j: isize, step: isize| {
                (1..=3)
                    .map(|d| row[(j + step * d).rem_euclid(w) as usize])
                    .find(|r| *r > 0.0)
            };
            for j in 0..w {
                if row[j as usize] > 0.0 {
                    returns += 1;
                } else if let (Some(l), Some(r)) = (near(j, -1), near(j, 1)) {
                    holes += usize::from((l - r).abs() <= 0.05 * l.min(r));
                }
            }
        }
    }
    holes as f64 / (holes + returns).max(1) as f64
}

#[test]
fn diagnose_errors_name_the_file_and_topic() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let missing = d.join("missing.mcap");
    let out = diagnose(&missing, &missing, &d.join("r"), &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("missing.mcap"), "{}", stderr(&out));
    let not_mcap = d.join("junk.mcap");
    std::fs::write(&not_mcap, b"definitely not an mcap file").unwrap();
    let out = diagnose(&not_mcap, &not_mcap, &d.join("r"), &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("junk.mcap"), "{}", stderr(&out));
    let sample = Path::new(env!("CARGO_MANIFEST_DIR")).join("sample_logs/drive_ideal.mcap");
    let out = diagnose(&sample, &sample, &d.join("r"), &["--topic", "/lidar_top"]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        err.contains("/lidar_top") && err.contains("/velodyne_points"),
        "{err}"
    );
    assert!(
        !d.join("r").join("report.json").exists(),
        "no report after a failure"
    );
}

/// Concealed pairs of the independent generator (its own scenes, ray caster and
/// sensors; seeds apart from the evaluation's): the hard cases of a 32-beam
/// organized cloud with grazing-incidence drops, mixed pixels on 64 beams,
/// motion distortion on a 32-beam organized cloud (a highway: traffic faces the motion at
/// the seam), range with beam dropout
/// together, and a null pair. The full evaluation is `examples/diagnose_eval.rs`.
#[test]
fn independent_generator_pairs_are_named() {
    let cases: [(u64, &[&str], usize, Option<bool>); 5] = [
        (91_001, &["incidence_dropout"], 32, Some(true)),
        (91_002, &["mixed_pixels"], 64, None),
        (92_005, &["motion_distortion"], 32, Some(true)),
        (91_004, &["range_dropout", "beam_dropout"], 64, None),
        (91_005, &[], 32, None),
    ];
    for (seed, effects, beams, organized) in cases {
        let p = testgen::pair_with(seed, effects, beams, organized);
        let d = testgen::diagnose_pair(&p);
        let named: Vec<&str> = d.report.effects.iter().map(|e| e.id.as_str()).collect();
        let context = format!(
            "pair {seed} ({}, {}): truth {:?}, named {named:?}, candidates {:?}",
            p.kind.name(),
            p.sensor.describe(),
            p.truth_params,
            d.report.candidates
        );
        if effects.is_empty() {
            assert!(named.is_empty(), "{context}");
            continue;
        }
        assert!(
            named.first().is_some_and(|n| effects.contains(n)),
            "{context}"
        );
        assert!(effects.iter().all(|e| named.contains(e)), "{context}");
        assert!(d.report.fit.after < d.report.fit.before, "{context}");
    }
}

/// A strong effect's curve never fits it exactly, and whichever other family traces what
/// it leaves would be named beside it: grazing-incidence dropout alone on 128 beams is named
/// alone, while a range dropout (32 beams, 13 % of the rays) beside an incidence dropout
/// that gains 28 times as much is still named. Pairs of the independent generator's plan
/// seeds 393, 417 and 435 (development seeds of the suite).
#[test]
fn a_strong_effects_misfit_is_not_named_beside_it() {
    let cases: [(u64, usize, &[&str]); 3] = [
        (417, 17, &["incidence_dropout"]),
        (435, 17, &["incidence_dropout"]),
        (393, 40, &["incidence_dropout", "range_dropout"]),
    ];
    for (plan_seed, index, expected) in cases {
        let (seed, effects, beams) = testgen::plan(plan_seed).swap_remove(index);
        let p = testgen::pair(seed, &effects, beams);
        let d = testgen::diagnose_pair(&p);
        let named: Vec<&str> = d.report.effects.iter().map(|e| e.id.as_str()).collect();
        let gains: Vec<f64> = (d.report.effects.iter())
            .map(|e| e.gain_nats_per_pixel)
            .collect();
        assert_eq!(named, expected, "pair {seed}: gains {gains:?}");
    }
}

/// Motion during the sweep is found where each sensor's sweep starts, whatever the cloud
/// says it with: pairs of the independent generator whose sweeps start behind or ahead,
/// turn either way, on 16 to 128 beams, organized or not, with a ring and a time field or
/// without (the seam then comes from the order the points were written in). Motion moves
/// only surfaces that face it; where nothing faces it at the seam (open road, a garage's
/// floor and ceiling) it leaves nothing to read, and nothing is claimed. The same sensors
/// without motion name nothing.
#[test]
fn motion_is_found_at_the_seam_each_cloud_shows() {
    let cases: [(u64, usize, bool); 5] = [
        (92_001, 16, false),
        (92_003, 64, true),
        (92_004, 128, false),
        (92_005, 32, false),
        (92_006, 16, true),
    ];
    let mut found = 0;
    for (seed, beams, organized) in cases {
        let p = testgen::pair_with(seed, &["motion_distortion"], beams, Some(organized));
        let d = testgen::diagnose_pair(&p);
        let named: Vec<&str> = d.report.effects.iter().map(|e| e.id.as_str()).collect();
        let context = format!(
            "pair {seed} ({}, {}): named {named:?}, candidates {:?}",
            p.kind.name(),
            p.sensor.describe(),
            d.report.candidates
        );
        let readable = d
            .report
            .candidates
            .iter()
            .any(|c| c.id == "motion_distortion");
        if !readable {
            assert!(named.is_empty(), "{context}");
            continue;
        }
        found += 1;
        assert_eq!(named.first(), Some(&"motion_distortion"), "{context}");
        let motion = &d.report.effects[0];
        assert!(
            motion.params["motion_per_sweep_m"].as_f64().unwrap() > 0.0,
            "{context}"
        );
        let seam = motion.params["seam_azimuth_deg"].as_f64().unwrap() as f32;
        let off = (seam - p.sensor.sweep_start_rad.to_degrees() + 540.0).rem_euclid(360.0) - 180.0;
        assert!(off.abs() < 3.0, "{context}: seam at {seam} deg");
    }
    assert!(found >= 3, "motion readable in {found} of 5 pairs");
    for (seed, beams, organized) in [(92_002, 32, true), (92_004, 128, false)] {
        let p = testgen::pair_with(seed, &[], beams, Some(organized));
        let d = testgen::diagnose_pair(&p);
        assert!(
            d.report.effects.is_empty(),
            "pair {seed}: {:?}",
            d.report.effects
        );
    }
}

/// A sensor that reports each column in the frame of its own firing instant, not
/// de-skewed, its sweep starting straight behind the ego, and nothing telling the diagnosis
/// how fast it drove: organized and unorganized clouds, with a per-point time field and
/// without. The ground under the sensor is met at the same range whatever it does, so only
/// the surfaces facing the motion step at the seam; the speed is measured from them.
#[test]
fn motion_is_measured_behind_the_ego_without_being_told_the_speed() {
    // Highways: traffic behind the ego faces its motion. Each case is the next plan seed
    // from 93 001 that draws a highway.
    let highways = (93_001u64..).filter(|&seed| {
        testgen::Rng::new(seed).pick(&testgen::Kind::ALL) == testgen::Kind::Highway
    });
    let setups = [
        (32, true, true),
        (64, false, true),
        (32, false, false),
        (64, true, false),
    ];
    for (seed, (beams, organized, time_field)) in highways.zip(setups) {
        let p = testgen::pair_on(seed, &["motion_distortion"], beams, |sensor| {
            sensor.organized = organized;
            sensor.time_field = time_field;
            sensor.sweep_start_rad = std::f32::consts::PI;
        });
        let d = testgen::diagnose_pair(&p);
        let named: Vec<&str> = d.report.effects.iter().map(|e| e.id.as_str()).collect();
        let context = format!(
            "pair {seed} ({}, {}, {:.1} m/s): truth {:?}, named {named:?}, candidates {:?}",
            p.kind.name(),
            p.sensor.describe(),
            p.real_speed_mps,
            p.truth_params,
            d.report.candidates
        );
        assert_eq!(named.first(), Some(&"motion_distortion"), "{context}");
        let scale: f32 = p.truth_params[0]
            .split("scale: ")
            .nth(1)
            .and_then(|rest| rest.split(',').next())
            .and_then(|v| v.parse().ok())
            .expect("the drawn scale");
        let truth = f64::from(scale * p.real_speed_mps);
        let speed = d.report.effects[0].params["speed_mps"].as_f64().unwrap();
        assert!(
            (speed - truth).abs() <= 0.25 * truth + 1.0,
            "{context}: measured {speed:.1} m/s, undeskewed {truth:.1} m/s"
        );
        assert!(d.report.fit.after < d.report.fit.before, "{context}");
    }
}

/// Two simulated streets are alike; a simulated street against a real Ouster OS1-64
/// recording of a small indoor space is said to differ, on the report's first screen and
/// on stderr, and the effects named there get half the confidence.
#[test]
fn a_street_against_a_real_room_is_said_to_be_another_scene() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (a, b) = (d.join("a.mcap"), d.join("b.mcap"));
    simulate(&a, 31, "ideal", false);
    simulate(&b, 32, "realistic", false);
    let report = d.join("streets");
    let o = diagnose(&a, &b, &report, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report.join("report.json")).unwrap())
            .unwrap();
    let scene = &json["inputs"]["scene"];
    assert_eq!(scene["differs"], false, "{scene}");
    assert!(
        !std::fs::read_to_string(report.join("report.html"))
            .unwrap()
            .contains("Different scenes")
    );

    let Some(data) = common::real_data("a_street_against_a_real_room_is_said_to_be_another_scene")
    else {
        return;
    };
    let real = data.join("mcap/pointcloudset_test.mcap");
    let sim = d.join("os1.mcap");
    let o = run(&[
        "--quiet",
        "simulate",
        "--scene",
        "3",
        "--sensor",
        "os1-64",
        "--columns",
        "512",
        "--scans",
        "6",
        "--physics",
        "ideal",
        sim.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report = d.join("room");
    let o = diagnose(&sim, &real, &report, &["--columns", "512"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("scenes differ"), "{}", stderr(&o));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report.join("report.json")).unwrap())
            .unwrap();
    let scene = &json["inputs"]["scene"];
    assert_eq!(scene["differs"], true, "{scene}");
    assert!(scene["range_distance"].as_f64().unwrap() > 0.5, "{scene}");
    for e in json["effects"].as_array().unwrap() {
        assert!(e["confidence"].as_f64().unwrap() <= 0.5, "{e}");
    }
    let html = std::fs::read_to_string(report.join("report.html")).unwrap();
    let first_screen = &html[..html.find("Missing physics").expect("a summary")];
    assert!(first_screen.contains("Different scenes"), "{first_screen}");
    // The room's scans have sectors with no return on any beam: gaps in the data, on the
    // first screen and stderr, none on the simulated side, and no fitted sector of
    // self-occlusion lies inside one.
    assert!(
        first_screen.contains("Gaps in the recording"),
        "{first_screen}"
    );
    assert!(stderr(&o).contains("gaps in the data"), "{}", stderr(&o));
    let gaps = json["inputs"]["gaps"].as_array().unwrap();
    assert!(!gaps.is_empty());
    assert!(gaps.iter().all(|g| g["recording"] == "real"), "{gaps:?}");
    let inside = |az: f64| {
        gaps.iter().any(|g| {
            let (a, b) = (
                g["azimuth_deg"][0].as_f64().unwrap(),
                g["azimuth_deg"][1].as_f64().unwrap(),
            );
            // Azimuth falls from a gap's first column to its last.
            b + 1.0 < az && az < a - 1.0
        })
    };
    let sectors = json["fitted_physics"]["self_occlusion"]["sectors"].as_array();
    for s in sectors.into_iter().flatten() {
        let mid =
            (s["azimuth_min_deg"].as_f64().unwrap() + s["azimuth_max_deg"].as_f64().unwrap()) / 2.0;
        assert!(
            !inside(mid),
            "a fitted sector at {mid} deg lies in a gap: {s}"
        );
    }
}

/// A real recording of one scan gets a report: the fit is made on half its pixels and
/// checked on the other half, and the first screen and stderr say so. On a simulated
/// `realistic` scan against the ideal simulator the held-out fit improves; the real
/// one-scan Ouster OS-1-32 capture is diagnosed too.
#[test]
fn a_recording_of_one_scan_is_checked_on_held_out_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (sim, real) = (d.join("sim.mcap"), d.join("real.mcap"));
    simulate(&sim, 41, "ideal", false);
    let o = run(&[
        "--quiet",
        "simulate",
        "--scene",
        "42",
        "--columns",
        "512",
        "--scans",
        "1",
        "--physics",
        "realistic",
        real.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report = d.join("one");
    let o = diagnose(&sim, &real, &report, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("has one scan"), "{}", stderr(&o));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report.join("report.json")).unwrap())
            .unwrap();
    assert_eq!(json["inputs"]["held_out"], "pixels");
    assert!(
        !json["effects"].as_array().unwrap().is_empty(),
        "{}",
        json["effects"]
    );
    let fit = &json["fit"];
    assert!(fit["after"].as_f64() < fit["before"].as_f64(), "{fit}");
    let html = std::fs::read_to_string(report.join("report.html")).unwrap();
    let first_screen = &html[..html.find("Missing physics").expect("a summary")];
    assert!(first_screen.contains("One real scan"), "{first_screen}");

    let Some(data) = common::real_data("a_recording_of_one_scan_is_checked_on_held_out_pixels")
    else {
        return;
    };
    let capture = data.join("ouster/OS-1-32-G_v2.1.1_1024x10.pcap");
    let meta = data.join("ouster/OS-1-32-G_v2.1.1_1024x10.json");
    let (os32, sim32) = (d.join("os32.mcap"), d.join("sim32.mcap"));
    let o = run(&[
        "--quiet",
        "import",
        capture.to_str().unwrap(),
        os32.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = run(&[
        "--quiet",
        "simulate",
        "--scene",
        "2",
        "--sensor",
        meta.to_str().unwrap(),
        "--columns",
        "1024",
        "--scans",
        "4",
        "--physics",
        "ideal",
        sim32.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = diagnose(&sim32, &os32, &d.join("os32"), &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("has one scan"), "{}", stderr(&o));
}

/// A 64-beam simulation against a real VLP-16 recording (imported from its PCD file, no
/// `simulate` metadata: its sensor is estimated from its scan) is refused, naming both
/// sensors, instead of squeezing 16 beams onto 64 rows and "finding" dead beams.
#[test]
fn recordings_of_two_sensors_are_not_compared() {
    let Some(root) = common::real_data("recordings_of_two_sensors_are_not_compared") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let sim = d.join("sim.mcap");
    simulate(&sim, 5, "ideal", false);
    let real = d.join("vlp16.mcap");
    let o = run(&[
        "import",
        root.join("nebula").to_str().unwrap(),
        real.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = diagnose(&sim, &real, &d.join("r"), &[]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        // The VLP-16's count is estimated from one room scan: 15 or 16 beams.
        err.contains("64-beam") && err.contains("vlp16.mcap a 1"),
        "{err}"
    );
    assert!(!d.join("r").join("report.json").exists());
}
