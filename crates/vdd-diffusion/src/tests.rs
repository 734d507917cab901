//! Tests of the learned teachers: DSM gradients, the score conversions on trained toy
//! teachers against the exact Gaussian-mixture score, policies in raw space, determinism,
//! save/load and errors.

use faer::{Mat, MatRef};
use vdd_core::{Affine, CoreError, NoiseSchedule, Policy, ScoreModel, Seeds};
use vdd_nn::{Activation, Parameters};

use crate::metrics::mean_cosine_similarity;
use crate::*;

fn tiny_net() -> NetConfig {
    NetConfig {
        hidden_dim: 8,
        num_blocks: 1,
        embed_dim: 4,
        activation: Activation::Tanh,
        max_frequency: 4.0,
    }
}

fn small_net() -> NetConfig {
    NetConfig { hidden_dim: 48, num_blocks: 1, ..Default::default() }
}

/// Two equally weighted isotropic modes at (±1, 0.5), std 0.3, state ignored.
fn two_modes() -> GmmTeacher {
    GmmTeacher::isotropic(&[1.0, 1.0], &[vec![1.0, 0.5], vec![-1.0, 0.5]], 0.3).unwrap()
}

fn gmm_data(teacher: &mut GmmTeacher, n: usize, seed: u64) -> (Mat<f32>, Mat<f32>) {
    let states = Mat::<f32>::zeros(n, 1);
    let actions = teacher.sample(states.as_ref(), &mut Seeds::new(seed).stream("data")).unwrap();
    (states, actions)
}

fn quick_train() -> TrainConfig {
    TrainConfig {
        steps: 1000,
        batch_size: 128,
        adam: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
        warmup_steps: 20,
        ema_decay: 0.99,
        log_every: 100,
        ..Default::default()
    }
}

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-diffusion-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join("teacher.safetensors")
}

/// Central finite differences of a loss over every parameter entry of `net`.
fn check_loss_gradient(
    net: &mut DenoiserNet,
    loss: &mut dyn FnMut(&mut DenoiserNet, bool) -> f32,
) -> f32 {
    net.zero_grad();
    loss(net, true);
    let mut analytic = Vec::new();
    net.visit_params("", &mut |_, p| analytic.extend_from_slice(&p.grad));
    let h = 1e-2f32;
    let mut worst = 0.0f32;
    let mut idx = 0usize;
    let total = analytic.len();
    while idx < total {
        let set = |net: &mut DenoiserNet, delta: f32| {
            let mut k = 0usize;
            net.visit_params_mut("", &mut |_, p| {
                for v in p.value.iter_mut() {
                    if k == idx {
                        *v += delta;
                    }
                    k += 1;
                }
            });
        };
        set(net, h);
        let lp = f64::from(loss(net, false));
        set(net, -2.0 * h);
        let lm = f64::from(loss(net, false));
        set(net, h);
        let numeric = ((lp - lm) / (2.0 * f64::from(h))) as f32;
        let err = (analytic[idx] - numeric).abs() / numeric.abs().max(1e-2);
        worst = worst.max(err);
        idx += 1;
    }
    worst
}

#[test]
fn edm_dsm_loss_gradient_matches_finite_differences() {
    let config = BesoConfig { net: tiny_net(), ..Default::default() };
    let beso = Beso::new(&config, Affine::identity(1), Affine::identity(2), 3).unwrap();
    let mut net = beso.net().clone();
    let a = Mat::from_fn(6, 2, |i, j| (i as f32 - 2.5) * 0.4 + j as f32 * 0.3);
    let s = Mat::from_fn(6, 1, |i, _| i as f32 * 0.2);
    let mut obj = beso.objective_for_tests();
    let mut loss =
        |net: &mut DenoiserNet, backward: bool| obj(net, a.as_ref(), s.as_ref(), 11, backward);
    let err = check_loss_gradient(&mut net, &mut loss);
    assert!(err < 2e-2, "EDM loss gradient error {err}");
}

#[test]
fn ddpm_dsm_loss_gradient_matches_finite_differences() {
    let config = DdpmConfig { net: tiny_net(), ..Default::default() };
    let ddpm = Ddpm::new(&config, Affine::identity(1), Affine::identity(2), 3).unwrap();
    let mut net = ddpm.net().clone();
    let a = Mat::from_fn(6, 2, |i, j| (i as f32 - 2.5) * 0.4 - j as f32 * 0.3);
    let s = Mat::from_fn(6, 1, |i, _| i as f32 * 0.2);
    let mut obj = ddpm.objective_for_tests();
    let mut loss =
        |net: &mut DenoiserNet, backward: bool| obj(net, a.as_ref(), s.as_ref(), 12, backward);
    let err = check_loss_gradient(&mut net, &mut loss);
    assert!(err < 2e-2, "DDPM loss gradient error {err}");
}

