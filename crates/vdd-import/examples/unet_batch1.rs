//! Batch-1 U-Net calls on one input, 100 times: min / median / max CPU time per call, for a
//! normal input and for a subnormal one (issue 34, item 4: "single-observation calls are slow
//! and erratic").
//!
//! The network is LeRobot's `DiffusionConditionalUnet1d` at its default scale with seeded
//! random weights (PyTorch's default initialisation): horizon 16, 2-D actions, 2 observation
//! steps of 4 features, `diffusion_step_embed_dim` 128, kernel 5, 8 groups, FiLM scale.
//!
//! ```text
//! cargo run --release -p vdd-import --example unet_batch1 -- [--dims 64,128,256] [--calls 100]
//! ```
//!
//! Each case first makes 5 untimed calls (the layers size their buffers on the first).
//!
//! `--dims 512,1024,2048` is LeRobot's default `down_dims`; 64,128,256 (the default here) is the
//! scale of the LeRobot teacher of issue 34.

use std::time::Instant;

/// Untimed calls per case before the timed ones.
const WARM_UP: usize = 5;

use faer::Mat;
use rand::{Rng as _, SeedableRng as _};
use rand_chacha::ChaCha8Rng;
use vdd_nn::Parameters as _;
use vdd_torch::{ConditionalUnet1d, Unet1dConfig, UnetLayout};

