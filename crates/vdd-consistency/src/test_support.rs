//! Shared pieces of the consistency tests: an exact four-mode teacher
//! ([`vdd_diffusion::GmmTeacher`] through [`ScoreTeacher`]), small data, a finite-difference
//! check of a loss's parameter gradients, and the "one-step samples land on the modes" check.

use faer::{Mat, MatRef};
use rand::Rng as _;
use vdd_core::{Policy, Seeds};
use vdd_diffusion::{GmmTeacher, NetConfig};
use vdd_nn::Parameters;

use crate::config::ConsistencyConfig;
use crate::teacher::{ConsistencyTeacher, ScoreTeacher};
use crate::trainer::Distillation;

/// The four modes (unit circle, 90° apart).
pub const FOUR_MODES: [[f32; 2]; 4] = [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]];

/// Standard deviation of each mode.
pub const MODE_STD: f32 = 0.1;

/// `Σ_k ¼ N(μ_k, 0.1² I)` over [`FOUR_MODES`], state (1-D) ignored.
pub fn four_mode_gmm() -> GmmTeacher {
    let means: Vec<Vec<f32>> = FOUR_MODES.iter().map(|m| m.to_vec()).collect();
    GmmTeacher::isotropic(&[1.0; 4], &means, MODE_STD).expect("valid mixture")
}

/// The exact four-mode teacher with identity normalisers: its denoiser is Tweedie's formula
/// on the mixture's closed-form score.
pub fn four_mode_teacher() -> ScoreTeacher<GmmTeacher> {
    ScoreTeacher::identity(four_mode_gmm()).expect("variance-exploding teacher")
}

/// A network small enough for finite differences.
pub fn tiny_net() -> NetConfig {
    NetConfig { hidden_dim: 6, num_blocks: 1, embed_dim: 4, ..Default::default() }
}

/// `n` actions uniform in `[−1.5, 1.5]²` with a constant 1-D state 0.
pub fn uniform_actions(n: usize, seed: u64) -> (Mat<f32>, Mat<f32>) {
    let mut rng = Seeds::new(seed).stream("data");
    let actions = Mat::from_fn(n, 2, |_, _| rng.random_range(-1.5f32..1.5));
    (Mat::zeros(n, 1), actions)
}

/// Compares the parameter gradient that `loss(core, true)` accumulates into `core.online`
/// with central finite differences of `loss(core, false)` (the drawn batch and target held
/// fixed). Returns the loss, the worst relative error (against `max(|numeric|, 1e-2)`) and
/// the number of entries checked.
pub fn gradient_error<T: ConsistencyTeacher>(
    core: &mut Distillation<T>,
    mut loss: impl FnMut(&mut Distillation<T>, bool) -> f32,
) -> (f32, f64, usize) {
    core.online.zero_grad();
    let loss0 = loss(core, true);
    let mut analytic = Vec::new();
    core.online.visit_params("", &mut |_, p| analytic.push(p.grad.clone()));
    let h = 3e-3f32;
    let (mut worst, mut checked) = (0.0f64, 0);
    for (pi, grads) in analytic.iter().enumerate() {
        for (e, &g) in grads.iter().enumerate() {
            let shift = |core: &mut Distillation<T>, delta: f32| {
                let mut k = 0;
                core.online.visit_params_mut("", &mut |_, p| {
                    if k == pi {
                        p.value[e] += delta;
                    }
                    k += 1;
                });
            };
            shift(core, h);
            let up = f64::from(loss(core, false));
            shift(core, -2.0 * h);
            let down = f64::from(loss(core, false));
            shift(core, h);
            let fd = (up - down) / (2.0 * f64::from(h));
            worst = worst.max((fd - f64::from(g)).abs() / fd.abs().max(1e-2));
            checked += 1;
        }
    }
    (loss0, worst, checked)
}

/// The fraction of rows within `radius` of some mode, and the fraction of rows nearest to
/// each mode.
pub fn near_mode_fraction(samples: MatRef<'_, f32>, radius: f32) -> (f32, [f32; 4]) {
    let n = samples.nrows();
    let (mut near, mut counts) = (0usize, [0usize; 4]);
    for i in 0..n {
        let (mut best, mut arg) = (f32::INFINITY, 0);
        for (k, m) in FOUR_MODES.iter().enumerate() {
            let d = ((samples[(i, 0)] - m[0]).powi(2) + (samples[(i, 1)] - m[1]).powi(2)).sqrt();
            if d < best {
                (best, arg) = (d, k);
            }
        }
        counts[arg] += 1;
        near += usize::from(best <= radius);
    }
    (near as f32 / n as f32, counts.map(|c| c as f32 / n as f32))
}

/// Distils the exact four-mode teacher with `train(config, states, actions)` (which returns
/// the untrained and the trained policy) on 2000 samples of the mixture, and checks that the
/// untrained policy's one-step samples are spread out while the trained one's land within 0.3
/// of a mode (more than half of them) on all four modes (each more than 15%).
pub fn distils_the_modes(
    train: impl FnOnce(
        ConsistencyConfig,
        MatRef<'_, f32>,
        MatRef<'_, f32>,
    ) -> (Box<dyn Policy>, Box<dyn Policy>),
) {
    let mut rng = Seeds::new(5).stream("data");
    let actions = four_mode_gmm().sample(Mat::<f32>::zeros(2000, 1).as_ref(), &mut rng).unwrap();
    let states = Mat::<f32>::zeros(2000, 1);
    let mut config = ConsistencyConfig {
        net: NetConfig { hidden_dim: 32, num_blocks: 1, ..Default::default() },
        num_scales: 10,
        sigma_max: 20.0,
        ..Default::default()
    }
    .with_seed(2);
    config.train.steps = 1000;
    config.train.batch_size = 128;
    config.train.adam.lr = 1e-2;
    config.train.final_lr_factor = 0.05;
    config.train.target_ema_decay = 0.9;
    config.train.ema_decay = 0.9;
    let (mut untrained, mut trained) = train(config, states.as_ref(), actions.as_ref());
    let obs = Mat::<f32>::zeros(1000, 1);
    let mut out = Mat::zeros(1000, 2);
    untrained.act_batch(obs.as_ref(), out.as_mut()).unwrap();
    let (near_untrained, _) = near_mode_fraction(out.as_ref(), 0.3);
    assert!(near_untrained < 0.3, "untrained: {near_untrained}");
    trained.act_batch(obs.as_ref(), out.as_mut()).unwrap();
    let (near, per_mode) = near_mode_fraction(out.as_ref(), 0.3);
    assert!(near > 0.5, "only {near} of the samples within 0.3 of a mode");
    assert!(per_mode.iter().all(|&f| f > 0.15), "mode fractions {per_mode:?}");
}