/// Mean cosine similarity between a teacher's score and the exact mixture score at matching
/// noise levels, on fresh samples of the mixture.
/// For a VP teacher, the exact score of `x_t = sqrt(ᾱ) a + sqrt(1 − ᾱ) ε` at `x` is
/// `∇ log π_σ(x / sqrt(ᾱ)) / sqrt(ᾱ)` with `σ = sqrt((1 − ᾱ)/ᾱ)`: `x_scale = 1/sqrt(ᾱ)`.
fn score_agreement<T: ScoreModel>(teacher: &mut T, levels: f32, sigma: f32, x_scale: f32) -> f32 {
    let mut gmm = two_modes();
    let (s, a) = gmm_data(&mut gmm, 500, 99);
    let mut learned = Mat::zeros(500, 2);
    let mut exact = Mat::zeros(500, 2);
    teacher.score(a.as_ref(), s.as_ref(), &vec![levels; 500], learned.as_mut()).unwrap();
    let y = Mat::from_fn(500, 2, |i, j| a[(i, j)] * x_scale);
    gmm.score(y.as_ref(), s.as_ref(), &vec![sigma; 500], exact.as_mut()).unwrap();
    mean_cosine_similarity(learned.as_ref(), exact.as_ref())
}

#[test]
fn trained_beso_score_matches_the_exact_mixture_score() {
    let mut gmm = two_modes();
    let (s, a) = gmm_data(&mut gmm, 2000, 1);
    let config = BesoConfig {
        net: small_net(),
        action_normalizer: NormalizerKind::Identity,
        ..Default::default()
    };
    let mut reports = Vec::new();
    let mut beso =
        Beso::train(&config, &quick_train(), s.as_ref(), a.as_ref(), 5, &mut |p| reports.push(p))
            .unwrap();
    assert_eq!(reports.len(), 10);
    assert_eq!(reports.last().unwrap().step, 1000);
    assert!(reports.last().unwrap().loss < reports[0].loss, "{reports:?}");
    let cos = score_agreement(&mut beso, 0.2, 0.2, 1.0);
    assert!(cos > 0.9, "BESO score cosine {cos}");
    // An untrained network does not agree: the check can fail.
    let mut fresh =
        Beso::new(&config, beso.normalizers().0.clone(), beso.normalizers().1.clone(), 5).unwrap();
    assert!(score_agreement(&mut fresh, 0.2, 0.2, 1.0) < 0.8);
}

#[test]
fn trained_ddpm_score_matches_the_exact_mixture_score() {
    let mut gmm = two_modes();
    let (s, a) = gmm_data(&mut gmm, 2000, 2);
    let config = DdpmConfig {
        net: small_net(),
        action_normalizer: NormalizerKind::Identity,
        ..Default::default()
    };
    let mut ddpm =
        Ddpm::train(&config, &quick_train(), s.as_ref(), a.as_ref(), 6, &mut |_| {}).unwrap();
    // The VP score at t is the score of x_t = sqrt(ᾱ) a + sqrt(1 − ᾱ) ε; at small t it is
    // close to the VE score at σ(t).
    let t = ddpm.schedule().time_for_sigma(0.2);
    assert!(t > 0.0 && t < 2.0, "{t}");
    let scale = 1.0 / ddpm.schedule().alpha_bar(t).sqrt();
    let cos = score_agreement(&mut ddpm, t, 0.2, scale);
    assert!(cos > 0.9, "DDPM score cosine {cos}");
}

#[test]
fn policies_act_in_raw_space_and_cover_both_modes() {
    // Raw actions far from the origin and badly scaled: the normalisers must undo this.
    let mut gmm = two_modes();
    let (s, a) = gmm_data(&mut gmm, 2000, 3);
    let raw = Mat::from_fn(2000, 2, |i, j| {
        if j == 0 { 100.0 + 10.0 * a[(i, 0)] } else { -5.0 + 0.1 * a[(i, 1)] }
    });
    let beso_cfg = BesoConfig { net: small_net(), ..Default::default() };
    let ddpm_cfg = DdpmConfig { net: small_net(), ..Default::default() };
    let mut teachers: Vec<DiffusionTeacher> = vec![
        Beso::train(&beso_cfg, &quick_train(), s.as_ref(), raw.as_ref(), 7, &mut |_| {})
            .unwrap()
            .into(),
        Ddpm::train(&ddpm_cfg, &quick_train(), s.as_ref(), raw.as_ref(), 8, &mut |_| {})
            .unwrap()
            .into(),
    ];
    for t in teachers.iter_mut() {
        t.set_steps(8).unwrap();
        t.seed(1);
        let obs = Mat::<f32>::zeros(400, 1);
        let mut act = Mat::zeros(400, 2);
        t.act_batch(obs.as_ref(), act.as_mut()).unwrap();
        let right = (0..400).filter(|&i| act[(i, 0)] > 100.0).count();
        let mean_y = (0..400).map(|i| act[(i, 1)]).sum::<f32>() / 400.0;
        assert!((120..=280).contains(&right), "{:?}: {right} of 400 on the right mode", t.kind());
        assert!((mean_y - (-4.95)).abs() < 0.05, "{:?}: mean y {mean_y}", t.kind());
        let near_modes =
            (0..400).filter(|&i| ((act[(i, 0)] - 100.0).abs() - 10.0).abs() < 9.0).count();
        assert!(near_modes > 360, "{:?}: {near_modes}", t.kind());
        // act_into is one row of act_batch.
        let one = t.act(&[0.0]).unwrap();
        assert!(one.iter().all(|x| x.is_finite()) && one.len() == 2);
        // Same seed, same actions.
        t.seed(1);
        let mut again = Mat::zeros(400, 2);
        t.act_batch(obs.as_ref(), again.as_mut()).unwrap();
        assert_eq!(act, again);
    }
}

