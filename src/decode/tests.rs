use super::*;
use crate::lidar::SurfaceRule;
use crate::model::sample::{SampleOptions, sample};

#[test]
fn scan_seed_depends_on_topic_and_time() {
    assert_eq!(scan_seed("/a", 5), scan_seed("/a", 5));
    assert_ne!(scan_seed("/a", 5), scan_seed("/b", 5));
    assert_ne!(scan_seed("/a", 5), scan_seed("/a", 6));
}

#[test]
fn sparsify_keeps_evenly_spaced_rows_or_a_fraction() {
    assert_eq!(
        Sparsify::kept_rows(8, 64),
        vec![0, 8, 16, 24, 32, 40, 48, 56]
    );
    assert_eq!(Sparsify::kept_rows(16, 64).len(), 16);
    let (h, w) = (8, 100);
    let mut mask = vec![1.0; h * w];
    Sparsify::Lines(2).apply(&mut mask, h, w, &mut Rng::new(1));
    assert_eq!(mask.iter().sum::<f32>(), 200.0);
    assert_eq!(mask[0], 1.0);
    assert_eq!(mask[w], 0.0);
    let mut mask = vec![1.0; h * w];
    mask[3] = 0.0;
    Sparsify::Fraction(0.1).apply(&mut mask, h, w, &mut Rng::new(1));
    let kept = mask.iter().sum::<f32>();
    assert!((40.0..120.0).contains(&kept), "kept {kept}");
    assert_eq!(mask[3], 0.0, "an unmeasured pixel stays unmeasured");
}

#[test]
fn masks_follow_the_drop_probability_and_the_seed() {
    let p: Vec<f32> = (0..20_000)
        .map(|i| if i % 2 == 0 { 0.9 } else { 0.1 })
        .collect();
    let a = sample_masks(&p, 2, 7);
    assert_eq!(a, sample_masks(&p, 2, 7));
    assert_ne!(a[0], a[1], "samples differ from each other");
    let kept_even = a[0].iter().step_by(2).filter(|k| **k).count() as f32 / 10_000.0;
    let kept_odd = a[0].iter().skip(1).step_by(2).filter(|k| **k).count() as f32 / 10_000.0;
    assert!((kept_even - 0.1).abs() < 0.02, "{kept_even}");
    assert!((kept_odd - 0.9).abs() < 0.02, "{kept_odd}");
}

/// A generated scan of the shipped model on the model grid, as a range image.
fn generated_scan(model: &Model, seed: u64) -> RangeImage {
    let s = sample(
        model,
        &SampleOptions {
            n: 1,
            seed,
            truncation: 0.7,
            grid: Some(model_grid()),
        },
        &Device::flex(),
    )
    .expect("sample")
    .remove(0);
    let mut img = RangeImage::empty(s.angles.clone());
    img.range_m = s.range_m;
    img
}

/// The paper's schedule from w_avg, shortened: both phases of the optimiser run.
fn decoder(w_steps: usize, tune_steps: usize, restore: Option<Sparsify>) -> Decoder {
    let model = Model::shipped(&Device::flex()).expect("shipped model");
    let mut opts = DecodeOptions::new(Quality::Paper);
    opts.schedule = Schedule::reference();
    opts.schedule.w_steps = w_steps;
    opts.schedule.set_tune_steps(tune_steps);
    opts.restore = restore;
    Decoder::new(model, opts)
        .expect("decoder")
        .without_encoder()
}

