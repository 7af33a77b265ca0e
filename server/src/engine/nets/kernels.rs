//! Elementwise chains fused by hand into one pass over CPU memory (issue 38).
//!
//! At the reward's sizes (a few tens of thousands of elements per tensor) libtorch's cost is
//! per operation, not per element: Mish's slope and curvature are some twenty elementwise
//! operations, each a dispatch, an allocation and a pass, and libtorch's own `mish` takes three
//! transcendental passes. [`mish_parts`] computes Mish with both derivatives, [`mish`] its
//! value alone, in one loop with an exp of its own (a polynomial the compiler vectorises;
//! libm's scalar exp would not be), compiled for each SIMD level (`multiversion`, chosen at
//! run time).
//!
//! The kernels take float32 tensors on the CPU and return `None` for anything else (float64,
//! a GPU tensor, see `elements`), where callers keep their libtorch path; the tests check both
//! paths against autograd.

use multiversion::multiversion;
use tch::{Device, Kind, Tensor};

use crate::error::Result;

/// exp(x) for x in [-87, 88], Cephes' `expf` (range reduction by ln 2 in two parts, a degree-6
/// polynomial): within 2 ulp of the exact value, branch-free and without a float-to-int
/// conversion (whose saturating semantics cost Rust's `as` a factor 2.6 here) so that the loops
/// vectorise.
#[inline(always)]
fn exp_f32(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Round to nearest by adding and removing 1.5 * 2^23 (exact for |v| < 2^22): the sum's low
    // mantissa bits then hold n itself.
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let shifted = x * LOG2E + ROUND;
    let n = shifted - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let mut p = 1.987_569_1e-4_f32;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 0.5;
    let p = p * r * r + r + 1.0;
    // 2^n from its exponent bits: n + 127 in [1, 254] after the clamp.
    let exponent = shifted.to_bits().wrapping_sub(ROUND.to_bits()).wrapping_add(127) << 23;
    p * f32::from_bits(exponent)
}

/// Where Mish's derivatives treat the input as passing through (see `blocks::Mish`): from
/// here on tanh(softplus(x)) is 1 in float32 (it rounds there from x = 9), so mish(x) = x and
/// mish'(x) = 1 exactly, |mish''(x)| under 4e-17 |x|; exp(20) is far from overflowing. The kernels
/// clamp the exp's input here.
pub const MISH_PASS_THROUGH: f64 = 20.0;

/// (e, n, T, 1 / w) of one element: e = exp(min(x, pass)), n = e (e + 2), w = n + 2 and
/// T = n / w = tanh(softplus x). Every kernel computes mish(x) = x T from these same
/// operations, so a value is the same bit for bit whichever kernel produced it.
#[inline(always)]
fn tanh_softplus(x: f32) -> (f32, f32, f32, f32) {
    let e = exp_f32(x.min(MISH_PASS_THROUGH as f32));
    let n = e * (e + 2.0);
    let rw = 1.0 / (n + 2.0);
    (e, n, n * rw, rw)
}

#[multiversion(targets = "simd")]
fn value_loop(a: &[f32], value: &mut [f32]) {
    for (&x, v) in a.iter().zip(value.iter_mut()) {
        let (_, _, tanh, _) = tanh_softplus(x);
        *v = x * tanh;
    }
}

/// mish, mish' = T + x k with k = 4 e (1 + e) / w^2 = (1 - T^2) sigmoid(x).
#[multiversion(targets = "simd")]
fn slope_loop(a: &[f32], value: &mut [f32], slope: &mut [f32]) {
    for ((&x, v), s) in a.iter().zip(value.iter_mut()).zip(slope.iter_mut()) {
        let (e, _, tanh, rw) = tanh_softplus(x);
        *v = x * tanh;
        *s = tanh + x * (4.0 * e * (1.0 + e) * rw * rw);
    }
}

