//! The GAN loop end to end on tiny networks and synthetic scans: training, checkpoints,
//! resume, coarse-to-fine growth and the baselines.

use super::step::{BatchStats, batch_parts, drop_rate_anchor, row_drop_rates};
use super::*;
use std::path::{Path, PathBuf};

use crate::lidar::SensorProfile;
use crate::model::baseline::ConvGeneratorConfig;
use crate::model::discriminator::DiscriminatorConfig;
use crate::model::generator::GeneratorConfig;
use crate::train::growth::Stage;
use crate::train::reconstruct::ReconstructionConfig;
use crate::train::{Backend, load_generator};
use crate::util::rng::Rng;
use crate::util::tensor::tensor_to_vec;
use burn::module::Module;
use burn::module::ParamId;
use burn::module::{ModuleVisitor, Param};

/// Every float parameter of a generator, in visiting order, with its id.
/// A two-block generator and a small discriminator on the synthetic 64 x 64 scans,
/// batch 2, lazy R1 every 2 steps: runs that take well under a second.
fn tiny_run_config() -> TrainConfig {
    let generator = GeneratorConfig::new()
        .with_mapping(
            crate::model::generator::MappingConfig::new()
                .with_d_z(8)
                .with_d_w(8),
        )
        .with_channels(vec![8, 8])
        .with_n_freq(vec![4, 4])
        .with_lh(vec![4, 5])
        .with_lw(vec![3, 4]);
    TrainConfig::new()
        .with_generator(generator)
        .with_discriminator(DiscriminatorConfig::new().with_channels(vec![4, 8, 8]))
        .with_batch_size(2)
        .with_r1_interval(2)
}

/// Every float parameter's values, in module order (ids left out).
fn module_values<M: Module>(m: &M) -> Vec<Vec<f32>> {
    struct Values(Vec<Vec<f32>>);
    impl ModuleVisitor for Values {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.push(tensor_to_vec(param.val()));
        }
    }
    let mut v = Values(Vec::new());
    m.visit(&mut v);
    v.0
}

fn generator_values(g: &AnyGenerator) -> Vec<(ParamId, Vec<f32>)> {
    struct Values(Vec<(ParamId, Vec<f32>)>);
    impl ModuleVisitor for Values {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            self.0.push((param.id, tensor_to_vec(param.val().inner())));
        }
    }
    let mut v = Values(Vec::new());
    g.visit(&mut v);
    v.0
}

#[test]
fn a_batch_splits_in_two_parts_when_it_can() {
    assert_eq!(batch_parts(8), 2);
    assert_eq!(batch_parts(5), 1);
}

#[test]
fn the_drop_rate_anchor_measures_rows_and_pulls_the_keep_logits_to_the_real_rates() {
    let device = Device::flex();
    // Two scans of 2 rows x 4 columns: row 0 drops 3 of 8 pixels, row 1 none.
    let real = tensor_from(
        vec![
            -1.0, 0.2, 0.3, -1.0, 0.1, 0.1, 0.1, 0.1, //
            0.5, -1.0, 0.4, 0.4, 0.2, 0.2, 0.2, 0.2,
        ],
        [2, 1, 2, 4],
        &device,
    );
    assert_eq!(row_drop_rates(&real), vec![3.0 / 8.0, 0.0]);
    // Keep logits that give exactly those rates cost nothing ...
    let logit = |p: f32| (p / (1.0 - p)).ln();
    let exact: Vec<f32> = [1.0 - 3.0 / 8.0, 0.999_999]
        .iter()
        .flat_map(|&k| std::iter::repeat_n(logit(k), 4))
        .collect();
    let exact = tensor_from([exact.clone(), exact].concat(), [2, 1, 2, 4], &device);
    let at_target = drop_rate_anchor(exact, &[3.0 / 8.0, 0.0]).into_scalar::<f32>();
    assert!(at_target < 1e-8, "{at_target}");
    // ... and from even odds the gradient raises row 1's keep logits and lowers row 0's.
    let ad = device.autodiff();
    let even = Tensor::<4>::zeros([2, 1, 2, 4], &ad).require_grad();
    let loss = drop_rate_anchor(even.clone(), &[0.9, 0.0]);
    assert!(loss.clone().inner().into_scalar::<f32>() > 0.1);
    let grads = loss.backward();
    let g = tensor_to_vec(even.grad(&grads).expect("a gradient"));
    assert!(
        g[..4].iter().all(|v| *v > 0.0),
        "row 0 must drop more: {g:?}"
    );
    assert!(
        g[4..8].iter().all(|v| *v < 0.0),
        "row 1 must keep more: {g:?}"
    );
}

