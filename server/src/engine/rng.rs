//! A small, seedable, checkpointable random number generator for everything the engine
//! draws (noise, timesteps, batch indices).
//!
//! Why not libtorch's generator: `tch::manual_seed` sets one process-wide generator, so two
//! concurrent requests (or a request and a training job) would perturb each other's streams
//! and "same seed, same samples" would not hold. This generator is owned by its user, and its
//! whole state is one `u64`, so a training checkpoint can store it and a resumed job continues
//! the exact stream.

use std::sync::OnceLock;

use serde::{Deserialize, Serialize};
use tch::{Device, Tensor};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Rng {
    state: u64,
}

/// SplitMix64's increment: the state after k draws is the seed plus k times this, which is
/// what lets [`Rng::fill_normal`] split a long fill among threads.
const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

/// Below this many values a fill stays on the calling thread (starting threads costs more).
const PARALLEL_FILL: usize = 1 << 16;

/// The machine's cores, read once (the standard library re-reads the cgroup limits per call).
fn cores() -> usize {
    static CORES: OnceLock<usize> = OnceLock::new();
    *CORES.get_or_init(|| std::thread::available_parallelism().map_or(1, usize::from))
}

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// SplitMix64 (Steele, Lea, Flood 2014): passes BigCrush, one add and three xor-shift-mults.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(GAMMA);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1) with 53 random bits.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform integer in [0, n) (Lemire's multiply-shift; the bias is below 2^-32 for the
    /// sizes used here).
    pub fn below(&mut self, n: u64) -> u64 {
        ((u128::from(self.next_u64()) * u128::from(n)) >> 64) as u64
    }

    /// Fills `out` with independent standard normal draws (Box-Muller, both outputs used; each
    /// pair, the odd last value too, takes two draws). A long fill is split among the machine's
    /// cores, each part starting its own copy of the stream at that part's position, so the
    /// values and the state afterwards are exactly those of one thread: Algorithm 1's noise
    /// at the paper's maze size (393k values) took about 8 ms on one core, time in which a
    /// GPU would sit idle every step.
    pub fn fill_normal(&mut self, out: &mut [f32]) {
        // Short fills (every sampling step's noise) never ask how many cores there are.
        let threads = if out.len() < 2 * PARALLEL_FILL { 1 } else { cores().min(out.len() / PARALLEL_FILL) };
        self.fill_normal_split(out, threads);
    }

    /// [`Self::fill_normal`] in `threads` parts (one part: on this thread).
    fn fill_normal_split(&mut self, out: &mut [f32], threads: usize) {
        if threads <= 1 || out.len() < 2 {
            return self.fill_normal_here(out);
        }
        // Parts of an even length, so that every part but the last holds whole pairs.
        let part = out.len().div_ceil(threads).next_multiple_of(2);
        let start = self.state;
        let pairs = out.len().div_ceil(2);
        std::thread::scope(|s| {
            for (i, chunk) in out.chunks_mut(part).enumerate() {
                let skip = (i * part) as u64;
                let mut rng = Rng::new(start.wrapping_add(skip.wrapping_mul(GAMMA)));
                s.spawn(move || rng.fill_normal_here(chunk));
            }
        });
        self.state = start.wrapping_add((2 * pairs as u64).wrapping_mul(GAMMA));
    }

    fn fill_normal_here(&mut self, out: &mut [f32]) {
        let mut chunks = out.chunks_exact_mut(2);
        for pair in &mut chunks {
            let (a, b) = self.normal_pair();
            pair[0] = a as f32;
            pair[1] = b as f32;
        }
        if let [last] = chunks.into_remainder() {
            *last = self.normal_pair().0 as f32;
        }
    }

    fn normal_pair(&mut self) -> (f64, f64) {
        // 1 - u lies in (0, 1], so the logarithm is finite.
        let r = (-2.0 * (1.0 - self.uniform()).ln()).sqrt();
        let theta = std::f64::consts::TAU * self.uniform();
        (r * theta.cos(), r * theta.sin())
    }

    /// A float32 tensor of standard normal draws with the given shape.
    pub fn randn(&mut self, shape: &[i64], device: Device) -> Tensor {
        let n: i64 = shape.iter().product();
        let mut buf = vec![0f32; usize::try_from(n).unwrap_or(0)];
        self.fill_normal(&mut buf);
        super::upload(&Tensor::from_slice(&buf).reshape(shape), device).expect("a float32 upload")
    }

    /// An int64 tensor of `n` uniform integers in [0, high).
    pub fn randint(&mut self, high: u64, n: usize, device: Device) -> Tensor {
        let v: Vec<i64> = (0..n).map(|_| self.below(high) as i64).collect();
        super::upload(&Tensor::from_slice(&v), device).expect("an int64 upload")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_seed_same_stream_and_state_resumes() {
        let mut a = Rng::new(42);
        let mut b = Rng::new(42);
        let first: Vec<u64> = (0..5).map(|_| a.next_u64()).collect();
        assert_eq!(first, (0..5).map(|_| b.next_u64()).collect::<Vec<_>>());
        let saved = a;
        let next = a.next_u64();
        let mut resumed = saved;
        assert_eq!(resumed.next_u64(), next);
        assert_ne!(Rng::new(43).next_u64(), Rng::new(42).next_u64());
    }

    #[test]
    fn normals_have_unit_moments() {
        let mut r = Rng::new(7);
        let mut v = vec![0f32; 200_001];
        r.fill_normal(&mut v);
        let n = v.len() as f64;
        let mean = v.iter().map(|&x| f64::from(x)).sum::<f64>() / n;
        let var = v.iter().map(|&x| (f64::from(x) - mean).powi(2)).sum::<f64>() / n;
        // Standard errors: 1/sqrt(n) ~ 0.0022 for the mean, sqrt(2/n) ~ 0.0032 for the variance.
        assert!(mean.abs() < 0.01, "mean {mean}");
        assert!((var - 1.0).abs() < 0.015, "var {var}");
        let tail = v.iter().filter(|&&x| x.abs() > 1.96).count() as f64 / n;
        assert!((tail - 0.05).abs() < 0.003, "two-sided 5% tail {tail}");
    }

    #[test]
    fn a_fill_split_among_threads_is_the_one_thread_fill() {
        // Any number of parts, odd and even lengths, a part shorter than a pair: the same values
        // and the same state afterwards as one thread, whatever this machine's core count.
        for (n, threads) in [(1001usize, 2usize), (1000, 3), (7, 5), (2, 4), (300_001, 4)] {
            let (mut split, mut one) = (Rng::new(11), Rng::new(11));
            let (mut a, mut b) = (vec![0f32; n], vec![0f32; n]);
            split.fill_normal_split(&mut a, threads);
            one.fill_normal_here(&mut b);
            assert!(a == b, "n = {n}, {threads} parts: values differ");
            assert_eq!(split, one, "n = {n}, {threads} parts: state after the fill");
        }
        // And through the public entry point, whichever split it picks here.
        let (mut split, mut one) = (Rng::new(5), Rng::new(5));
        let (mut a, mut b) = (vec![0f32; 262_145], vec![0f32; 262_145]);
        split.fill_normal(&mut a);
        one.fill_normal_here(&mut b);
        assert!(a == b && split == one);
    }

    #[test]
    fn below_is_in_range_and_roughly_uniform() {
        let mut r = Rng::new(1);
        let mut counts = [0u32; 10];
        for _ in 0..100_000 {
            counts[r.below(10) as usize] += 1;
        }
        assert!(counts.iter().all(|&c| (9_500..10_500).contains(&c)), "{counts:?}");
    }
}