/// mish, mish', and mish'' = k (2 + x (1 - sigmoid(x) (1 + 2 T))), sigmoid(x) = e / (1 + e),
/// without that division: k sigmoid(x) (1 + 2 T) = 4 e^2 (3 n + 2) / w^3, so
/// mish'' = k (2 + x) - 4 x (e^2 / w) ((3 n + 2) / w) / w (grouped so that no factor under- or
/// overflows for x up to the pass-through).
#[multiversion(targets = "simd")]
fn curvature_loop(a: &[f32], value: &mut [f32], slope: &mut [f32], curvature: &mut [f32]) {
    for (((&x, v), s), c) in a.iter().zip(value.iter_mut()).zip(slope.iter_mut()).zip(curvature.iter_mut()) {
        let (e, n, tanh, rw) = tanh_softplus(x);
        let k = 4.0 * e * (1.0 + e) * rw * rw;
        *v = x * tanh;
        *s = tanh + x * k;
        *c = k * (2.0 + x) - 4.0 * x * (e * e * rw) * ((3.0 * n + 2.0) * rw) * rw;
    }
}

/// Above this many elements and [`MAX_THREADS_FOR_KERNEL`] intra-op threads, libtorch's parallel
/// operations beat the single-threaded kernels (see `elements`).
const PARALLEL_ELEMENTS: usize = 1 << 15;
const MAX_THREADS_FOR_KERNEL: i32 = 4;