/// This thread's CPU time in ns (`clock_gettime(CLOCK_THREAD_CPUTIME_ID)` on Linux: what
/// other processes on a loaded machine take is not counted; `None` elsewhere, and the wall time
/// is used).
#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
fn cpu_ns() -> Option<u64> {
    #[repr(C)]
    struct Timespec {
        sec: i64,
        nsec: i64,
    }
    unsafe extern "C" {
        fn clock_gettime(clock: i32, ts: *mut Timespec) -> i32;
    }
    const CLOCK_THREAD_CPUTIME_ID: i32 = 3;
    let mut ts = Timespec { sec: 0, nsec: 0 };
    // SAFETY: `ts` is a valid `struct timespec` (64-bit Linux layout) for the call to fill.
    let rc = unsafe { clock_gettime(CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    (rc == 0).then(|| ts.sec as u64 * 1_000_000_000 + ts.nsec as u64)
}

/// Not measured off Linux: the wall time is used.
#[cfg(not(all(target_os = "linux", target_pointer_width = "64")))]
fn cpu_ns() -> Option<u64> {
    None
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut dims = vec![64, 128, 256];
    let mut calls = 100usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--dims" => {
                let v = args.next().ok_or("--dims needs a value")?;
                dims = v.split(',').map(str::parse).collect::<Result<_, _>>()?;
            }
            "--calls" => calls = args.next().ok_or("--calls needs a value")?.parse()?,
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    let (horizon, action_dim, cond_dim) = (16, 2, 8);
    let config = Unet1dConfig {
        input_dim: action_dim,
        global_cond_dim: cond_dim,
        step_embed_dim: 128,
        down_dims: dims.clone(),
        kernel_size: 5,
        n_groups: 8,
        film_scale: true,
        layout: UnetLayout::Lerobot,
    };
    let mut unet = ConditionalUnet1d::new(config)?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    // PyTorch's default init: U(±1/√fan_in) for weights and biases; GroupNorm 1 / 0.
    unet.visit_params_mut("", &mut |name, p| {
        if name.contains("block.1.") {
            return; // GroupNorm keeps weight 1, bias 0
        }
        let fan_in = if p.shape.len() >= 2 { p.shape[1..].iter().product::<usize>() } else { 64 };
        let bound = 1.0 / (fan_in as f32).sqrt();
        p.value.iter_mut().for_each(|v| *v = rng.random_range(-bound..bound));
    });
    let params: usize = {
        let mut n = 0;
        unet.visit_params("", &mut |_, p| n += p.value.len());
        n
    };
    println!("U-Net down_dims {dims:?}, {params} parameters, batch 1, {calls} calls per input");
    let clock = if cpu_ns().is_some() { "thread CPU time" } else { "wall time" };
    println!("per-call {clock}");
    let x = Mat::from_fn(horizon, action_dim, |_, _| rng.random_range(-1.0f32..1.0));
    let cond = Mat::from_fn(1, cond_dim, |_, _| rng.random_range(-1.0f32..1.0));
    let tiny = f32::MIN_POSITIVE / 64.0; // subnormal
    let xs = Mat::from_fn(horizon, action_dim, |i, j| tiny * (1 + i + j) as f32);
    let cs = Mat::from_fn(1, cond_dim, |_, j| -tiny * (1 + j) as f32);
    let zero_x = Mat::<f32>::zeros(horizon, action_dim);
    let cases: [(&str, &Mat<f32>, &Mat<f32>, f32); 4] = [
        ("normal input, step 50", &x, &cond, 50.0),
        ("normal input, step 0", &x, &cond, 0.0),
        ("zero input, step 0", &zero_x, &cond, 0.0),
        ("subnormal input, step 0", &xs, &cs, 0.0),
    ];
    println!(
        "{:<26} {:>10} {:>10} {:>10} {:>10} {:>8} {:>8} {:>6}",
        "case", "min µs", "median µs", "p90 µs", "max µs", "max/min", "p90/med", "cv"
    );
    // The machine's own variation: a fixed single-threaded GEMM of about the U-Net's work at
    // `--dims 64,128,256` (no allocation, no branches on the data), timed the same way.
    let n = 320;
    let a = Mat::from_fn(n, n, |i, j| ((i * 7 + j * 3) % 13) as f32 / 13.0);
    let mut out = Mat::<f32>::zeros(n, n);
    let mut gemm = || {
        faer::linalg::matmul::matmul(
            out.as_mut(),
            faer::Accum::Replace,
            a.as_ref(),
            a.as_ref(),
            1.0,
            faer::Par::Seq,
        );
        std::hint::black_box(out[(0, 0)]);
    };
    print_row(&format!("baseline: GEMM {n}³"), time_calls(calls, &mut gemm));
    // ... and one pass over as many bytes as the U-Net's parameters (memory-bound, as the
    // U-Net's weights are read once per call at batch 1).
    let bytes = vec![1.0f32; params];
    let mut stream = || {
        std::hint::black_box(bytes.iter().fold(0.0f32, |s, v| s + v));
    };
    print_row("baseline: read the weights", time_calls(calls, &mut stream));
    for (name, x, c, step) in cases {
        // Steady state, as in a control loop: the untimed first calls size the layers' buffers.
        let mut failed = None;
        let times =
            time_calls(calls, &mut || match unet.forward(x.as_ref(), &[step], c.as_ref()) {
                Ok(y) => {
                    std::hint::black_box(y[(0, 0)]);
                }
                Err(e) => failed = Some(e),
            });
        if let Some(e) = failed {
            return Err(e.into());
        }
        let y = unet.forward(x.as_ref(), &[step], c.as_ref())?;
        if !y.col_iter().all(|col| col.iter().all(|v| v.is_finite())) {
            return Err(format!("{name}: non-finite output").into());
        }
        print_row(name, times);
    }
    Ok(())
}

/// `calls` timings of `f` in µs (thread CPU time where available, else wall time), taken
/// after [`WARM_UP`] untimed calls.
fn time_calls(calls: usize, f: &mut dyn FnMut()) -> Vec<f64> {
    for _ in 0..WARM_UP {
        f();
    }
    (0..calls)
        .map(|_| {
            let (t0, c0) = (Instant::now(), cpu_ns());
            f();
            let wall = t0.elapsed().as_secs_f64() * 1e6;
            match (c0, cpu_ns()) {
                (Some(a), Some(b)) => (b - a) as f64 / 1e3,
                _ => wall,
            }
        })
        .collect()
}

/// One line of the table: min, median, p90, max, max/min, p90/median and the coefficient of
/// variation (standard deviation over mean) of `times`.
fn print_row(name: &str, mut times: Vec<f64>) {
    times.sort_by(f64::total_cmp);
    let n = times.len();
    let (lo, med, p90, hi) = (times[0], times[n / 2], times[(n * 9) / 10], times[n - 1]);
    let mean = times.iter().sum::<f64>() / n as f64;
    let var = times.iter().map(|t| (t - mean).powi(2)).sum::<f64>() / n as f64;
    println!(
        "{name:<26} {lo:>10.0} {med:>10.0} {p90:>10.0} {hi:>10.0} {:>8.2} {:>8.2} {:>6.3}",
        hi / lo,
        p90 / med,
        var.sqrt() / mean
    );
}
