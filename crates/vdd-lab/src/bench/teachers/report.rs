//! The text sections of `cargo xtask bench teachers`: the acceptance checks of a DDPM and a
//! BESO teacher on the circle toy ([`circle_section`]) and the rotating toy
//! ([`rotating_section`]), and their sampling latency ([`latency_section`]). Each returns the
//! section's text and, for the checks, the failed checks. [`run`] goes through them in order
//! with teachers the caller trains (or loads) and prints.

use std::fmt::Write as _;

use super::{
    CircleMeasures, CircleReference, RotatingReference, SamplerSetting, Thresholds, ToyTeachers,
    act_batch_latency_us, samples_at, score_cosine,
};
use vdd_diffusion::{DiffusionTeacher, TeacherKind};

use crate::Result;

/// A section of the report: its text (lines ending in `\n`) and the checks that failed.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Section {
    /// The text.
    pub text: String,
    /// One message per failed check, naming the teacher.
    pub failures: Vec<String>,
}

/// Appends one formatted line to a `String`.
macro_rules! push_line {
    ($out:expr, $($arg:tt)*) => {{
        let _ = writeln!($out, $($arg)*);
    }};
}

/// `DDPM` or `BESO`.
pub fn teacher_name(t: &DiffusionTeacher) -> &'static str {
    match t.kind() {
        TeacherKind::Ddpm => "DDPM",
        TeacherKind::Beso => "BESO",
    }
}

fn pass(ok: bool) -> &'static str {
    if ok { "pass" } else { "FAIL" }
}

/// The circle toy's checks of both teachers (trained on 5000 pairs): for each, 10,000 samples
/// with its default sampler against 2000 true samples of `seed` ([`CircleReference`],
/// [`Thresholds::check`]) and the score cosine at `sigma` (and, for information, at `sigma /
/// 2`); then, for information, every other sampler at 16, 8 and 1 steps (2000 samples each).
/// The teachers' samplers are restored.
pub fn circle_section(ts: &mut [DiffusionTeacher; 2], seed: u64, sigma: f32) -> Result<Section> {
    let thresholds = Thresholds::default();
    let reference = CircleReference::new(2000, seed)?;
    let (baseline, exact) = (reference.baseline, &reference.exact);
    let bar = thresholds.mmd2_bar(baseline);
    let mut out = Section::default();
    let text = &mut out.text;
    push_line!(
        text,
        "\n== acceptance: 2-D toy (8 modes on a circle of radius 2, std 0.5; 5000 pairs) =="
    );
    push_line!(
        text,
        "MMD² (RBF, bandwidth 1), two independent true sets of 2000: {baseline:.5}; bar 3x = {bar:.5}"
    );
    push_line!(
        text,
        "{:<6} {:<18} {:>4} {:>10} {:>9} {:>8} {:>22} {:>6}",
        "",
        "sampler, steps",
        "NFE",
        "min share",
        "MMD²",
        "MMD²/true",
        "score cos (σ = 0.1)",
        "result"
    );
    for t in ts.iter_mut() {
        let name = teacher_name(t);
        let default = SamplerSetting::of(t);
        let CircleMeasures { measures, shares, level } =
            reference.measure(t, 10_000, sigma, seed)?;
        let (share, mmd, cos) = (measures.min_mode_share, measures.mmd2, measures.score_cosine);
        let at = match t.kind() {
            TeacherKind::Ddpm => format!("{cos:.4} (t = {level:.3})"),
            TeacherKind::Beso => format!("{cos:.4}"),
        };
        let failed = thresholds.check(&measures, sigma);
        push_line!(
            text,
            "{name:<6} {:<18} {:>4} {share:>10.3} {mmd:>9.5} {:>8.2}x {at:>22} {:>6}",
            default.label(),
            default.nfe(),
            mmd / baseline,
            pass(failed.is_empty())
        );
        out.failures.extend(failed.iter().map(|f| format!("{name}: {f}")));
        let shares: Vec<String> = shares.iter().map(|s| format!("{s:.3}")).collect();
        push_line!(text, "       mode shares: {}", shares.join(" "));
        let half = score_cosine(t, exact, &[0.0], reference.true_b.as_ref(), 0.5 * sigma)?.cosine;
        push_line!(text, "       (info) score cosine at σ = {}: {half:.4}", 0.5 * sigma);
    }
    push_line!(text, "(info) other samplers, 2000 samples each (not part of the acceptance):");
    push_line!(
        text,
        "{:<6} {:<18} {:>4} {:>10} {:>9} {:>9}",
        "",
        "sampler, steps",
        "NFE",
        "min share",
        "MMD²",
        "MMD²/true"
    );
    for t in ts.iter_mut() {
        let name = teacher_name(t);
        for steps in [16usize, 8, 1] {
            for s in SamplerSetting::all(t.kind(), steps) {
                let saved = s.apply(t)?;
                let x = samples_at(t, &[0.0], 2000, seed);
                saved.apply(t)?;
                let (share, _, mmd) = reference.compare(x?.as_ref());
                push_line!(
                    text,
                    "{name:<6} {:<18} {:>4} {share:>10.3} {mmd:>9.5} {:>8.2}x",
                    s.label(),
                    s.nfe(),
                    mmd / baseline
                );
            }
        }
    }
    Ok(out)
}