#[test]
fn training_is_deterministic_for_a_seed() {
    let (s, a) = gmm_data(&mut two_modes(), 300, 4);
    let train = TrainConfig { steps: 30, batch_size: 64, ..Default::default() };
    let cfg = BesoConfig { net: tiny_net(), ..Default::default() };
    let run = |seed| {
        let mut b = Beso::train(&cfg, &train, s.as_ref(), a.as_ref(), seed, &mut |_| {}).unwrap();
        let mut out = Mat::zeros(300, 2);
        b.denoise(a.as_ref(), &[0.5; 300], s.as_ref(), out.as_mut()).unwrap();
        out
    };
    assert_eq!(run(1), run(1));
    assert_ne!(run(1), run(2));
}

/// `train` is the trainer run to the end: stepping a `TeacherTrainer` by hand gives the same
/// teacher, and its reports come every `log_every` steps and after the last.
#[test]
fn stepping_the_teacher_trainer_is_training() {
    use vdd_core::Trainer;
    let (s, a) = gmm_data(&mut two_modes(), 200, 5);
    let train = TrainConfig { steps: 25, batch_size: 64, log_every: 10, ..Default::default() };
    let cfg = DdpmConfig { net: tiny_net(), ..Default::default() };
    let mut reports = Vec::new();
    let trained =
        Ddpm::train(&cfg, &train, s.as_ref(), a.as_ref(), 3, &mut |p| reports.push(p)).unwrap();
    let mut trainer = TeacherTrainer::new(&cfg, &train, s.as_ref(), a.as_ref(), 3).unwrap();
    assert_eq!((trainer.iteration(), trainer.iterations()), (0, 25));
    let mut stepped = Vec::new();
    while !trainer.done() {
        stepped.extend(trainer.step().unwrap());
    }
    let by_hand: Ddpm = trainer.finish().unwrap();
    let steps = |r: &[TrainProgress]| r.iter().map(|p| (p.step, p.loss, p.lr)).collect::<Vec<_>>();
    assert_eq!(steps(&stepped), steps(&reports));
    assert_eq!(reports.iter().map(|p| p.step).collect::<Vec<_>>(), [10, 20, 25]);
    let weights = |t: &Ddpm| {
        let mut w = Vec::new();
        t.net().visit_params("", &mut |_, p| w.push(p.value.clone()));
        w
    };
    assert_eq!(weights(&by_hand), weights(&trained));
}

#[test]
fn beso_heun_step_and_one_step_sampling_use_the_denoiser() {
    let cfg = BesoConfig { net: tiny_net(), ..Default::default() };
    let mut beso = Beso::new(&cfg, Affine::identity(1), Affine::identity(2), 0).unwrap();
    let x = Mat::from_fn(3, 2, |i, j| i as f32 - j as f32);
    let s = Mat::<f32>::zeros(3, 1);
    // A Heun step to σ = 0 is the denoiser.
    let mut d = Mat::zeros(3, 2);
    beso.denoise(x.as_ref(), &[0.7; 3], s.as_ref(), d.as_mut()).unwrap();
    let mut h = Mat::zeros(3, 2);
    beso.heun_step(x.as_ref(), &[0.7; 3], &[0.0; 3], s.as_ref(), h.as_mut()).unwrap();
    assert!((&d - &h).norm_max() < 1e-6);
    // A Heun step to σ' > 0 matches the generic sampler's by-hand form.
    beso.heun_step(x.as_ref(), &[0.7; 3], &[0.3; 3], s.as_ref(), h.as_mut()).unwrap();
    let x2 = Mat::from_fn(3, 2, |i, j| x[(i, j)] + (0.3 - 0.7) * (x[(i, j)] - d[(i, j)]) / 0.7);
    let mut d2 = Mat::zeros(3, 2);
    beso.denoise(x2.as_ref(), &[0.3; 3], s.as_ref(), d2.as_mut()).unwrap();
    for i in 0..3 {
        for j in 0..2 {
            let k1 = (x[(i, j)] - d[(i, j)]) / 0.7;
            let k2 = (x2[(i, j)] - d2[(i, j)]) / 0.3;
            assert!((h[(i, j)] - (x[(i, j)] - 0.4 * 0.5 * (k1 + k2))).abs() < 1e-5);
        }
    }
    // The score is (D − x)/σ².
    let mut score = Mat::zeros(3, 2);
    beso.score(x.as_ref(), s.as_ref(), &[0.7; 3], score.as_mut()).unwrap();
    assert!(
        (&score - &Mat::from_fn(3, 2, |i, j| (d[(i, j)] - x[(i, j)]) / 0.49)).norm_max() < 1e-4
    );
    // The denoiser form recovers D from the score.
    let form = beso.denoiser_form(0.7).unwrap();
    for i in 0..3 {
        for j in 0..2 {
            assert!((form.denoise(x[(i, j)], score[(i, j)]) - d[(i, j)]).abs() < 1e-4);
        }
    }
    // BESO-1 with Euler: D(σ_max z; σ_max).
    beso.set_sampler(KarrasSampler::Euler, 1).unwrap();
    assert_eq!(beso.sigmas(), &[80.0, 0.0]);
    let mut rng = Seeds::new(3).stream("z");
    let mut out = Mat::zeros(3, 2);
    beso.sample_actions(s.as_ref(), &mut rng, out.as_mut()).unwrap();
    let mut rng = Seeds::new(3).stream("z");
    let z = Mat::from_fn(3, 2, |_, _| 0.0f32);
    let mut z = z;
    for j in 0..2 {
        for i in 0..3 {
            z[(i, j)] = 80.0 * vdd_core::standard_normal(&mut rng);
        }
    }
    beso.denoise(z.as_ref(), &[80.0; 3], s.as_ref(), d.as_mut()).unwrap();
    assert!((&out - &d).norm_max() < 1e-5);
}

