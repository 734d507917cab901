//! Deterministic data parallelism for training steps.
//!
//! A trainer splits each batch into a fixed number of chunks — a setting of its configuration,
//! never the number of threads — computes each chunk on a replica of its network with buffers
//! of its own, and sums the replicas' gradients into the network in chunk order
//! ([`add_grads`]). [`Workers`] runs the chunks: in the calling thread, on a pool of its own,
//! or on the process-wide pool. As the split and the order of the sums are fixed, the results
//! are the same bits for any number of threads; only the number of chunks changes them (the
//! gradient of a batch is summed over fewer rows at a time).
//!
//! ```
//! use vdd_nn::parallel::{Workers, chunk_range};
//! let mut sums = vec![0u64; 3];
//! let data: Vec<u64> = (0..10).collect();
//! for threads in [1, 2, 3] {
//!     let workers = Workers::new(threads).unwrap();
//!     workers.for_each_mut(&mut sums, |c, s| *s = data[chunk_range(data.len(), 3, c)].iter().sum());
//!     assert_eq!(sums, vec![6, 15, 24]); // rows 0..3, 3..6, 6..10
//! }
//! ```

use rayon::prelude::*;

use crate::error::NnError;
use crate::param::Parameters;

/// Largest number of threads of a pool of its own ([`Workers::new`]).
pub const MAX_THREADS: usize = 1024;

/// Where the chunks of a step run.
enum Pool {
    /// One after the other in the calling thread.
    Inline,
    /// On a pool of this many threads, owned by the [`Workers`].
    Own(rayon::ThreadPool),
    /// On the process-wide pool (`RAYON_NUM_THREADS` threads, default one per core), shared
    /// with every other trainer of the process that uses it.
    Global,
}

/// Runs the chunks of a training step, possibly in parallel (see the [module](self)
/// documentation): `threads == 1` in the calling thread, `threads > 1` on a pool of that many
/// threads of its own, `threads == 0` on the process-wide pool (`RAYON_NUM_THREADS` threads,
/// default one per core), which concurrent trainings of one process then share.
pub struct Workers {
    pool: Pool,
}

impl std::fmt::Debug for Workers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Workers").field("threads", &self.threads()).finish()
    }
}

impl Default for Workers {
    /// The process-wide pool (`Workers::new(0)`).
    fn default() -> Self {
        Self { pool: Pool::Global }
    }
}

impl Workers {
    /// Workers with `threads` threads: 1 runs the chunks in the calling thread, more a pool of
    /// that many threads of its own (at most [`MAX_THREADS`]), 0 the process-wide pool.
    pub fn new(threads: usize) -> Result<Self, NnError> {
        let pool = match threads {
            0 => Pool::Global,
            1 => Pool::Inline,
            n if n > MAX_THREADS => {
                return Err(NnError::Config(format!(
                    "threads must be at most {MAX_THREADS}, got {n}"
                )));
            }
            n => Pool::Own(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .thread_name(|i| format!("vdd-worker-{i}"))
                    .build()
                    .map_err(|e| NnError::Config(format!("cannot start {n} threads: {e}")))?,
            ),
        };
        Ok(Self { pool })
    }

    /// Chunks run in the calling thread, one after the other.
    pub fn inline() -> Self {
        Self { pool: Pool::Inline }
    }

    /// Number of threads the chunks may run on.
    pub fn threads(&self) -> usize {
        match &self.pool {
            Pool::Inline => 1,
            Pool::Own(p) => p.current_num_threads(),
            Pool::Global => rayon::current_num_threads(),
        }
    }

    /// Calls `f(c, &mut items[c])` for every item, in parallel where there are threads. Each
    /// call must depend only on its item and on what `f` reads, never on which thread runs it
    /// or in which order the calls happen; then the results are those of a plain loop.
    pub fn for_each_mut<T: Send>(&self, items: &mut [T], f: impl Fn(usize, &mut T) + Sync) {
        if items.len() <= 1 {
            items.iter_mut().enumerate().for_each(|(c, t)| f(c, t));
            return;
        }
        let run = |items: &mut [T]| {
            items.par_iter_mut().with_max_len(1).enumerate().for_each(|(c, t)| f(c, t))
        };
        match &self.pool {
            Pool::Inline => items.iter_mut().enumerate().for_each(|(c, t)| f(c, t)),
            Pool::Own(p) => p.install(|| run(items)),
            // A process-wide pool of one thread: no hand-over to it.
            Pool::Global if rayon::current_num_threads() == 1 => {
                items.iter_mut().enumerate().for_each(|(c, t)| f(c, t))
            }
            Pool::Global => run(items),
        }
    }
}

/// Rows of chunk `c` when `n` rows are split into `chunks` chunks of near-equal size (the
/// first `n % chunks` chunks one row longer), in order.
///
/// # Panics
/// When `chunks` is 0 (the trainers check their chunk counts when configured).
///
/// ```
/// use vdd_nn::parallel::chunk_range;
/// assert_eq!((0..3).map(|c| chunk_range(10, 3, c)).collect::<Vec<_>>(), [0..4, 4..7, 7..10]);
/// ```
pub fn chunk_range(n: usize, chunks: usize, c: usize) -> std::ops::Range<usize> {
    let (q, r) = (n / chunks, n % chunks);
    let start = c * q + c.min(r);
    start..start + q + usize::from(c < r)
}