#[test]
fn a_few_steps_reduce_the_error_and_renders_any_grid() {
    let model = Model::shipped(&Device::flex()).expect("shipped model");
    let scan = generated_scan(&model, 3);
    let start = decoder(0, 0, None).decode(&scan, 1).expect("decode");
    let d = decoder(6, 6, None);
    let tuned = d.decode(&scan, 1).expect("decode");
    let (e0, e1) = (start.error.unwrap(), tuned.error.unwrap());
    assert!(e1 < e0, "error {e0} -> {e1}");
    assert_eq!(tuned.losses.len(), 12);
    // Same seed, same result; the model-grid outputs are complete.
    let again = d.decode(&scan, 1).expect("decode");
    assert_eq!(again.model, tuned.model);
    assert_eq!(tuned.model.depth_m.len(), 64 * 512);
    assert!(
        tuned
            .model
            .depth_m
            .iter()
            .all(|v| (1.45..=80.0).contains(v))
    );
    assert!(
        tuned
            .model
            .drop_prob
            .iter()
            .all(|p| (0.0..=1.0).contains(p))
    );
    // 2x denser grid: same scene, so its 2x2 means follow the model-grid render.
    let grid = d.model_grid().resized(128, 1024);
    let dense = tuned.render(&d, &grid);
    assert_eq!(dense.depth_m.len(), 128 * 1024);
    let mut close = 0;
    for i in 0..64 {
        for j in 0..512 {
            let m = tuned.model.depth_m[i * 512 + j];
            let pooled = (0..4)
                .map(|k| dense.depth_m[(2 * i + k / 2) * 1024 + 2 * j + k % 2])
                .sum::<f32>()
                / 4.0;
            if ((pooled - m) / m).abs() < 0.2 {
                close += 1;
            }
        }
    }
    assert!(
        close > 64 * 512 * 7 / 10,
        "{close} of {} pixels agree",
        64 * 512
    );
    // Another sensor's grid, not divisible by 16: rendered and resampled; beams far above
    // the KITTI field of view stay empty.
    let vlp = SensorProfile::builtin("vlp32c").unwrap().angle_grid();
    let r = tuned.render(&d, &vlp);
    assert_eq!(r.depth_m.len(), 32 * 1800);
    assert_eq!(r.depth_m[0], 0.0, "+15 deg is outside the model's beams");
    assert!(r.depth_m[20 * 1800] > 0.0, "-3 deg is inside");
}

/// Both qualities start from the encoder's prediction, which is much closer to a generated
/// scene than w_avg, the paper's start (`without_encoder`).
#[test]
fn decoding_starts_from_the_encoder_unless_told_otherwise() {
    let model = Model::shipped(&Device::flex()).expect("shipped model");
    let scan = generated_scan(&model, 5);
    let mut opts = DecodeOptions::new(Quality::Paper);
    opts.schedule.set_tune_steps(0);
    let d = Decoder::new(model, opts).expect("decoder");
    let shipped = TrainedEncoder::shipped(&Device::flex()).expect("shipped encoder");
    let d = d.with_encoder(shipped).expect("same sizes");
    assert_eq!(
        d.source().matches(" + encoder ").count(),
        1,
        "{}",
        d.source()
    );
    let from_encoder = d.decode(&scan, 1).expect("decode");
    let d = d.without_encoder();
    assert!(!d.source().contains("encoder"), "{}", d.source());
    let from_w_avg = d.decode(&scan, 1).expect("decode");
    let (e, a) = (from_encoder.error.unwrap(), from_w_avg.error.unwrap());
    assert!(e < 0.8 * a, "encoder start {e} against w_avg {a}");
}

#[test]
fn restoration_reports_the_error_on_held_out_pixels() {
    let model = Model::shipped(&Device::flex()).expect("shipped model");
    let scan = generated_scan(&model, 4);
    let d = decoder(2, 2, Some(Sparsify::Lines(8)));
    let r = d.decode(&scan, 9).expect("decode");
    let seen_rows: Vec<usize> = (0..64)
        .filter(|i| {
            r.observed_m[i * 512..(i + 1) * 512]
                .iter()
                .any(|v| *v > 0.0)
        })
        .collect();
    assert!(seen_rows.iter().all(|i| i % 8 == 0), "{seen_rows:?}");
    assert!(r.held_out_error.is_some());
    let held = r.held_out_m.iter().filter(|v| **v > 0.0).count();
    let seen = r.observed_m.iter().filter(|v| **v > 0.0).count();
    assert!(held > 5 * seen, "held {held} seen {seen}");
}