#[test]
fn ddpm_conversions_and_one_step() {
    let cfg = DdpmConfig { net: tiny_net(), ..Default::default() };
    let mut ddpm = Ddpm::new(&cfg, Affine::identity(1), Affine::identity(2), 0).unwrap();
    let x = Mat::from_fn(3, 2, |i, j| 0.5 * i as f32 - j as f32);
    let s = Mat::<f32>::zeros(3, 1);
    let t = [0.4f32, 3.0, 16.0];
    let mut eps = Mat::zeros(3, 2);
    ddpm.predict_noise(x.as_ref(), &t, s.as_ref(), eps.as_mut()).unwrap();
    let mut score = Mat::zeros(3, 2);
    ddpm.score(x.as_ref(), s.as_ref(), &t, score.as_mut()).unwrap();
    let sched = ddpm.schedule().clone();
    for i in 0..3 {
        let k = (1.0 - sched.alpha_bar(t[i])).sqrt();
        for j in 0..2 {
            assert!((score[(i, j)] + eps[(i, j)] / k).abs() < 1e-4 * (1.0 + score[(i, j)].abs()));
        }
    }
    // A DDIM step to t = 0 is the clean-action prediction.
    let mut x0 = Mat::zeros(3, 2);
    ddpm.ddim_step(x.as_ref(), &t, &[0.0; 3], s.as_ref(), x0.as_mut()).unwrap();
    for i in 0..3 {
        let ab = sched.alpha_bar(t[i]);
        for j in 0..2 {
            let expect = (x[(i, j)] - (1.0 - ab).sqrt() * eps[(i, j)]) / ab.sqrt();
            assert!(
                (x0[(i, j)] - expect).abs() < 1e-3 * (1.0 + expect.abs()),
                "{} vs {expect}",
                x0[(i, j)]
            );
        }
    }
    // The denoiser form recovers x̂₀ from the score.
    for i in 0..3 {
        let form = ddpm.denoiser_form(t[i]).unwrap();
        for j in 0..2 {
            let d = form.denoise(x[(i, j)], score[(i, j)]);
            assert!((d - x0[(i, j)]).abs() < 1e-3 * (1.0 + d.abs()), "{d} vs {}", x0[(i, j)]);
        }
    }
    // DDPM-1 without clipping = x0 prediction from x_N = z.
    let cfg1 =
        DdpmConfig { clip_denoised: None, sampling_steps: 1, sampler: VpSampler::Ddim, ..cfg };
    let mut one = Ddpm::new(&cfg1, Affine::identity(1), Affine::identity(2), 0).unwrap();
    let mut rng = Seeds::new(9).stream("z");
    let mut out = Mat::zeros(3, 2);
    one.sample_actions(s.as_ref(), &mut rng, out.as_mut()).unwrap();
    let mut rng = Seeds::new(9).stream("z");
    let mut z = Mat::zeros(3, 2);
    for j in 0..2 {
        for i in 0..3 {
            z[(i, j)] = vdd_core::standard_normal(&mut rng);
        }
    }
    one.ddim_step(z.as_ref(), &[16.0; 3], &[0.0; 3], s.as_ref(), x0.as_mut()).unwrap();
    assert!((&out - &x0).norm_max() < 1e-3 * (1.0 + x0.norm_max()));
}