/// The heading of the rotating toy's section, for `pairs` training pairs.
pub fn rotating_heading(pairs: usize) -> String {
    format!(
        "\n== acceptance: rotating toy (mode k at angle s + 2πk/8, s ~ U[0, 2π); {pairs} pairs) =="
    )
}

/// The rotating toy's checks of both teachers (trained on `rot`'s data): each must put at
/// least [`Thresholds::min_mode_share`] of 2000 samples on every mode at 8 states
/// ([`RotatingReference::check_at`]).
pub fn rotating_section(
    ts: &mut [DiffusionTeacher; 2],
    rot: &mut RotatingReference,
    seed: u64,
) -> Result<Section> {
    let mut out = Section::default();
    let text = &mut out.text;
    push_line!(
        text,
        "min share of 2000 samples over the 8 modes at state s (MMD² to 1000 true samples):"
    );
    push_line!(text, "{:>7} {:>22} {:>22}", "s", "DDPM", "BESO");
    let thresholds = Thresholds::default();
    let mut worst = [f32::INFINITY; 2];
    let mut covered = [0usize; 2];
    for i in 0..8 {
        let s = (i as f32 + 0.5) * std::f32::consts::TAU / 8.0 * 0.999;
        let mut cells = Vec::new();
        for (k, t) in ts.iter_mut().enumerate() {
            let (share, mmd) = rot.check_at(t, s, i, seed)?;
            worst[k] = worst[k].min(share);
            covered[k] += usize::from(thresholds.covers(share));
            cells.push(format!("{share:.3} ({mmd:.4})"));
        }
        push_line!(text, "{s:>7.3} {:>22} {:>22}", cells[0], cells[1]);
    }
    for (k, name) in ["DDPM", "BESO"].iter().enumerate() {
        let ok = covered[k] == 8;
        push_line!(
            text,
            "{name}: all 8 modes (>= 6% each) at {}/8 states, worst share {:.3}: {}",
            covered[k],
            worst[k],
            pass(ok)
        );
        if !ok {
            out.failures.push(format!("{name} rotating: modes covered at {}/8 states", covered[k]));
        }
    }
    Ok(out)
}