#[test]
fn fills_keep_measured_returns_and_complete_with_the_rendering() {
    let model = Model::shipped(&Device::flex()).expect("shipped model");
    let scan = generated_scan(&model, 5);
    for restore in [Sparsify::Lines(8), Sparsify::Fraction(0.1)] {
        let d = decoder(0, 1, Some(restore));
        let r = d.decode(&scan, 3).expect("decode");
        assert_eq!(r.model_output(Fill::Gan), r.model);
        let out = r.model_output(Fill::Guided);
        assert_eq!(out.drop_prob, r.model.drop_prob);
        let interpolated = r.interpolate_restored(Fill::Guided, &SurfaceRule::default());
        let mut filled = 0;
        for (k, (d, i)) in out.depth_m.iter().zip(&interpolated).enumerate() {
            if r.observed_m[k] > 0.0 {
                assert_eq!(d.to_bits(), r.observed_m[k].to_bits(), "{k}");
            } else if *i > 0.0 {
                assert_eq!(d, i);
                filled += 1;
            } else {
                assert_eq!(*d, r.model.depth_m[k], "completed by x_d");
            }
        }
        assert!(filled > 10_000, "{restore:?}: {filled} pixels interpolated");
        // A 2x grid: interpolated from the restored observation, x_d where it does not reach.
        let grid = d.prepare(&d.model_grid().resized(128, 1024));
        let gan = r.render_output(&grid, Fill::Gan);
        assert_eq!(gan, r.render_prepared(&grid));
        let guided = r.render_output(&grid, Fill::Guided);
        let changed = (0..gan.depth_m.len())
            .filter(|&k| guided.depth_m[k] != gan.depth_m[k])
            .count();
        assert!(changed > 128 * 1024 / 2, "{changed}");
        assert!(guided.depth_m.iter().all(|v| *v > 0.0));
    }
}

/// Without restoration, `depth` is the completed scan: every measured return exactly, a
/// dropped ray near returns filled from them, and x_d deep inside a large hole (`guided`);
/// the default then moves dropped rays along their rays, and only them.
#[test]
fn depth_keeps_every_return_and_fills_dropped_rays_by_reach() {
    let model = Model::shipped(&Device::flex()).expect("shipped model");
    let mut scan = generated_scan(&model, 6);
    // A 20 x 40 hole: its middle lies 10 steps from any return.
    for i in 20..40 {
        for j in 200..240 {
            scan.range_m[i * 512 + j] = 0.0;
        }
    }
    let r = decoder(0, 1, None).decode(&scan, 4).expect("decode");
    let out = r.model_output(Fill::Guided);
    assert_eq!(r.model_output(Fill::Gan), r.model, "gan: x_d everywhere");
    let learned = r.model_output(Fill::DEFAULT);
    let mut moved = 0;
    for k in 0..out.depth_m.len() {
        let (a, b) = (learned.depth_m[k], out.depth_m[k]);
        if r.observed_m[k] > 0.0 || b == 0.0 {
            assert_eq!(a.to_bits(), b.to_bits(), "{k}: measured or empty");
        } else {
            assert!(
                (a / b).ln().abs() <= super::row_fill::MAX_MOVE + 1e-4,
                "{k}: {a} {b}"
            );
            moved += usize::from(a != b);
        }
    }
    assert!(moved >= 20 * 40 / 2, "{moved} dropped rays moved");
    let distance = crate::lidar::holes::distance_to_returns(&r.observed_m, 64, 512);
    let (mut filled, mut rendered) = (0, 0);
    for (k, &steps) in distance.iter().enumerate() {
        if r.observed_m[k] > 0.0 {
            assert_eq!(out.depth_m[k].to_bits(), r.observed_m[k].to_bits(), "{k}");
        } else if steps > super::hole_fill::COMPLETION_REACH {
            assert_eq!(out.depth_m[k], r.model.depth_m[k], "{k}: x_d beyond reach");
            rendered += 1;
        } else if out.depth_m[k] != r.model.depth_m[k] {
            filled += 1;
        }
    }
    assert!(rendered >= 14 * 34, "{rendered} pixels of x_d");
    assert!(
        filled >= 20 * 40 - 14 * 34 - 50,
        "{filled} pixels filled from returns"
    );
}

