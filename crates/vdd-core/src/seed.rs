//! Seeding: one `u64` seed fans out into independent ChaCha streams, one per purpose.
//!
//! Every random draw in the workspace comes from a [`Seeds::stream`]: the same seed and
//! purpose give the same numbers on every platform, and two purposes never share a stream,
//! so adding draws for one purpose (say, more evaluation rollouts) never shifts another
//! (say, network initialisation).

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::hash::fnv1a;

/// The random number generator used everywhere in the workspace.
pub type Rng = ChaCha8Rng;

/// A root seed from which independent, named random streams are derived.
///
/// ```
/// use rand::Rng as _;
/// use vdd_core::Seeds;
/// let seeds = Seeds::new(7);
/// let a: f32 = seeds.stream("init").random();
/// let b: f32 = seeds.stream("init").random();
/// let c: f32 = seeds.stream("noise").random();
/// assert_eq!(a, b);
/// assert_ne!(a, c);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Seeds {
    root: u64,
}

impl Seeds {
    /// Creates the seed tree rooted at `root`.
    pub fn new(root: u64) -> Self {
        Self { root }
    }

    /// The root seed.
    pub fn root(&self) -> u64 {
        self.root
    }

    /// The stream for `purpose` (e.g. `"init"`, `"minibatch"`, `"vi-noise"`).
    pub fn stream(&self, purpose: &str) -> Rng {
        self.stream_indexed(purpose, 0)
    }

    /// The `index`-th stream for `purpose` (e.g. one per rollout or per worker).
    pub fn stream_indexed(&self, purpose: &str, index: u64) -> Rng {
        let mut key = [0u8; 32];
        let mut state = self.root ^ fnv1a(purpose.as_bytes());
        for chunk in key.chunks_mut(8) {
            chunk.copy_from_slice(&splitmix64(&mut state).to_le_bytes());
        }
        let mut rng = ChaCha8Rng::from_seed(key);
        rng.set_stream(index);
        rng
    }

    /// A child seed tree, for handing a component its own namespace.
    pub fn child(&self, purpose: &str) -> Seeds {
        let mut state = self.root ^ fnv1a(purpose.as_bytes()).rotate_left(17);
        Seeds::new(splitmix64(&mut state))
    }
}

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Fills `out` with independent standard normal draws.
pub fn fill_standard_normal<R: rand::Rng + ?Sized>(rng: &mut R, out: &mut [f32]) {
    for x in out {
        *x = rng.sample(StandardNormal);
    }
}

/// One standard normal draw.
pub fn standard_normal<R: rand::Rng + ?Sized>(rng: &mut R) -> f32 {
    rng.sample(StandardNormal)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;

    #[test]
    fn streams_are_reproducible_and_distinct() {
        let s = Seeds::new(3);
        let mut a = s.stream_indexed("x", 1);
        let mut b = s.stream_indexed("x", 1);
        let mut c = s.stream_indexed("x", 2);
        let va: Vec<u32> = (0..4).map(|_| a.random()).collect();
        let vb: Vec<u32> = (0..4).map(|_| b.random()).collect();
        let vc: Vec<u32> = (0..4).map(|_| c.random()).collect();
        assert_eq!(va, vb);
        assert_ne!(va, vc);
        assert_ne!(Seeds::new(3).child("a"), Seeds::new(3).child("b"));
    }

    #[test]
    fn normal_draws_have_unit_variance() {
        let mut rng = Seeds::new(0).stream("t");
        let mut xs = vec![0.0f32; 20_000];
        fill_standard_normal(&mut rng, &mut xs);
        let mean = xs.iter().sum::<f32>() / xs.len() as f32;
        let var = xs.iter().map(|x| (x - mean) * (x - mean)).sum::<f32>() / xs.len() as f32;
        assert!(mean.abs() < 0.03, "mean {mean}");
        assert!((var - 1.0).abs() < 0.04, "var {var}");
    }
}