/// µs per action of `act_batch` (single thread, [`act_batch_latency_us`] with `min_secs`) at
/// batch 1 and 256, for every sampler of both teachers at 1, 2, 4, 8 and 16 steps and the
/// teacher's default. The teachers end with their default samplers.
pub fn latency_section(ts: &mut [DiffusionTeacher; 2], min_secs: f64) -> Result<String> {
    let mut text = String::new();
    push_line!(
        text,
        "\n== sampling latency: µs per action (act_batch, single thread, best of 5 rounds) =="
    );
    push_line!(
        text,
        "(2-D toy teachers; wall clock on a shared machine: other jobs inflate these figures)"
    );
    let steps = [1usize, 2, 4, 8, 16];
    for batch in [1usize, 256] {
        push_line!(text, "\nbatch {batch}:");
        let head: String = steps.iter().map(|k| format!("{:>9}", format!("{k} st"))).collect();
        push_line!(text, "{:<6} {:<16}{head} {:>16}", "", "sampler", "default");
        for t in ts.iter_mut() {
            let name = teacher_name(t);
            let default = SamplerSetting::of(t);
            for s in SamplerSetting::all(t.kind(), 1) {
                let mut row = String::new();
                for &k in &steps {
                    s.with_steps(k).apply(t)?;
                    let _ = write!(row, "{:>9.1}", act_batch_latency_us(t, batch, min_secs)?);
                }
                let def = if s.name() == default.name() {
                    default.apply(t)?;
                    let us = act_batch_latency_us(t, batch, min_secs)?;
                    format!("{us:.1} ({} st)", default.steps())
                } else {
                    String::new()
                };
                push_line!(text, "{name:<6} {:<16}{row} {def:>16}", s.name());
            }
            default.apply(t)?;
        }
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use vdd_core::Affine;

    use vdd_diffusion::{Beso, Ddpm};

    use super::*;

    /// Untrained toy teachers (8 wide, one block).
    fn untrained() -> [DiffusionTeacher; 2] {
        let toy = ToyTeachers { width: 8, blocks: 1, ..ToyTeachers::toy() };
        let (s, a) = (Affine::identity(1), Affine::identity(2));
        let ddpm = Ddpm::new(&toy.ddpm(), s.clone(), a.clone(), 0).unwrap();
        let beso = Beso::new(&toy.beso(), s, a, 0).unwrap();
        [DiffusionTeacher::Ddpm(ddpm), DiffusionTeacher::Beso(beso)]
    }

    #[test]
    fn untrained_teachers_fail_the_circle_checks_and_keep_their_samplers() {
        let mut ts = untrained();
        let before = ts.each_ref().map(SamplerSetting::of);
        let s = circle_section(&mut ts, 0, 0.1).unwrap();
        assert!(s.failures.iter().any(|f| f.starts_with("DDPM: ")), "{:?}", s.failures);
        assert!(s.failures.iter().any(|f| f.starts_with("BESO: ")), "{:?}", s.failures);
        assert!(s.text.contains("== acceptance: 2-D toy") && s.text.contains("FAIL"), "{}", s.text);
        assert_eq!(ts.each_ref().map(SamplerSetting::of), before);
        let text = latency_section(&mut ts, 1e-4).unwrap();
        let rows = |name: &str| text.lines().filter(|l| l.starts_with(name)).count();
        let samplers = |k| SamplerSetting::all(k, 1).len();
        assert_eq!(rows("DDPM"), 2 * samplers(TeacherKind::Ddpm), "{text}");
        assert_eq!(rows("BESO"), 2 * samplers(TeacherKind::Beso), "{text}");
        assert_eq!(ts.each_ref().map(SamplerSetting::of), before);
    }
}

/// What [`run`] checks and measures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BenchOptions {
    /// Seed of the data, the training and the checks.
    pub seed: u64,
    /// Training steps on the circle toy.
    pub steps: u64,
    /// Training steps on the rotating toy.
    pub rot_steps: u64,
    /// Noise level of the score check (normalised units).
    pub sigma: f32,
    /// Minimum seconds per latency measurement.
    pub min_secs: f64,
    /// Run the acceptance checks.
    pub acceptance: bool,
    /// Measure the latency tables.
    pub latency: bool,
    /// The teachers' settings, for the heading (`train` is the caller's).
    pub toy: ToyTeachers,
}

/// The heading of [`run`]: the teachers' settings and the training steps of `options`.
pub fn heading(options: &BenchOptions) -> String {
    let t = &options.toy;
    format!(
        "toy teachers: residual MLP {} wide, {} blocks; Adam lr {} (warm-up, cosine decay), \
         batch {}; {} training steps (circle), {} (rotating); seed {}\n\
         DDPM: cosine β, N = 16, ε-prediction, log-normal training noise; BESO: EDM \
         preconditioning (σ_data 0.5), Karras σ ∈ [0.002, 80], ρ = 7, log-normal training noise\n",
        t.width, t.blocks, t.lr, t.batch, options.steps, options.rot_steps, options.seed
    )
}

/// `cargo xtask bench teachers`: the [`heading`], the circle toy's checks ([`circle_section`])
/// of the teachers `train` gives for 5000 pairs of the circle toy (`train(task, steps, states,
/// actions)` trains or loads a task's DDPM and BESO teachers, in that order), then the rotating
/// toy's ([`rotating_section`], 20,000 pairs), then the latency tables ([`latency_section`]),
/// as `options` asks. Each section goes to `print` when it is ready; returns the failed checks.
pub fn run<E: From<crate::LabError>>(
    options: &BenchOptions,
    mut train: impl FnMut(
        &str,
        u64,
        &faer::Mat<f32>,
        &faer::Mat<f32>,
    ) -> Result<[DiffusionTeacher; 2], E>,
    mut print: impl FnMut(&str),
) -> Result<Vec<String>, E> {
    let seed = options.seed;
    print(&heading(options));
    let mut rng = vdd_core::Seeds::new(seed).stream("toy-data");
    let (states, actions) = vdd_core::gmm::GmmTeacher::circle_toy_data(5000, &mut rng)
        .map_err(crate::LabError::from)?;
    let mut circle = train("circle", options.steps, &states, &actions)?;
    let mut failures = Vec::new();
    if options.acceptance {
        let s = circle_section(&mut circle, seed, options.sigma)?;
        print(&s.text);
        failures.extend(s.failures);
        let pairs = 20_000;
        let mut rot = RotatingReference::new()?;
        let (states, actions) = rot.data(pairs, seed)?;
        print(&(rotating_heading(pairs) + "\n"));
        let mut ts = train("rotating", options.rot_steps, &states, &actions)?;
        let s = rotating_section(&mut ts, &mut rot, seed)?;
        print(&s.text);
        failures.extend(s.failures);
    }
    if options.latency {
        print(&latency_section(&mut circle, options.min_secs)?);
    }
    Ok(failures)
}