#[test]
fn batch_stats_count_drops_and_describe_the_returns_alone() {
    let x = tensor_from(
        vec![-1.0, 0.2, -1.0, 0.6, -1.0, 0.4, 0.2, 0.6],
        [2, 1, 2, 2],
        &Device::flex(),
    );
    let s = BatchStats::of(&x);
    assert!((s.drop - 3.0 / 8.0).abs() < 1e-6, "{s:?}");
    assert!((s.mean - 0.4).abs() < 1e-6, "{s:?}");
    assert!((s.std - (0.032f32).sqrt()).abs() < 1e-5, "{s:?}");
    let m = BatchStats::mean([s, BatchStats::default()].into_iter());
    assert!((m.drop - s.drop / 2.0).abs() < 1e-6 && (m.std - s.std / 2.0).abs() < 1e-6);
}

/// A dataset cache of `n` 64 x 64 images in `dir`: each pixel dropped (-1) with
/// probability 0.2, else `value(pixel index, rng)`.
fn synthetic_cache(
    dir: &Path,
    n: usize,
    seed: u64,
    value: impl Fn(usize, &mut Rng) -> f32,
) -> PathBuf {
    let profile = SensorProfile::kitti_hdl64e().with_columns(64);
    let grid = profile.angle_grid();
    let (h, w) = (grid.height, grid.width);
    let mut rng = Rng::new(seed);
    let images: Vec<f32> = (0..n * h * w)
        .map(|i| {
            if rng.uniform() < 0.2 {
                -1.0
            } else {
                value(i, &mut rng)
            }
        })
        .collect();
    let data = RangeDataset::from_images(profile, grid, images);
    let cache = dir.join("ds.bin");
    data.save(&cache).expect("cache");
    cache
}

/// The baselines run through the same loop (fixed 64x64 output here).
#[test]
fn baselines_train_a_few_steps() {
    for arch in [Arch::Dusty1, Arch::Vanilla] {
        let dir = tempfile::tempdir().expect("tempdir");
        let (h, w) = (64, 64);
        let cache = synthetic_cache(dir.path(), 4, 4, |_, rng| rng.uniform() - 0.5);
        let config = TrainConfig::new()
            .with_arch(arch)
            .with_conv_generator(
                ConvGeneratorConfig::new()
                    .with_d_z(8)
                    .with_channels(vec![8, 8, 8, 8, 8])
                    .with_base_width(4),
            )
            .with_discriminator(DiscriminatorConfig::new().with_channels(vec![4, 8, 8]))
            .with_batch_size(2)
            .with_r1_interval(1)
            .with_total_images(4)
            .with_snapshot_every_images(4);
        let opts = options(dir.path().join("run"), cache, config);
        run(&opts).expect("train");
        let (g, c) = load_generator(&opts.run_dir, &Device::flex()).expect("load");
        assert_eq!(c.arch, arch);
        let AnyGenerator::Conv(g) = g else {
            panic!("conv generator expected")
        };
        let z = Rng::new(1).normal_tensor([1, 8], &Device::flex());
        let channels = if arch == Arch::Vanilla { 1 } else { 2 };
        assert_eq!(g.forward(z).dims(), [1, channels, h, w]);
    }
}

/// The training state in a run's checkpoint.
fn saved_state(run_dir: &Path) -> TrainState {
    let text = std::fs::read_to_string(run_dir.join("checkpoint/state.json")).expect("state");
    serde_json::from_str(&text).expect("json")
}

/// Options of a quiet CPU run in `run_dir` on the dataset cache `cache`.
fn options(run_dir: PathBuf, cache: PathBuf, config: TrainConfig) -> TrainOptions {
    TrainOptions {
        run_dir,
        dataset_cache: cache,
        source: None,
        config,
        backend: Backend::Flex,
        total_images: None,
        max_duration: None,
        progress: false,
        init_from: None,
        regularisation: None,
        sim_share: None,
    }
}