thread_local! {
    /// Set while a pass is traced into TorchScript ([`with_libtorch_ops`]).
    static LIBTORCH_ONLY: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f` with every kernel here declining (returning `None`), so callers take libtorch's
/// operations: for a pass traced into TorchScript (`engine::export`), where the tracer records
/// libtorch's calls and a kernel's result would be recorded as a constant built from host
/// data. Restores the previous setting however `f` ends.
pub fn with_libtorch_ops<R>(f: impl FnOnce() -> R) -> R {
    super::with_flag_set(&LIBTORCH_ONLY, f)
}

/// What a thread keeps for its kernels: at most this many buffers, of 32 MiB in all (a
/// group-norm backward holds nine at once, half a megabyte each at a ValueFunction's first
/// level); larger buffers are freed.
const POOLED_BUFFERS: usize = 16;
const POOLED_FLOATS: usize = 1 << 23;

thread_local! {
    static POOL: std::cell::RefCell<Vec<Vec<f32>>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// A host buffer of `len` floats from this thread's pool, back to the pool when dropped. The
/// kernels' buffers are a few hundred kilobytes, above glibc's mmap threshold: a fresh `Vec`
/// per call is a fresh mapping, whose page faults and zeroing cost more than the kernel's own
/// arithmetic (a fifth of a ValueFunction gradient's time, measured with perf).
struct Buffer(Vec<f32>);

impl Buffer {
    fn new(len: usize) -> Self {
        let pooled = POOL.with(|pool| {
            let mut pool = pool.borrow_mut();
            // The smallest that fits, so that small requests leave the large buffers alone.
            let fit = (0..pool.len()).filter(|&i| pool[i].capacity() >= len).min_by_key(|&i| pool[i].capacity())?;
            Some(pool.swap_remove(fit))
        });
        let mut values = pooled.unwrap_or_default();
        // Only growth is zero-filled: every user writes all `len` floats before reading any
        // (a copy out of a tensor, a kernel's loop), so a reused buffer's old values are never
        // read.
        values.resize(len, 0.0);
        Self(values)
    }
}

impl std::ops::Deref for Buffer {
    type Target = [f32];
    fn deref(&self) -> &[f32] {
        &self.0
    }
}

impl std::ops::DerefMut for Buffer {
    fn deref_mut(&mut self) -> &mut [f32] {
        &mut self.0
    }
}

impl Drop for Buffer {
    fn drop(&mut self) {
        let values = std::mem::take(&mut self.0);
        // try_with: a buffer dropped while the thread's locals are torn down is freed.
        let _ = POOL.try_with(|pool| {
            let mut pool = pool.borrow_mut();
            let kept: usize = pool.iter().map(Vec::capacity).sum();
            if pool.len() < POOLED_BUFFERS && kept + values.capacity() <= POOLED_FLOATS {
                pool.push(values);
            }
        });
    }
}

/// A float32 CPU tensor's elements in its logical order (one copy; `None` for other kinds or
/// devices, inside [`with_libtorch_ops`], and for large tensors where libtorch runs more than
/// [`MAX_THREADS_FOR_KERNEL`] threads). Copies rather than borrowing libtorch's memory: the
/// workspace forbids `unsafe`, and a copy of a few hundred kilobytes costs less than one of the
/// operations it replaces.
fn elements(t: &Tensor) -> Result<Option<Buffer>> {
    if t.device() != Device::Cpu || t.kind() != Kind::Float || LIBTORCH_ONLY.with(|flag| flag.get()) {
        return Ok(None);
    }
    // The loops run on the calling thread; libtorch's Mish (about 4.6x the kernel's cost per
    // element on one thread) splits a large tensor over its intra-op threads, and wins from
    // five of them on.
    if t.numel() >= PARALLEL_ELEMENTS && tch::get_num_threads() > MAX_THREADS_FOR_KERNEL {
        return Ok(None);
    }
    let numel = t.numel();
    let mut values = Buffer::new(numel);
    t.f_copy_data(&mut values, numel)?;
    Ok(Some(values))
}

fn tensor(values: &[f32], shape: &[i64]) -> Result<Tensor> {
    Ok(Tensor::f_from_slice(values)?.f_view(shape)?)
}

/// mish(a), shaped as `a`, not differentiable: for passes nobody differentiates (`blocks::Mish`
/// takes it when the input needs no gradient). `None` where the kernels decline (`elements`).
pub fn mish(a: &Tensor) -> Result<Option<Tensor>> {
    let Some(input) = elements(a)? else { return Ok(None) };
    let mut value = Buffer::new(input.len());
    value_loop(&input, &mut value);
    Ok(Some(tensor(&value, &a.size())?))
}

/// Mish with its derivatives, each shaped as the input, from one loop.
#[derive(Debug)]
pub struct MishParts {
    /// mish(a), bit for bit [`mish`]'s.
    pub value: Tensor,
    /// mish'(a); 1 above [`MISH_PASS_THROUGH`].
    pub slope: Tensor,
    /// mish''(a) when asked; negligible above [`MISH_PASS_THROUGH`] (under 4e-17 |a|).
    pub curvature: Option<Tensor>,
}

/// [`MishParts`] of `a`; `None` where the kernels decline (`elements`).
pub fn mish_parts(a: &Tensor, second: bool) -> Result<Option<MishParts>> {
    let Some(input) = elements(a)? else { return Ok(None) };
    let shape = a.size();
    let (mut value, mut slope) = (Buffer::new(input.len()), Buffer::new(input.len()));
    let curvature = if second {
        let mut curvature = Buffer::new(input.len());
        curvature_loop(&input, &mut value, &mut slope, &mut curvature);
        Some(tensor(&curvature, &shape)?)
    } else {
        slope_loop(&input, &mut value, &mut slope);
        None
    };
    Ok(Some(MishParts { value: tensor(&value, &shape)?, slope: tensor(&slope, &shape)?, curvature }))
}

/// Sums of a and of a b, with eight accumulators so that the loop vectorises.
#[inline(always)]
fn sums(a: &[f32], b: &[f32]) -> (f32, f32) {
    let (mut s1, mut s2) = ([0.0f32; 8], [0.0f32; 8]);
    let (a8, b8) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (a8.remainder(), b8.remainder());
    for (ca, cb) in a8.zip(b8) {
        for i in 0..8 {
            s1[i] += ca[i];
            s2[i] += ca[i] * cb[i];
        }
    }
    let (mut t1, mut t2) = (s1.iter().sum::<f32>(), s2.iter().sum::<f32>());
    for (&x, &y) in ra.iter().zip(rb) {
        t1 += x;
        t2 += x * y;
    }
    (t1, t2)
}

/// The shapes of one group-norm backward: `groups` per sample, `channels` per sample, `inner`
/// positions per channel.
struct GroupShape {
    groups: usize,
    channels: usize,
    inner: usize,
}

#[multiversion(targets = "simd")]
#[allow(clippy::too_many_arguments)]
fn group_norm_backward_loop(
    shape: &GroupShape,
    g: &[f32],
    slope: &[f32],
    x: &[f32],
    mean: &[f32],
    rstd: &[f32],
    weight: &[f32],
    out: &mut [f32],
) {
    let per_group = shape.channels / shape.groups;
    let span = per_group * shape.inner;
    let mut g_hat = Buffer::new(span);
    let mut x_hat = Buffer::new(span);
    for (block, (m, r)) in mean.iter().zip(rstd).enumerate() {
        let at = block * span;
        let channel0 = (block % shape.groups) * per_group;
        for c in 0..per_group {
            let w = weight[channel0 + c];
            let range = at + c * shape.inner..at + (c + 1) * shape.inner;
            let local = c * shape.inner..(c + 1) * shape.inner;
            for ((((gh, xh), &gi), &si), &xi) in g_hat[local.clone()]
                .iter_mut()
                .zip(&mut x_hat[local])
                .zip(&g[range.clone()])
                .zip(&slope[range.clone()])
                .zip(&x[range])
            {
                *gh = gi * si * w;
                *xh = (xi - m) * r;
            }
        }
        let (s1, s2) = sums(&g_hat, &x_hat);
        let (m1, m2) = (s1 / span as f32, s2 / span as f32);
        for ((o, &gh), &xh) in out[at..at + span].iter_mut().zip(g_hat.iter()).zip(x_hat.iter()) {
            *o = r * (gh - m1 - xh * m2);
        }
    }
}

/// Group norm's input backward behind Mish, d sum(g * mish(group_norm(x))) / dx, in one pass
/// per (sample, group) instead of some ten libtorch operations: with g^ = g mish'(y) weight[c]
/// and x^ = (x - mean) rstd, dx = rstd (g^ - mean(g^) - x^ mean(g^ x^)), the means over the
/// group's channels and positions. `x` [B, C, ...] is the group norm's input, `mean` and `rstd`
/// [B, groups] its statistics (`native_group_norm`'s), `slope` mish' at its output. `None` where
/// the kernels decline (`elements`).
pub fn mish_group_norm_backward(
    g: &Tensor,
    slope: &Tensor,
    x: &Tensor,
    (mean, rstd): (&Tensor, &Tensor),
    weight: &Tensor,
    groups: i64,
) -> Result<Option<Tensor>> {
    let size = x.size();
    let (Some(gv), Some(sv), Some(xv), Some(mv), Some(rv), Some(wv)) =
        (elements(g)?, elements(slope)?, elements(x)?, elements(mean)?, elements(rstd)?, elements(weight)?)
    else {
        return Ok(None);
    };
    let count = |n: i64| usize::try_from(n).unwrap_or(0);
    let shape = GroupShape {
        groups: count(groups),
        channels: count(size[1]),
        inner: size[2..].iter().map(|&n| count(n)).product(),
    };
    let expected = count(size[0]) * shape.channels * shape.inner;
    if shape.groups == 0
        || !shape.channels.is_multiple_of(shape.groups)
        || [gv.len(), sv.len(), xv.len()] != [expected; 3]
        || mv.len() != rv.len()
        || mv.len() * shape.channels / shape.groups * shape.inner != expected
        || wv.len() != shape.channels
    {
        return Err(crate::error::Error::internal("group norm backward", "tensors of mismatched shapes"));
    }
    let mut out = Buffer::new(expected);
    group_norm_backward_loop(&shape, &gv, &sv, &xv, &mv, &rv, &wv, &mut out);
    Ok(Some(tensor(&out, &size)?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_f32_is_within_two_ulp_of_libm() {
        let mut worst = 0.0f64;
        let mut x = -87.0f32;
        while x <= 88.0 {
            let want = f64::from(x).exp();
            let got = f64::from(exp_f32(x));
            worst = worst.max(((got - want) / want).abs());
            x += 0.0137;
        }
        assert!(worst < 2.5 * f64::from(f32::EPSILON), "relative error {worst:e}");
    }

    #[test]
    fn mish_and_its_derivatives_equal_autograd() {
        let a = Tensor::linspace(-30.0, 40.0, 7001, (Kind::Float, Device::Cpu));
        let parts = mish_parts(&a, true).expect("kernel").expect("float32 on the CPU");
        // Autograd's mish, mish' and mish'' in float64, the reference.
        let x = a.to_kind(Kind::Double).set_requires_grad(true);
        let y = x.mish();
        let first = Tensor::run_backward(&[&y.sum(Kind::Double)], &[&x], true, true).pop().expect("first");
        let second = Tensor::run_backward(&[&first.sum(Kind::Double)], &[&x], false, false).pop().expect("second");
        // Relative to max(1, |value|): float32 rounding.
        let close = |got: &Tensor, want: &Tensor, what: &str| {
            let scale = want.abs().clamp_min(1.0);
            let diff = ((got.to_kind(Kind::Double) - want).abs() / scale).max().double_value(&[]);
            assert!(diff < 1e-6, "{what}: max relative difference {diff:e}");
        };
        close(&parts.value, &y.detach(), "mish");
        close(&parts.slope, &first.detach(), "mish'");
        // Above the pass-through the reference is 0 (exactly: under 1e-16; the kernel's under
        // 4e-17 |x|, within the tolerance).
        let curvature = parts.curvature.expect("second");
        close(&curvature, &second.where_self(&x.le(MISH_PASS_THROUGH), &second.zeros_like()), "mish''");
        // Every kernel's value is the same bit for bit; first-derivative parts too.
        assert!(mish(&a).expect("kernel").expect("cpu").equal(&parts.value));
        let first_only = mish_parts(&a, false).expect("kernel").expect("cpu");
        assert!(first_only.value.equal(&parts.value) && first_only.slope.equal(&parts.slope));
        assert!(first_only.curvature.is_none());
        // libtorch's own mish, to float32 rounding.
        close(&parts.value, &a.mish().to_kind(Kind::Double), "mish against libtorch's");
        // Not float32 on the CPU: the caller's path.
        assert!(mish_parts(&a.to_kind(Kind::Double), true).expect("ok").is_none());
        assert!(mish(&a.to_kind(Kind::Double)).expect("ok").is_none());
        // A non-contiguous input is read in its logical order.
        let grid = a.narrow(0, 0, 7000).reshape([70, 100]);
        let transposed = mish(&grid.tr()).expect("kernel").expect("cpu");
        assert_eq!(transposed.size(), vec![100, 70]);
        assert!(transposed.equal(&mish(&grid.tr().contiguous()).expect("kernel").expect("cpu")));
        // Declined inside with_libtorch_ops (tracing), and again after it.
        assert!(with_libtorch_ops(|| mish(&a).expect("ok").is_none() && mish_parts(&a, true).expect("ok").is_none()));
        assert!(mish(&a).expect("kernel").is_some());
        // Empty tensors.
        assert_eq!(mish(&a.narrow(0, 0, 0)).expect("kernel").expect("cpu").numel(), 0);
    }
}

#[cfg(test)]
pub(crate) mod timing {
    use super::*;

    /// Prints the fastest of ten rounds of 100 calls of `f` (after 50 to warm up), in
    /// microseconds per call: the machine's other work only adds time.
    pub(crate) fn best_of(label: &str, f: &mut dyn FnMut()) {
        for _ in 0..50 {
            f();
        }
        let best = (0..10)
            .map(|_| {
                let start = std::time::Instant::now();
                for _ in 0..100 {
                    f();
                }
                start.elapsed().as_secs_f64() * 1e4
            })
            .fold(f64::INFINITY, f64::min);
        eprintln!("{label}: {best:.1} us");
    }

    /// Not a test: each kernel against libtorch's operations on a [256, 128] float32 tensor
    /// (`cargo test --release -p relreward-server --lib time_kernels -- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn time_kernels() {
        tch::set_num_threads(1);
        let time = best_of;
        let a = Tensor::randn([256, 128], (Kind::Float, Device::Cpu));
        time("kernel mish", &mut || drop(mish(&a).expect("kernel")));
        time("kernel mish, mish'", &mut || drop(mish_parts(&a, false).expect("kernel")));
        time("kernel mish, mish', mish''", &mut || drop(mish_parts(&a, true).expect("kernel")));
        time("libtorch mish", &mut || drop(a.mish()));
        // A TemporalUnet block's GroupNorm then Mish at the training benchmark's size.
        let x = Tensor::randn([64, 128, 32], (Kind::Float, Device::Cpu));
        let (w, b) =
            (Tensor::ones([128], (Kind::Float, Device::Cpu)), Tensor::zeros([128], (Kind::Float, Device::Cpu)));
        let norm = |x: &Tensor| x.group_norm(8, Some(&w), Some(&b), 1e-5, false);
        time("libtorch group_norm + libtorch mish [64, 128, 32]", &mut || drop(norm(&x).mish()));
        time("libtorch group_norm + kernel mish [64, 128, 32]", &mut || drop(mish(&norm(&x)).expect("kernel")));
        time("libtorch exp", &mut || drop(a.exp()));
        time("libtorch mul", &mut || drop(&a * &a));
    }
}