/// `vdd_core::ClampedDenoiser` over both learned teachers: a box wide enough leaves the score
/// bit for bit, a unit box puts every denoised estimate in it and pulls far points back.
#[test]
fn clamped_denoisers_of_both_teachers_stay_in_their_box() {
    let (sn, an) = (Affine::identity(1), Affine::identity(2));
    let b = BesoConfig { net: tiny_net(), ..Default::default() };
    let d = DdpmConfig { net: tiny_net(), ..Default::default() };
    let teachers: Vec<DiffusionTeacher> = vec![
        Beso::new(&b, sn.clone(), an.clone(), 3).unwrap().into(),
        Ddpm::new(&d, sn, an, 3).unwrap().into(),
    ];
    for teacher in teachers {
        let level = if teacher.kind() == TeacherKind::Beso { 0.3 } else { 2.0 };
        let actions = faer::mat![[0.1f32, -0.2], [30.0, -40.0], [0.0, 0.0]];
        let states = Mat::<f32>::zeros(3, 1);
        let levels = [level; 3];
        let mut raw = Mat::<f32>::zeros(3, 2);
        teacher.clone().score(actions.as_ref(), states.as_ref(), &levels, raw.as_mut()).unwrap();
        let mut wide =
            vdd_core::ClampedDenoiser::new(teacher.clone(), vec![-1e6; 2], vec![1e6; 2]).unwrap();
        let mut out = Mat::<f32>::zeros(3, 2);
        wide.score(actions.as_ref(), states.as_ref(), &levels, out.as_mut()).unwrap();
        assert_eq!(out, raw);
        let form = teacher.denoiser_form(level).unwrap();
        let mut unit =
            vdd_core::ClampedDenoiser::new(teacher, vec![-1.0; 2], vec![1.0; 2]).unwrap();
        unit.score(actions.as_ref(), states.as_ref(), &levels, out.as_mut()).unwrap();
        for i in 0..3 {
            for j in 0..2 {
                let d = form.denoise(actions[(i, j)], out[(i, j)]);
                assert!((-1.0 - 1e-3..=1.0 + 1e-3).contains(&d), "row {i}: D = {d}");
            }
        }
        assert!(out[(1, 0)] < 0.0 && out[(1, 1)] > 0.0, "far points are pulled back: {out:?}");
    }
}

#[test]
fn noise_levels_are_drawn_onto_valid_levels() {
    let mut rng = Seeds::new(0).stream("levels");
    let ddpm = Ddpm::new(
        &DdpmConfig { net: tiny_net(), ..Default::default() },
        Affine::identity(1),
        Affine::identity(1),
        0,
    )
    .unwrap();
    let mut out = [0.0f32; 200];
    ddpm.draw_noise_levels(
        &NoiseSchedule::Uniform { min: 0.0, max: 40.0 },
        0.0,
        &mut rng,
        &mut out,
    );
    assert!(out.iter().all(|&t| (MIN_TIME..=16.0).contains(&t)));
    assert!(out.iter().any(|&t| t.fract() != 0.0), "continuous times stay continuous");
    let discrete = Ddpm::new(
        &DdpmConfig {
            net: tiny_net(),
            time_sampling: TimeSampling::Discrete,
            ..Default::default()
        },
        Affine::identity(1),
        Affine::identity(1),
        0,
    )
    .unwrap();
    discrete.draw_noise_levels(
        &NoiseSchedule::Uniform { min: 0.0, max: 4.0 },
        0.0,
        &mut rng,
        &mut out,
    );
    assert!(out.iter().all(|&t| t.fract() == 0.0 && (1.0..=4.0).contains(&t)), "{out:?}");
    let beso = Beso::new(
        &BesoConfig { net: tiny_net(), ..Default::default() },
        Affine::identity(1),
        Affine::identity(1),
        0,
    )
    .unwrap();
    beso.draw_noise_levels(&NoiseSchedule::Uniform { min: 0.0, max: 0.1 }, 0.0, &mut rng, &mut out);
    assert!(out.iter().all(|&s| (0.002..=0.1).contains(&s)));
    assert_eq!(ddpm.noise_convention(), vdd_core::NoiseConvention::Time);
    assert_eq!(beso.noise_convention(), vdd_core::NoiseConvention::Sigma);
    // The trained ranges are stated, and the teacher enum passes them on.
    assert_eq!(ddpm.noise_range(), Some((MIN_TIME, 16.0)));
    assert_eq!(discrete.noise_range(), Some((1.0, 16.0)));
    assert_eq!(beso.noise_range(), Some((0.002, 80.0)));
    assert_eq!(crate::DiffusionTeacher::from(beso).noise_range(), Some((0.002, 80.0)));
    assert_eq!(crate::DiffusionTeacher::from(ddpm).noise_range(), Some((MIN_TIME, 16.0)));
}

#[test]
fn training_sigma_distributions_stay_in_range_and_have_their_medians() {
    let mut rng = Seeds::new(1).stream("sigma");
    for (dist, median) in [
        (SigmaDistribution::LogLogistic { loc: 0.5f32.ln(), scale: 0.5 }, 0.5f32),
        (SigmaDistribution::LogNormal { mean: -1.2, std: 1.2 }, (-1.2f32).exp()),
    ] {
        let mut v: Vec<f32> = (0..4001).map(|_| dist.draw(0.002, 80.0, &mut rng)).collect();
        assert!(v.iter().all(|s| (0.002..=80.0).contains(s)));
        v.sort_by(f32::total_cmp);
        assert!((v[2000] / median - 1.0).abs() < 0.08, "{dist:?}: median {}", v[2000]);
    }
    // Truncation is by inverse CDF for the log-logistic: a narrow range is filled evenly.
    let d = SigmaDistribution::LogLogistic { loc: 0.0, scale: 0.5 };
    let v: Vec<f32> = (0..1000).map(|_| d.draw(0.1, 0.2, &mut rng)).collect();
    assert!(v.iter().all(|s| (0.1..=0.2).contains(s)));
    assert!(v.iter().filter(|&&s| s < 0.15).count() > 300);
}