/// A short whole-turn run in `dir/whole` on synthetic scans (cache seed `seed`), the source
/// of the branches on windows: its cache, the loaded scans and its options.
fn whole_turn_source(dir: &Path, seed: u64) -> (PathBuf, RangeDataset, TrainOptions) {
    let cache = synthetic_cache(dir, 8, seed, |i, _| (i % 64) as f32 / 64.0 - 0.5);
    let data = RangeDataset::load(&cache).expect("cache");
    let source = options(
        dir.join("whole"),
        cache.clone(),
        tiny_run_config().with_total_images(4),
    );
    run(&source).expect("train on whole turns");
    (cache, data, source)
}

/// A trained generator branched into a run on windows of the turn: a fresh discriminator
/// of windows (reading their azimuths) learns alone first, then the generator moves; the
/// checkpoint resumes and the snapshots still show whole turns.
#[test]
fn a_trained_generator_goes_on_learning_on_windows() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (cache, data, source) = whole_turn_source(dir.path(), 3);
    let config = tiny_run_config()
        .with_window(Some(16))
        .with_d_warmup_images(4)
        .with_total_images(10);
    let mut opts = TrainOptions {
        init_from: Some(source.run_dir.clone()),
        ..options(dir.path().join("windows"), cache, config)
    };
    std::fs::create_dir_all(&opts.run_dir).expect("mkdir");
    let mut t = Trainer::new(&opts.config, &opts, &data).expect("branch");
    assert!(t.state.fresh_discriminator);
    // D starts from the whole-turn run's: its convolutions are the source's.
    let whole = Level::of(&[], 0, 2, 64, 64);
    let source_d = stage_discriminator(&source.config, 0, &whole, &Device::flex())
        .try_load_file(source.run_dir.join("checkpoint/d.bpk"))
        .expect("source d");
    assert_eq!(module_values(&t.d.blocks), module_values(&source_d.blocks));
    assert_eq!(t.grid.as_ref().map(|g| g.width), Some(16 + 2 * 4));
    let start = generator_values(&t.g);
    t.step(&data).expect("step");
    t.state.images += 2;
    assert_eq!(generator_values(&t.g), start, "G waits while D warms up");
    for _ in 0..2 {
        t.step(&data).expect("step");
        t.state.images += 2;
    }
    assert_ne!(
        generator_values(&t.g),
        start,
        "G learns from the windows' D"
    );
    run(&opts).expect("train on windows");
    opts.total_images = Some(12);
    run(&opts).expect("resume on windows");
    let state = saved_state(&opts.run_dir);
    assert_eq!(state.images, 12);
    let level = Level::of(&[], 0, 2, 64, 64).with_window(Some(16));
    let d = stage_discriminator(&opts.config, 0, &level, &Device::flex());
    d.try_load_file(opts.run_dir.join("checkpoint/d.bpk"))
        .expect("the checkpoint holds a discriminator of windows");
    let snapshot = std::fs::read_dir(opts.run_dir.join("snapshots"))
        .expect("snapshots")
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .max()
        .expect("a snapshot");
    // The PNG header's width (big-endian, bytes 16-19).
    let bytes = std::fs::read(&snapshot).expect("read snapshot");
    let width = u32::from_be_bytes([bytes[16], bytes[17], bytes[18], bytes[19]]);
    assert_eq!(width % 64, 0, "whole turns of 64 columns: {width}");
}