/// Copies the parameter values of `src` into `dst`, which must have the same architecture
/// (parameters of the same sizes, visited in the same order); `flat` is scratch.
///
/// # Panics
/// When `dst` holds more parameter values than `src` (replicas are clones of one network, so
/// the trainers never meet this).
pub fn copy_values(src: &dyn Parameters, dst: &mut dyn Parameters, flat: &mut Vec<f32>) {
    flat.clear();
    src.visit_params("", &mut |_, p| flat.extend_from_slice(&p.value));
    let mut off = 0;
    dst.visit_params_mut("", &mut |_, p| {
        let n = p.value.len();
        p.value.copy_from_slice(&flat[off..off + n]);
        off += n;
    });
}

/// Adds the gradients of `src` to those of `dst` (same architecture as for [`copy_values`]);
/// `flat` is scratch. Summing chunk replicas into a network whose gradients were zeroed, in
/// chunk order, gives the same bits whatever thread computed each chunk.
///
/// # Panics
/// As [`copy_values`], when `dst` holds more parameter values than `src`.
pub fn add_grads(src: &dyn Parameters, dst: &mut dyn Parameters, flat: &mut Vec<f32>) {
    flat.clear();
    src.visit_params("", &mut |_, p| {
        if p.grad.len() == p.value.len() {
            flat.extend_from_slice(&p.grad);
        } else {
            flat.resize(flat.len() + p.value.len(), 0.0);
        }
    });
    let mut off = 0;
    dst.visit_params_mut("", &mut |_, p| {
        let n = p.value.len();
        if p.grad.len() != n {
            p.zero_grad();
        }
        for (g, s) in p.grad.iter_mut().zip(&flat[off..off + n]) {
            *g += s;
        }
        off += n;
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Activation, Module, ResidualMlp, ResidualMlpConfig};
    use faer::Mat;

    #[test]
    fn chunks_cover_the_rows_in_order() {
        for n in [1, 5, 128, 257] {
            for chunks in 1..=7 {
                let mut next = 0;
                for c in 0..chunks {
                    let r = chunk_range(n, chunks, c);
                    assert_eq!(r.start, next);
                    assert!(r.len() == n / chunks || r.len() == n / chunks + 1);
                    next = r.end;
                }
                assert_eq!(next, n);
            }
        }
    }

    #[test]
    fn too_many_threads_is_an_error() {
        assert!(Workers::new(MAX_THREADS + 1).is_err());
        assert_eq!(Workers::new(1).unwrap().threads(), 1);
        assert_eq!(Workers::new(3).unwrap().threads(), 3);
    }

    /// Chunked gradients on replicas, summed in chunk order, are the same bits for any
    /// number of threads, and close to the gradient of the whole batch.
    #[test]
    fn replica_gradients_do_not_depend_on_the_threads() {
        let cfg = ResidualMlpConfig {
            in_dim: 3,
            hidden_dim: 16,
            num_blocks: 2,
            out_dim: 2,
            activation: Activation::Mish,
            layer_norm: false,
        };
        let mut master = ResidualMlp::new(&cfg, &mut vdd_core::Seeds::new(3).stream("t")).unwrap();
        let n = 37;
        let x = Mat::from_fn(n, 3, |i, j| ((i * 7 + j * 5) % 13) as f32 / 6.5 - 1.0);
        let g = Mat::from_fn(n, 2, |i, j| ((i * 3 + j) % 7) as f32 / 7.0 - 0.5);
        let grads = |threads: usize, chunks: usize, master: &mut ResidualMlp| {
            let workers = Workers::new(threads).unwrap();
            let mut replicas = vec![master.clone(); chunks];
            let mut flat = Vec::new();
            for r in &mut replicas {
                copy_values(&*master, r, &mut flat);
            }
            workers.for_each_mut(&mut replicas, |c, r| {
                r.zero_grad();
                let rows = chunk_range(n, chunks, c);
                r.forward(x.subrows(rows.start, rows.len()));
                r.backward(g.subrows(rows.start, rows.len()));
            });
            master.zero_grad();
            for r in &replicas {
                add_grads(r, master, &mut flat);
            }
            let mut out = Vec::new();
            master.visit_params("", &mut |_, p| out.extend_from_slice(&p.grad));
            out
        };
        let whole = {
            master.zero_grad();
            master.forward(x.as_ref());
            master.backward(g.as_ref());
            let mut out = Vec::new();
            master.visit_params("", &mut |_, p| out.extend_from_slice(&p.grad));
            out
        };
        for chunks in [1, 3, 4] {
            let one = grads(1, chunks, &mut master);
            for threads in [0, 2, 3] {
                assert_eq!(one, grads(threads, chunks, &mut master), "{chunks} chunks");
            }
            for (a, b) in one.iter().zip(&whole) {
                assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "{a} vs {b}");
            }
        }
    }
}