fn assert_same_teacher<T: ScoreModel>(a: &mut T, b: &mut T, level: f32) {
    let x = Mat::from_fn(5, 2, |i, j| i as f32 * 0.3 - j as f32);
    let s = Mat::from_fn(5, 1, |i, _| i as f32);
    let (mut sa, mut sb) = (Mat::zeros(5, 2), Mat::zeros(5, 2));
    a.score(x.as_ref(), s.as_ref(), &[level; 5], sa.as_mut()).unwrap();
    b.score(x.as_ref(), s.as_ref(), &[level; 5], sb.as_mut()).unwrap();
    assert_eq!(sa, sb);
}

#[test]
fn save_load_round_trips_and_reports_clear_errors() {
    let s = Mat::from_fn(64, 1, |i, _| 3.0 + i as f32);
    let a = Mat::from_fn(64, 2, |i, j| (i * (j + 1)) as f32 * 0.1 - 2.0);
    let train = TrainConfig { steps: 5, batch_size: 16, ..Default::default() };
    let beso_cfg = BesoConfig {
        net: tiny_net(),
        sampler: KarrasSampler::Heun,
        sampling_steps: 3,
        ..Default::default()
    };
    let mut beso = Beso::train(&beso_cfg, &train, s.as_ref(), a.as_ref(), 0, &mut |_| {}).unwrap();
    let path = tmp("beso");
    beso.save(&path).unwrap();
    let mut back = Beso::load(&path, 0).unwrap();
    assert_eq!(back.config(), beso.config());
    assert_eq!(back.normalizers(), beso.normalizers());
    assert_eq!(back.train_config(), Some(&train));
    assert_same_teacher(&mut beso, &mut back, 0.3);
    assert_eq!(beso.act(&[5.0]).unwrap(), back.act(&[5.0]).unwrap());

    let ddpm_cfg = DdpmConfig {
        net: tiny_net(),
        sampler: VpSampler::Ddim,
        sampling_steps: 4,
        ..Default::default()
    };
    let mut ddpm = Ddpm::train(&ddpm_cfg, &train, s.as_ref(), a.as_ref(), 0, &mut |_| {}).unwrap();
    let dpath = tmp("ddpm");
    ddpm.save(&dpath).unwrap();
    let mut dback = Ddpm::load(&dpath, 0).unwrap();
    assert_eq!(dback.config(), ddpm.config());
    assert_eq!(dback.normalizers(), ddpm.normalizers());
    assert_same_teacher(&mut ddpm, &mut dback, 2.0);
    assert_eq!(DiffusionTeacher::load(&dpath, 0).unwrap().kind(), TeacherKind::Ddpm);

    // Wrong kind, missing metadata, missing file, truncated file.
    assert!(matches!(Ddpm::load(&path, 0), Err(DiffusionError::Format { .. })));
    assert!(matches!(Beso::load(&dpath, 0), Err(DiffusionError::Format { .. })));
    let bare = tmp("bare");
    vdd_nn::io::save_safetensors(&bare, beso.net(), &Default::default()).unwrap();
    assert!(matches!(Beso::load(&bare, 0), Err(DiffusionError::Format { .. })));
    assert!(matches!(DiffusionTeacher::load(&bare, 0), Err(DiffusionError::Format { .. })));
    // Unreadable metadata keeps the JSON error as its source.
    let bad = tmp("bad-meta");
    let meta = std::collections::BTreeMap::from([
        ("vdd_diffusion.kind".to_owned(), "beso".to_owned()),
        ("vdd_diffusion.version".to_owned(), "1".to_owned()),
        ("vdd_diffusion.config".to_owned(), "{not json".to_owned()),
    ]);
    vdd_nn::io::save_safetensors(&bad, beso.net(), &meta).unwrap();
    let err = Beso::load(&bad, 0).unwrap_err();
    assert!(matches!(err, DiffusionError::BadMetadata { key: "vdd_diffusion.config", .. }));
    let source = std::error::Error::source(&err).unwrap();
    assert!(source.downcast_ref::<serde_json::Error>().is_some(), "{source:?}");
    let missing = path.with_file_name("absent.safetensors");
    assert!(matches!(Beso::load(&missing, 0), Err(DiffusionError::Nn(vdd_nn::NnError::Io { .. }))));
    let bytes = std::fs::read(&path).unwrap();
    let cut = tmp("cut");
    std::fs::write(&cut, &bytes[..bytes.len() - 9]).unwrap();
    assert!(Beso::load(&cut, 0).is_err());
    // Metadata whose config does not match the stored tensors: a larger network than the
    // file holds is refused before it is built, a smaller one by the tensors' shapes.
    let mut meta = vdd_nn::io::read_metadata(&path).unwrap();
    let wider = BesoConfig { net: NetConfig { hidden_dim: 9, ..tiny_net() }, ..beso_cfg.clone() };
    meta.insert("vdd_diffusion.config".into(), serde_json::to_string(&wider).unwrap());
    let bad = tmp("mismatch");
    vdd_nn::io::save_safetensors(&bad, beso.net(), &meta).unwrap();
    let err = Beso::load(&bad, 0).unwrap_err();
    assert!(
        matches!(err, DiffusionError::Nn(vdd_nn::NnError::Format { .. }))
            && err.to_string().contains("parameters"),
        "{err}"
    );
    let narrower = BesoConfig { net: NetConfig { hidden_dim: 7, ..tiny_net() }, ..beso_cfg };
    meta.insert("vdd_diffusion.config".into(), serde_json::to_string(&narrower).unwrap());
    vdd_nn::io::save_safetensors(&bad, beso.net(), &meta).unwrap();
    assert!(matches!(
        Beso::load(&bad, 0),
        Err(DiffusionError::Nn(vdd_nn::NnError::ShapeMismatch { .. }))
    ));
    for p in [path, dpath, bare, cut, bad] {
        let _ = std::fs::remove_dir_all(p.parent().unwrap());
    }
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let cfg = BesoConfig { net: tiny_net(), ..Default::default() };
    let mut beso = Beso::new(&cfg, Affine::identity(1), Affine::identity(2), 0).unwrap();
    let x = Mat::<f32>::zeros(2, 2);
    let s = Mat::<f32>::zeros(2, 1);
    let mut out = Mat::<f32>::zeros(2, 2);
    let e = beso.score(x.as_ref(), Mat::<f32>::zeros(2, 3).as_ref(), &[0.1, 0.1], out.as_mut());
    assert!(matches!(e, Err(CoreError::Shape { .. })));
    assert!(beso.score(x.as_ref(), s.as_ref(), &[0.1], out.as_mut()).is_err());
    assert!(beso.score(x.as_ref(), s.as_ref(), &[0.1, 0.0], out.as_mut()).is_err());
    assert!(beso.score(x.as_ref(), s.as_ref(), &[0.1, f32::NAN], out.as_mut()).is_err());
    let mut nan = x.clone();
    nan[(0, 0)] = f32::INFINITY;
    assert!(matches!(
        beso.score(nan.as_ref(), s.as_ref(), &[0.1, 0.1], out.as_mut()),
        Err(CoreError::NonFinite { .. })
    ));
    assert!(beso.act(&[0.0, 1.0]).is_err());
    assert!(beso.act(&[f32::NAN]).is_err());
    assert!(beso.set_sampler(KarrasSampler::Heun, 0).is_err());
    assert!(
        Beso::new(
            &BesoConfig { sigma_min: 0.0, ..cfg.clone() },
            Affine::identity(1),
            Affine::identity(2),
            0
        )
        .is_err()
    );

    let dcfg = DdpmConfig { net: tiny_net(), ..Default::default() };
    let mut ddpm = Ddpm::new(&dcfg, Affine::identity(1), Affine::identity(2), 0).unwrap();
    assert!(ddpm.score(x.as_ref(), s.as_ref(), &[0.0, 1.0], out.as_mut()).is_err());
    assert!(ddpm.score(x.as_ref(), s.as_ref(), &[1.0, 16.5], out.as_mut()).is_err());
    assert!(
        ddpm.ddim_step(x.as_ref(), &[1.0, 2.0], &[2.0, 1.0], s.as_ref(), out.as_mut()).is_err()
    );
    assert!(ddpm.set_sampler(VpSampler::Ancestral, 17).is_err());
    assert!(
        Ddpm::new(
            &DdpmConfig { num_steps: 0, ..dcfg.clone() },
            Affine::identity(1),
            Affine::identity(2),
            0
        )
        .is_err()
    );
    assert!(
        Ddpm::new(
            &DdpmConfig { clip_denoised: Some(-1.0), ..dcfg.clone() },
            Affine::identity(1),
            Affine::identity(2),
            0
        )
        .is_err()
    );

    let train = TrainConfig { steps: 3, batch_size: 4, ..Default::default() };
    let a = Mat::<f32>::zeros(5, 2);
    let e =
        Ddpm::train(&dcfg, &train, Mat::<f32>::zeros(4, 1).as_ref(), a.as_ref(), 0, &mut |_| {});
    assert!(matches!(e, Err(DiffusionError::Data(_))));
    let e = Beso::train(
        &cfg,
        &train,
        Mat::<f32>::zeros(0, 1).as_ref(),
        Mat::<f32>::zeros(0, 2).as_ref(),
        0,
        &mut |_| {},
    );
    assert!(matches!(e, Err(DiffusionError::Data(_))));
    let mut bad = a.clone();
    bad[(2, 1)] = f32::NAN;
    let e =
        Beso::train(&cfg, &train, Mat::<f32>::zeros(5, 1).as_ref(), bad.as_ref(), 0, &mut |_| {});
    assert!(matches!(e, Err(DiffusionError::Core(CoreError::NonFinite { .. }))));
    let e = Beso::train(
        &cfg,
        &TrainConfig { steps: 0, ..train },
        Mat::<f32>::zeros(5, 1).as_ref(),
        a.as_ref(),
        0,
        &mut |_| {},
    );
    assert!(matches!(e, Err(DiffusionError::Config(_))));
    // A diverging run is reported, not returned.
    let huge = TrainConfig {
        adam: vdd_nn::AdamConfig { lr: 1e30, ..Default::default() },
        grad_clip: None,
        steps: 50,
        ..train
    };
    let data = Mat::from_fn(5, 2, |i, j| (i + j) as f32);
    let e =
        Beso::train(&cfg, &huge, Mat::<f32>::zeros(5, 1).as_ref(), data.as_ref(), 0, &mut |_| {});
    assert!(matches!(e, Err(DiffusionError::Diverged { .. })), "{e:?}");
}