/// Whole-turn steps between the windows: the whole-turn discriminator starts as the
/// whole-turn source's (with its ADA probability), steps on every second step only, is
/// checkpointed with its own step count and resumes; a run without windows refuses them.
#[test]
fn whole_turn_steps_keep_their_own_discriminator_between_the_windows() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (cache, data, source) = whole_turn_source(dir.path(), 5);
    let refused = tiny_run_config().with_whole_every(Some(2)).check();
    assert!(
        format!("{:#}", refused.expect_err("no window")).contains("window"),
        "whole-turn steps need windows"
    );
    let config = tiny_run_config()
        .with_window(Some(16))
        .with_whole_every(Some(2))
        .with_d_warmup_images(0)
        .with_log_every_steps(1)
        .with_total_images(8);
    let mut opts = TrainOptions {
        init_from: Some(source.run_dir.clone()),
        ..options(dir.path().join("windows"), cache, config)
    };
    std::fs::create_dir_all(&opts.run_dir).expect("mkdir");
    let t = Trainer::new(&opts.config, &opts, &data).expect("branch");
    let whole = Level::of(&[], 0, 2, 64, 64);
    let load_whole = |path: PathBuf| {
        stage_discriminator(&source.config, 0, &whole, &Device::flex())
            .try_load_file(path)
            .expect("a discriminator of whole turns")
    };
    let source_d = load_whole(source.run_dir.join("checkpoint/d.bpk"));
    let pass = t.whole.as_ref().expect("a whole-turn pass");
    assert_eq!(
        module_values(&pass.d.blocks),
        module_values(&source_d.blocks)
    );
    assert_eq!(pass.counters.ada_p, saved_state(&source.run_dir).ada_p);
    assert_eq!(pass.grid.as_ref().map(|g| g.width), Some(64));
    drop(t);
    run(&opts).expect("train on windows and whole turns");
    let counters = |dir: &Path| -> whole::DCounters {
        let text = std::fs::read_to_string(dir.join("checkpoint/whole.json")).expect("whole.json");
        serde_json::from_str(&text).expect("json")
    };
    assert_eq!(counters(&opts.run_dir).step, 2, "every second of 4 steps");
    let trained = load_whole(opts.run_dir.join("checkpoint").join(whole::WHOLE_D));
    assert_ne!(
        module_values(&trained.blocks),
        module_values(&source_d.blocks)
    );
    let log = std::fs::read_to_string(opts.run_dir.join("log.jsonl")).expect("log");
    let lines: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).expect("json"))
        .collect();
    let widths: Vec<u64> = lines
        .iter()
        .map(|l| l["grid"][1].as_u64().unwrap_or(0))
        .collect();
    assert_eq!(widths, [16, 64, 16, 64], "windows, then a whole turn");
    assert!(lines[0]["whole_turn"].is_null() && lines[1]["whole_turn"]["loss_d"].is_number());
    opts.total_images = Some(12);
    run(&opts).expect("resume");
    assert_eq!(counters(&opts.run_dir).step, 3, "the count resumes");
}

/// With a share of simulated scans, the discriminator's real batches draw about that share
/// from the run's `sim.bin`; a run that asks for them without the file stops and says so.
#[test]
fn simulated_scans_join_the_real_batches_at_their_share() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = synthetic_cache(dir.path(), 64, 3, |_, _| 0.5);
    let data = RangeDataset::load(&cache).expect("cache");
    let sim_dir = dir.path().join("sim");
    std::fs::create_dir_all(&sim_dir).expect("mkdir");
    let sim_cache = synthetic_cache(&sim_dir, 4, 4, |_, _| -0.25);
    let opts = options(
        dir.path().join("run"),
        cache,
        tiny_run_config().with_batch_size(64).with_sim_share(0.25),
    );
    let err = run(&opts).expect_err("no sim.bin");
    assert!(format!("{err:#}").contains("sim.bin"), "{err:#}");
    std::fs::copy(&sim_cache, opts.run_dir.join(SIMULATED_SCANS)).expect("copy");
    let simulated_in_batch = |share: f32| {
        let config = opts.config.clone().with_sim_share(share);
        let mut t = Trainer::new(&config, &opts, &data).expect("trainer");
        t.sim = simulated_scans(&opts.run_dir, &config, &data).expect("sim");
        let batch = tensor_to_vec(t.real_batch(&data, None, &t.device.clone()));
        let simulated = |image: &[f32]| image.iter().any(|&v| (v + 0.25).abs() < 1e-6);
        batch
            .chunks(64 * 64)
            .filter(|image| simulated(image))
            .count()
    };
    let quarter = simulated_in_batch(0.25);
    assert!((6..=28).contains(&quarter), "{quarter} of 64 simulated");
    assert_eq!(simulated_in_batch(1.0), 64);
    assert_eq!(simulated_in_batch(0.0), 0);
}

