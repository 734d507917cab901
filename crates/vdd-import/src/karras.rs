//! BESO's σ schedules and samplers (`gc_sampling.py`, adapted from k-diffusion) over a VE
//! grid, with the noise source passed in: a policy draws it from its own stream, a fixture
//! test replays PyTorch's.

use faer::{Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize};
use vdd_diffusion::{KarrasSampler, karras_sigmas};

use crate::beso_error::BesoError;

/// BESO's noise schedules (`get_noise_schedule`), each ending with an appended 0.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SigmaSchedule {
    /// `get_sigmas_karras(n, σ_min, σ_max, ρ)`.
    Karras {
        /// `ρ`.
        rho: f32,
    },
    /// `get_sigmas_exponential`: `exp(linspace(ln σ_max, ln σ_min, n))` (BESO's default).
    Exponential,
    /// `get_sigmas_linear`: `linspace(σ_max, σ_min, n)` (what D3IL's `BesoAgent` uses).
    Linear,
}

/// `torch.linspace(start, end, n)` in `f32`, with PyTorch's CPU kernel's two-sided
/// evaluation (the first half from `start`, the second from `end`).
pub fn torch_linspace(start: f32, end: f32, n: usize) -> Vec<f32> {
    if n == 1 {
        return vec![start];
    }
    let step = (end - start) / (n - 1) as f32;
    let half = n / 2;
    (0..n)
        .map(|i| if i < half { start + step * i as f32 } else { end - step * (n - 1 - i) as f32 })
        .collect()
}

impl SigmaSchedule {
    /// The `n + 1` levels from `σ_max` down to `σ_min`, then 0.
    ///
    /// ```
    /// use vdd_import::SigmaSchedule;
    /// let s = SigmaSchedule::Linear.sigmas(4, 0.1, 1.0).unwrap();
    /// assert_eq!(s.len(), 5);
    /// assert!((s[1] - 0.7).abs() < 1e-6 && s[4] == 0.0);
    /// ```
    pub fn sigmas(self, n: usize, sigma_min: f32, sigma_max: f32) -> Result<Vec<f32>, BesoError> {
        let range = vdd_diffusion::check_sigma_range(sigma_min, sigma_max);
        if n == 0 || n > 100_000 || range.is_err() {
            return Err(BesoError::Core(vdd_core::CoreError::Config(format!(
                "σ schedule needs n > 0 and {} ≤ σ_min < σ_max ≤ {}, got n = {n}, \
                 [{sigma_min}, {sigma_max}]",
                vdd_diffusion::MIN_SIGMA,
                vdd_diffusion::MAX_SIGMA
            ))));
        }
        let mut s = match self {
            SigmaSchedule::Karras { rho } => {
                return Ok(karras_sigmas(n, sigma_min, sigma_max, rho)?);
            }
            SigmaSchedule::Exponential => {
                let mut v = torch_linspace(sigma_max.ln(), sigma_min.ln(), n);
                v.iter_mut().for_each(|x| *x = x.exp());
                v
            }
            SigmaSchedule::Linear => torch_linspace(sigma_max, sigma_min, n),
        };
        s.push(0.0);
        Ok(s)
    }
}

/// Scratch of [`sample`], reused between calls.
#[derive(Debug, Clone)]
pub struct KarrasBuffers {
    denoised: Mat<f32>,
    x2: Mat<f32>,
    denoised2: Mat<f32>,
    levels: Vec<f32>,
    noise: Vec<f32>,
}

impl Default for KarrasBuffers {
    fn default() -> Self {
        Self {
            denoised: Mat::zeros(0, 0),
            x2: Mat::zeros(0, 0),
            denoised2: Mat::zeros(0, 0),
            levels: Vec::new(),
            noise: Vec::new(),
        }
    }
}

fn ensure(m: &mut Mat<f32>, r: usize, c: usize) {
    if m.nrows() != r || m.ncols() != c {
        *m = Mat::zeros(r, c);
    }
}