#[allow(dead_code)]
fn _assert_send<T: Send>() {}
#[allow(dead_code)]
fn _teachers_are_send() {
    _assert_send::<Beso>();
    _assert_send::<Ddpm>();
    _assert_send::<DiffusionTeacher>();
}

#[allow(dead_code)]
fn _unused(_: MatRef<'_, f32>) {}

#[test]
fn hostile_teacher_metadata_is_refused_before_work() {
    let cfg = BesoConfig { net: tiny_net(), ..Default::default() };
    let beso = Beso::new(&cfg, Affine::identity(1), Affine::identity(2), 0).unwrap();
    let dir = std::env::temp_dir().join(format!("vdd-diffusion-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("t.safetensors");
    beso.save(&path).unwrap();
    let meta = vdd_nn::io::read_metadata(&path).unwrap();
    let load = |key: &str, edit: &dyn Fn(&mut serde_json::Value)| {
        let mut m = meta.clone();
        let mut v: serde_json::Value = serde_json::from_str(&m[key]).unwrap();
        edit(&mut v);
        m.insert(key.to_owned(), v.to_string());
        vdd_nn::io::save_safetensors(&path, beso.net(), &m).unwrap();
        DiffusionTeacher::load(&path, 0).map(drop).unwrap_err().to_string()
    };
    let config = "vdd_diffusion.config";
    // A sampler that would run for ever, a network far larger than the file, overflows.
    let e = load(config, &|c| c["sampling_steps"] = 1_000_000_000_000u64.into());
    assert!(e.contains("sampling_steps") && e.contains("t.safetensors"), "{e}");
    let e = load(config, &|c| c["net"]["hidden_dim"] = 65536.into());
    assert!(e.contains("parameters"), "{e}");
    let e = load(config, &|c| c["net"]["embed_dim"] = (u64::MAX - 1).into());
    assert!(e.contains("embed_dim"), "{e}");
    let e = load("vdd_diffusion.shape", &|s| s["action_dim"] = u64::MAX.into());
    assert!(e.contains("t.safetensors"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_saved_teacher_keeps_its_deployment_and_acts_on_raw_observations() {
    // States are windows of 2 observations of 1 value; actions chunks of 2 steps of 1 value.
    let s = Mat::from_fn(64, 2, |i, j| (i + j) as f32 * 0.1);
    let a = Mat::from_fn(64, 2, |i, j| (i * (j + 1)) as f32 * 0.05 - 1.0);
    let train = TrainConfig { steps: 5, batch_size: 16, ..Default::default() };
    let cfg = BesoConfig { net: tiny_net(), sampling_steps: 2, ..Default::default() };
    let mut beso = Beso::train(&cfg, &train, s.as_ref(), a.as_ref(), 0, &mut |_| {}).unwrap();
    assert_eq!(beso.deploy_spec(), &vdd_data::DeploySpec::identity());
    let spec = vdd_data::DeploySpec {
        obs_window: 2,
        action_chunk: 2,
        execute_steps: 2,
        ..vdd_data::DeploySpec::identity()
    };
    // A window that does not divide the state is refused, and the spec is kept.
    let odd = vdd_data::DeploySpec { obs_window: 3, ..spec.clone() };
    assert!(matches!(beso.set_deploy_spec(odd), Err(DiffusionError::Deploy(_))));
    beso.set_deploy_spec(spec.clone()).unwrap();
    let path = tmp("deploy");
    beso.save(&path).unwrap();
    let mut policy = DiffusionTeacher::load_policy(&path, 7).unwrap();
    assert_eq!(policy.obs_dim(), 1, "one raw observation per step");
    assert_eq!(policy.action_dim(), 1, "one action per step");
    let mut by_hand = DiffusionTeacher::from(Beso::load(&path, 7).unwrap()).into_policy().unwrap();
    for t in 0..4 {
        let o = [t as f32 * 0.1];
        assert_eq!(policy.act(&o).unwrap(), by_hand.act(&o).unwrap());
    }
    // A spec in the file that does not fit the teacher is an error naming the key.
    let (meta, _) = vdd_nn::io::read_header(&path).unwrap();
    let mut meta = meta.clone();
    meta.insert(
        "deploy_spec".into(),
        serde_json::to_string(&vdd_data::DeploySpec { obs_window: 3, ..spec }).unwrap(),
    );
    let bad = tmp("deploy-bad");
    vdd_nn::io::save_safetensors(&bad, beso.net(), &meta).unwrap();
    let e = DiffusionTeacher::load_policy(&bad, 0).unwrap_err().to_string();
    assert!(e.contains("deploy_spec"), "{e}");
}