/// A few steps on synthetic data, a checkpoint, and a resume that continues the count.
#[test]
fn trains_checkpoints_and_resumes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = synthetic_cache(dir.path(), 8, 3, |i, _| (i % 64) as f32 / 64.0 - 0.5);
    let data = RangeDataset::load(&cache).expect("cache");
    let (h, w) = (data.height, data.width);
    let config = tiny_run_config()
        .with_total_images(8)
        .with_snapshot_every_images(4)
        .with_ada_interval(1)
        .with_ada_speed_images(10.0);
    let mut opts = options(dir.path().join("run"), cache, config);
    run(&opts).expect("train");
    let state = saved_state(&opts.run_dir);
    assert_eq!(state.images, 8);
    let log = std::fs::read_to_string(opts.run_dir.join("log.jsonl")).expect("log");
    assert!(log.lines().count() >= 1 || state.step < 10);
    // Resume with a larger budget: continues from 8, not from 0.
    opts.total_images = Some(12);
    run(&opts).expect("resume");
    let state = saved_state(&opts.run_dir);
    assert_eq!(state.images, 12);
    // A compact checkpoint without the discriminator's optimiser state resumes too.
    std::fs::remove_file(opts.run_dir.join("checkpoint/opt_d.bpk")).expect("rm opt_d");
    opts.total_images = Some(16);
    run(&opts).expect("resume without opt_d");
    assert!(opts.run_dir.join("checkpoint/opt_d.bpk").exists());
    assert!(
        std::fs::read_dir(opts.run_dir.join("snapshots"))
            .expect("snapshots")
            .count()
            >= 2
    );
    let (g, _) = load_generator(&opts.run_dir, &Device::flex()).expect("load ema");
    assert_eq!(g.d_z(), 8);
    // Fine-tuning: a new run initialised from this one starts from its weights, at 0 images.
    let ft = TrainOptions {
        run_dir: dir.path().join("fine-tune"),
        init_from: Some(opts.run_dir.clone()),
        ..opts.clone()
    };
    std::fs::create_dir_all(&ft.run_dir).expect("mkdir");
    let t = Trainer::new(&ft.config, &ft, &data).expect("init from run");
    assert_eq!(t.state.images, 0);
    t.g_ema
        .clone()
        .save_file(ft.run_dir.join("start.bpk"))
        .expect("save");
    assert_eq!(
        std::fs::read(ft.run_dir.join("start.bpk")).expect("read"),
        std::fs::read(opts.run_dir.join("checkpoint/g_ema.bpk")).expect("read"),
        "the fine-tuning run starts from the source's EMA generator"
    );
    assert!(ft.run_dir.join("init_from.json").exists());
    // A discriminator of another shape starts fresh instead of failing to load.
    let other = TrainOptions {
        run_dir: dir.path().join("fine-tune-half-resolution-d"),
        ..ft.clone()
    };
    std::fs::create_dir_all(&other.run_dir).expect("mkdir");
    let half_d = ft.config.clone().with_discriminator(
        DiscriminatorConfig::new()
            .with_stem(2)
            .with_channels(vec![4, 8]),
    );
    Trainer::new(&half_d, &other, &data).expect("init from run with another discriminator");
    // Fine-tuning the ray-drop logit alone: a few steps change the second row of the
    // heads and nothing else of the generator.
    let drop_only = TrainOptions {
        run_dir: dir.path().join("fine-tune-drop-head"),
        ..ft.clone()
    };
    std::fs::create_dir_all(&drop_only.run_dir).expect("mkdir");
    let cfg = ft.config.clone().with_drop_head_only(true).with_lr(0.05);
    let mut t = Trainer::new(&cfg, &drop_only, &data).expect("init from run");
    let before = generator_values(&t.g);
    for _ in 0..3 {
        t.step(&data).expect("step");
    }
    let after = generator_values(&t.g);
    let AnyGenerator::Implicit(generator) = &t.g else {
        panic!("dusty2 run")
    };
    let heads: Vec<ParamId> = generator
        .blocks
        .iter()
        .flat_map(|b| [b.head.weight.id, b.head.bias.id])
        .collect();
    let mut drop_rows_moved = false;
    for ((id, a), (_, b)) in before.iter().zip(&after) {
        if !heads.contains(id) {
            assert_eq!(a, b, "a frozen parameter moved");
            continue;
        }
        // [2, d] or [2]: the first half is the depth row, the second the drop logit.
        let half = a.len() / 2;
        assert_eq!(a[..half], b[..half], "the depth output of a head moved");
        drop_rows_moved |= a[half..] != b[half..];
    }
    assert!(drop_rows_moved, "the drop logit did not train");
    // Sampling from the run, on the training grid and on a 2x denser one.
    let mut sopts = crate::model::sample::SampleOptions {
        n: 3,
        seed: 1,
        truncation: 1.0,
        grid: Some(data.angles.clone()),
    };
    let model =
        crate::model::weights::Model::from_dir(&opts.run_dir, &Device::flex()).expect("model");
    let scans = crate::model::sample::sample(&model, &sopts, &Device::flex()).expect("sample");
    assert_eq!(scans.len(), 3);
    let s = &scans[0];
    assert_eq!(s.range_m.len(), h * w);
    assert!(s.drop_prob.iter().all(|p| (0.0..=1.0).contains(p)));
    assert!(s.range_m.iter().zip(&s.mask).all(|(r, m)| (*r > 0.0) == *m));
    assert_eq!(s.points().len(), s.mask.iter().filter(|m| **m).count());
    sopts.grid = Some(crate::model::layers::AngleGridExt::resample(
        &data.angles,
        2 * h,
        2 * w,
    ));
    let dense = crate::model::sample::sample(&model, &sopts, &Device::flex()).expect("dense");
    assert_eq!(dense[0].range_m.len(), 4 * h * w);
    // SWD of the run against the real set, and the real set against itself (floor 0).
    let cfg = crate::model::metrics::SwdConfig {
        patches_per_image: 16,
        projections: 8,
        ..Default::default()
    };
    let report =
        crate::model::metrics::swd_of_model(&model, &data, 4, &cfg, &Device::flex()).expect("swd");
    assert_eq!(report.per_level.len(), 3);
    assert!(report.mean > 0.0 && report.mean.is_finite());
    let floor = crate::model::metrics::swd_between(&data, &data, &cfg);
    assert!(
        floor.mean < report.mean,
        "floor {} run {}",
        floor.mean,
        report.mean
    );
}