#[test]
fn an_empty_scan_is_a_clear_error() {
    let d = decoder(1, 1, None);
    let empty = RangeImage::empty(model_grid());
    let e = d.decode(&empty, 1).unwrap_err().to_string();
    assert!(e.contains("nothing to decode"), "{e}");
}

/// The held-out real scans, if the shared data folder is here.
fn real_lidar() -> Option<std::path::PathBuf> {
    let found = ["../shared/real_lidar", "/work/shared/real_lidar"]
        .iter()
        .map(std::path::PathBuf::from)
        .find(|p| p.exists());
    if found.is_none() {
        eprintln!("skipping: no ../shared/real_lidar folder with held-out KITTI scans");
    }
    found
}

#[test]
fn fast_decoding_of_a_held_out_kitti_scan_improves_on_the_encoder() {
    let Some(root) = real_lidar() else { return };
    let file = crate::model::data::kitti_heldout_files(&root).expect("held-out files")[0].clone();
    let scan = crate::lidar::kitti::read_bin(&file).expect("read");
    // The scan's own 2048-column projection: decode resamples it to the model grid.
    let image = crate::lidar::project(
        &scan,
        &SensorProfile::kitti_hdl64e(),
        crate::lidar::Strategy::Auto,
    )
    .expect("project");
    let model = || Model::shipped(&Device::flex()).expect("shipped model");
    let mut opts = DecodeOptions::new(Quality::Fast);
    opts.schedule.set_tune_steps(0);
    let encoder_only = Decoder::new(model(), opts.clone()).expect("decoder");
    opts.schedule.set_tune_steps(6);
    let refined = Decoder::new(model(), opts).expect("decoder");
    let a = encoder_only.decode(&image, 1).expect("decode");
    let b = refined.decode(&image, 1).expect("decode");
    let (ea, eb) = (a.error.unwrap(), b.error.unwrap());
    assert!(eb < ea, "{}: error {ea} -> {eb}", file.display());
    let measured = a.observed_m.iter().filter(|d| **d > 0.0).count();
    assert!(
        measured > 20_000,
        "{measured} measured pixels on the model grid"
    );
}

#[test]
fn a_sparse_dense_grid_observation_keeps_every_return_on_the_model_grid() {
    // A 64 x 2048 scan with a return in every 4th column only (KITTI subsampled like
    // semantickitti_mini): each return must land on the 64 x 512 model grid.
    let grid = model_grid();
    let dense = SensorProfile::kitti_hdl64e().angle_grid();
    let mut img = RangeImage::empty(dense);
    for i in 0..64 {
        for j in (1..2048).step_by(4) {
            img.range_m[i * 2048 + j] = 10.0 + (i % 3) as f32;
        }
    }
    let out = reproject(&img, &grid);
    let filled = out.iter().filter(|d| **d > 0.0).count();
    assert_eq!(filled, 64 * 512);
    // Row i of the source stays row i; its range comes along.
    assert_eq!(out[5 * 512 + 100], 12.0);
    // A direction far above the beams is not forced onto the top row.
    let mut high = RangeImage::empty(AngleGrid::regular_columns(1, 4, |_| 0.3));
    high.range_m[0] = 5.0;
    assert!(reproject(&high, &grid).iter().all(|d| *d == 0.0));
}