/// Runs BESO's `sampler` over `sigmas` from `x` (`n x w`, holding `σ_0 · z` on entry, the
/// sample on exit).
///
/// `denoise(x, σ per row, out)` writes `D(x; σ)`; `noise(buf)` fills `buf` (`n · w` floats,
/// row-major, as `torch.randn_like` on the action tensor) with standard normals, and is called
/// exactly when BESO's sampler draws: once per Euler-ancestral step with `σ_down > 0` (that
/// is, `σ' > 0`). Euler, DDIM and Heun draw nothing (BESO's Euler with `s_churn = 0` draws
/// noise it does not use, and so draws nothing here).
///
/// ```
/// use faer::Mat;
/// use vdd_diffusion::KarrasSampler;
/// use vdd_import::{karras, SigmaSchedule};
/// // Data N(1, 0.5²): D(x; σ) = 1 + 0.25/(0.25 + σ²) (x − 1).
/// let mut d = |x: faer::MatRef<'_, f32>, s: &[f32], mut o: faer::MatMut<'_, f32>| {
///     o[(0, 0)] = 1.0 + 0.25 / (0.25 + s[0] * s[0]) * (x[(0, 0)] - 1.0);
///     Ok(())
/// };
/// let sigmas = SigmaSchedule::Exponential.sigmas(1, 0.1, 1.0).unwrap();
/// let mut x = Mat::from_fn(1, 1, |_, _| 1.0f32);
/// let mut buf = Default::default();
/// karras::sample(&mut d, KarrasSampler::Ddim, &sigmas, x.as_mut(), &mut |_| {}, &mut buf).unwrap();
/// assert!((x[(0, 0)] - 1.0).abs() < 1e-6);
/// ```
pub fn sample<F>(
    denoise: &mut F,
    sampler: KarrasSampler,
    sigmas: &[f32],
    mut x: MatMut<'_, f32>,
    noise: &mut dyn FnMut(&mut [f32]),
    buf: &mut KarrasBuffers,
) -> Result<(), BesoError>
where
    F: FnMut(MatRef<'_, f32>, &[f32], MatMut<'_, f32>) -> Result<(), BesoError> + ?Sized,
{
    let (n, w) = (x.nrows(), x.ncols());
    ensure(&mut buf.denoised, n, w);
    buf.levels.resize(n, 0.0);
    for pair in sigmas.windows(2) {
        let (s, s_next) = (pair[0], pair[1]);
        buf.levels.fill(s);
        denoise(x.as_ref(), &buf.levels, buf.denoised.as_mut())?;
        let den = &buf.denoised;
        match sampler {
            KarrasSampler::Euler => {
                let dt = s_next - s;
                for j in 0..w {
                    for i in 0..n {
                        let d = (x[(i, j)] - den[(i, j)]) / s;
                        x[(i, j)] += d * dt;
                    }
                }
            }
            KarrasSampler::EulerAncestral => {
                let (s2, n2) = (s * s, s_next * s_next);
                let up = s_next.min((n2 * (s2 - n2) / s2).max(0.0).sqrt());
                let down = (n2 - up * up).max(0.0).sqrt();
                let dt = down - s;
                let draw = down > 0.0;
                if draw {
                    buf.noise.resize(n * w, 0.0);
                    noise(&mut buf.noise);
                }
                for i in 0..n {
                    for j in 0..w {
                        let d = (x[(i, j)] - den[(i, j)]) / s;
                        let mut v = x[(i, j)] + d * dt;
                        if draw {
                            v += buf.noise[i * w + j] * up;
                        }
                        x[(i, j)] = v;
                    }
                }
            }
            KarrasSampler::Ddim => {
                // exp(−t') / exp(−t) with t = −ln σ, and −expm1(−h) = 1 − σ'/σ.
                let (t, t_next) = (-s.ln(), -s_next.ln());
                let ratio = (-t_next).exp() / (-t).exp();
                let h = t_next - t;
                let mix = -(-h).exp_m1();
                for j in 0..w {
                    for i in 0..n {
                        x[(i, j)] = ratio * x[(i, j)] + mix * den[(i, j)];
                    }
                }
            }
            KarrasSampler::Heun => {
                let dt = s_next - s;
                ensure(&mut buf.x2, n, w);
                for j in 0..w {
                    for i in 0..n {
                        buf.x2[(i, j)] = x[(i, j)] + (x[(i, j)] - den[(i, j)]) / s * dt;
                    }
                }
                if s_next == 0.0 {
                    x.copy_from(&buf.x2);
                    continue;
                }
                ensure(&mut buf.denoised2, n, w);
                buf.levels.fill(s_next);
                denoise(buf.x2.as_ref(), &buf.levels, buf.denoised2.as_mut())?;
                for j in 0..w {
                    for i in 0..n {
                        let d = (x[(i, j)] - buf.denoised[(i, j)]) / s;
                        let d2 = (buf.x2[(i, j)] - buf.denoised2[(i, j)]) / s_next;
                        x[(i, j)] += (d + d2) / 2.0 * dt;
                    }
                }
            }
        }
    }
    Ok(())
}