/// A coarse-to-fine, reconstruction-assisted run grows at its stage boundary (a fresh
/// discriminator and encoder of the finer grid), and a run stopped right after the growth
/// and resumed ends with the same weights as one that ran through.
#[test]
fn a_staged_assisted_run_grows_and_resumes_as_if_uninterrupted() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = synthetic_cache(dir.path(), 8, 5, |i, _| (i % 64) as f32 / 64.0 - 0.5);
    let config = tiny_run_config()
        .with_total_images(10)
        .with_snapshot_every_images(100)
        .with_stages(vec![Stage::new(1, 4)])
        // The first stage's discriminator differs from the full grid's.
        .with_stage_discriminators(vec![
            DiscriminatorConfig::new().with_channels(vec![4, 4, 8]),
        ])
        .with_d_warmup_images(2)
        .with_log_every_steps(1)
        .with_reconstruction(Some(ReconstructionConfig::new()));
    let opts = |name: &str, total: u64| TrainOptions {
        total_images: Some(total),
        ..options(dir.path().join(name), cache.clone(), config.clone())
    };
    let state = |o: &TrainOptions| saved_state(&o.run_dir);
    // Weight files carry random parameter ids, so the values are compared.
    let device = Device::flex();
    let weights = |o: &TrainOptions| {
        let ck = o.run_dir.join("checkpoint");
        let (g_ema, _) = load_generator(&o.run_dir, &device).expect("g_ema");
        let d = stage_discriminator(&config, 1, &Level::of(&[], 0, 2, 64, 64), &device)
            .try_load_file(ck.join("d.bpk"))
            .expect("d");
        let level = Level::of(&[], 0, 2, 64, 64);
        let e = InLoopEncoder::new(&ReconstructionConfig::new(), &level, 8, &device)
            .encoder
            .try_load_file(ck.join("e.bpk"))
            .expect("e");
        let state = std::fs::read_to_string(ck.join("state.json")).expect("state");
        (
            module_values(&g_ema),
            module_values(&d),
            module_values(&e),
            state,
        )
    };
    let through = opts("through", 10);
    run(&through).expect("train");
    let stopped = opts("stopped", 4);
    run(&stopped).expect("train to the boundary");
    let at_boundary = state(&stopped);
    assert_eq!((at_boundary.images, at_boundary.stage), (4, 1));
    assert!(stopped.run_dir.join("checkpoint/e.bpk").exists());
    let at_four = weights(&stopped);
    run(&opts("stopped", 10)).expect("resume");
    assert_eq!(state(&through).stage, 1);
    assert!(
        weights(&through) == weights(&stopped),
        "a resumed run ends elsewhere than one that ran through"
    );
    assert!(
        at_four != weights(&stopped),
        "the resumed steps changed nothing"
    );
    // The log shows both grids, and the generator sitting out the warm-up after growing.
    let log = std::fs::read_to_string(through.run_dir.join("log.jsonl")).expect("log");
    let lines: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).expect("json line"))
        .collect();
    let grids: Vec<&serde_json::Value> = lines.iter().map(|l| &l["grid"]).collect();
    assert_eq!(grids[0], &serde_json::json!([32, 32]));
    assert_eq!(grids[lines.len() - 1], &serde_json::json!([64, 64]));
    let grown = lines.iter().position(|l| l["stage"] == 1).expect("grew");
    assert!(
        lines[grown + 1]["loss_g"].is_null(),
        "the generator waits out the warm-up"
    );
    assert!(lines[grown + 2]["loss_g"].is_number());
    assert!(
        lines
            .iter()
            .all(|l| l["reconstruction"].is_number() || l["loss_g"].is_null())
    );
}

/// A run widened mid-way resumes at its image count with the wider generator, its
/// discriminator as it was, and trains on.
#[test]
fn a_widened_run_resumes_where_its_source_stopped() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = synthetic_cache(dir.path(), 8, 3, |i, _| (i % 64) as f32 / 64.0 - 0.5);
    let config = tiny_run_config().with_total_images(4);
    let source = options(dir.path().join("run"), cache, config);
    run(&source).expect("train");
    // A line the source logged after its last checkpoint (a killed run) stays behind.
    let source_log = source.run_dir.join("log.jsonl");
    let mut text = std::fs::read_to_string(&source_log).unwrap_or_default();
    text.push_str("{\"step\":999,\"after_the_checkpoint\":true}\n");
    std::fs::write(&source_log, &text).expect("write log");
    let wide_dir = dir.path().join("wide");
    let widen = || {
        crate::train::widen::widen_run(
            &source.run_dir,
            &wide_dir,
            vec![12, 10],
            vec![4, 6],
            &Device::flex(),
        )
    };
    widen().expect("widen");
    assert!(!wide_dir.join("checkpoint/opt_g.bpk").exists());
    assert_eq!(
        std::fs::read(wide_dir.join("checkpoint/d.bpk")).expect("read"),
        std::fs::read(source.run_dir.join("checkpoint/d.bpk")).expect("read"),
    );
    let wide_log = std::fs::read_to_string(wide_dir.join("log.jsonl")).expect("widened log");
    assert!(!wide_log.contains("after_the_checkpoint"), "{wide_log}");
    assert!(text.starts_with(&wide_log));
    // Widening never writes over a run.
    assert!(widen().is_err());

    let wide = TrainOptions {
        run_dir: wide_dir.clone(),
        total_images: Some(8),
        ..source.clone()
    };
    run(&wide).expect("resume widened");
    let state = saved_state(&wide_dir);
    assert_eq!(state.images, 8);
    let (g, c) = load_generator(&wide_dir, &Device::flex()).expect("load");
    assert_eq!(c.generator.channels, vec![12, 10]);
    let AnyGenerator::Implicit(g) = g else {
        panic!("implicit generator expected")
    };
    assert_eq!(g.blocks[1].conv1.weight.dims(), [10, 10]);
    assert!(wide_dir.join("checkpoint/opt_g.bpk").exists());
}

/// A run resumed with the discriminator's regularisers switched on keeps them in its saved
/// config and state: LeCam's anchors follow D's logits, APA's probability moves with the
/// overfitting heuristic, and every log line says both.
#[test]
fn a_resumed_run_branches_into_the_regularisers() {
    use crate::train::regularise::DRegularisation;
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = synthetic_cache(dir.path(), 8, 5, |i, _| (i % 64) as f32 / 64.0 - 0.5);
    let config = tiny_run_config()
        .with_total_images(4)
        .with_snapshot_every_images(100)
        .with_log_every_steps(1)
        .with_ada_interval(1)
        .with_ada_speed_images(4.0);
    let mut opts = options(dir.path().join("run"), cache, config);
    run(&opts).expect("train");
    let all = DRegularisation::new()
        .with_lecam(0.3)
        .with_diff_augment(true)
        .with_apa(true);
    opts.total_images = Some(16);
    opts.regularisation = Some(all.clone());
    run(&opts).expect("resume with the regularisers");
    let saved = load_config(&opts.run_dir.join("config.json")).expect("config");
    assert_eq!(saved.regularisation, all);
    assert_eq!(saved.total_images, 16);
    let state = saved_state(&opts.run_dir);
    let anchors = state.lecam.expect("LeCam's anchors after its steps");
    assert!(anchors.real.is_finite() && anchors.fake.is_finite());
    let log = std::fs::read_to_string(opts.run_dir.join("log.jsonl")).expect("log");
    let last: serde_json::Value =
        serde_json::from_str(log.lines().last().expect("a line")).expect("json");
    assert_eq!(last["apa_p"].as_f64().map(|p| p as f32), Some(state.apa_p));
    assert!(last["lecam"].is_array());
    assert!(log.lines().take(2).all(|l| l.contains("\"apa_p\":null")));
}

/// A run branched into a self-supervised discriminator trains its decoder beside D: the
/// reconstruction loss is logged on every line and falls as the decoder learns, and the
/// decoder and its Adam state are checkpointed and resumed as they were.
#[test]
fn a_self_supervised_discriminator_learns_to_rebuild_the_real_scans() {
    use crate::train::regularise::DRegularisation;
    let dir = tempfile::tempdir().expect("tempdir");
    let cache = synthetic_cache(dir.path(), 8, 5, |i, _| (i % 64) as f32 / 64.0 - 0.5);
    let config = tiny_run_config()
        .with_total_images(4)
        .with_snapshot_every_images(1000)
        .with_log_every_steps(1);
    let mut opts = options(dir.path().join("run"), cache, config);
    run(&opts).expect("train");
    let ck = opts.run_dir.join("checkpoint");
    assert!(!ck.join("d_decoder.bpk").exists());
    opts.total_images = Some(80);
    opts.regularisation = Some(DRegularisation::new().with_self_supervised(1.0));
    run(&opts).expect("resume with a self-supervised D");
    let decoder = std::fs::read(ck.join("d_decoder.bpk")).expect("the decoder is saved");
    assert!(ck.join("opt_d_decoder.bpk").exists());
    let losses = |log: &str| -> Vec<f64> {
        log.lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .filter_map(|v| v["self_supervised"].as_f64())
            .collect()
    };
    let log = std::fs::read_to_string(opts.run_dir.join("log.jsonl")).expect("log");
    let seen = losses(&log);
    assert_eq!(seen.len(), 38, "one loss per step after the branch");
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(
        mean(&seen[30..]) < 0.5 * mean(&seen[..5]),
        "the reconstruction should fall: {seen:?}"
    );
    // Resumed: the decoder goes on from its checkpoint, not from fresh weights.
    opts.total_images = Some(84);
    opts.regularisation = None;
    run(&opts).expect("resume");
    let log = std::fs::read_to_string(opts.run_dir.join("log.jsonl")).expect("log");
    let resumed = losses(&log);
    assert_eq!(resumed.len(), 40);
    assert!(resumed[38] < 0.5 * mean(&seen[..5]), "{resumed:?}");
    assert_ne!(
        std::fs::read(ck.join("d_decoder.bpk")).expect("read"),
        decoder
    );
}
